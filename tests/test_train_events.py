"""TensorBoard event files: CRC-32C, TFRecord framing and the Event protobuf, decoded independently."""

from __future__ import annotations

import io
import struct
import zlib

import imageio.v3 as iio
import pytest
import torch

from surfsplat.train.events import EventWriter, crc32c, masked_crc32c


def test_crc32c_known_answers() -> None:
    # RFC 3720 (iSCSI) test vectors and the classic check value.
    assert crc32c(b"123456789") == 0xE3069283
    assert crc32c(bytes(32)) == 0x8A9136AA
    assert crc32c(bytes([0xFF] * 32)) == 0x62A8AB43
    assert crc32c(bytes(range(32))) == 0x46DD794E
    assert crc32c(b"123456789") != zlib.crc32(b"123456789")  # not the zlib polynomial


def _read_records(data: bytes) -> list[bytes]:
    out, pos = [], 0
    while pos < len(data):
        (length,) = struct.unpack_from("<Q", data, pos)
        (length_crc,) = struct.unpack_from("<I", data, pos + 8)
        assert length_crc == masked_crc32c(data[pos : pos + 8])
        payload = data[pos + 12 : pos + 12 + length]
        (payload_crc,) = struct.unpack_from("<I", data, pos + 12 + length)
        assert payload_crc == masked_crc32c(payload)
        out.append(payload)
        pos += 16 + length
    assert pos == len(data)
    return out


def _fields(message: bytes) -> list[tuple[int, object]]:
    """A minimal protobuf wire-format reader: (field number, value) in order."""
    out, pos = [], 0

    def varint() -> int:
        nonlocal pos
        shift = result = 0
        while True:
            byte = message[pos]
            pos += 1
            result |= (byte & 0x7F) << shift
            shift += 7
            if not byte & 0x80:
                return result

    while pos < len(message):
        key = varint()
        field, wire = key >> 3, key & 7
        if wire == 0:
            out.append((field, varint()))
        elif wire == 1:
            out.append((field, struct.unpack_from("<d", message, pos)[0]))
            pos += 8
        elif wire == 5:
            out.append((field, struct.unpack_from("<f", message, pos)[0]))
            pos += 4
        elif wire == 2:
            n = varint()
            out.append((field, message[pos : pos + n]))
            pos += n
        else:
            raise AssertionError(f"unexpected wire type {wire}")
    return out


def dict_of(fields: list[tuple[int, object]]) -> dict[int, object]:
    return dict(fields)


def test_scalars_and_images_decode(tmp_path) -> None:
    writer = EventWriter(tmp_path)
    writer.add_scalars({"loss/total": 0.25, "train/lr": 2e-4}, step=7)
    writer.add_scalar("val/x1/psnr", 21.5, step=300)
    torch.manual_seed(0)
    image = torch.rand(3, 5, 6)
    writer.add_image("train/grid", image, step=300)
    writer.close()
    assert writer.path.name.startswith("events.out.tfevents.")

    events = [dict_of(_fields(r)) for r in _read_records(writer.path.read_bytes())]
    assert events[0][3] == b"brain.Event:2"  # file_version first
    scalars, image_events = [], []
    for event in events[1:]:
        for _, value in _fields(event[5]):
            v = dict_of(_fields(value))
            if 2 in v:
                scalars.append((event[2], v[1].decode(), v[2]))
            else:
                image_events.append((event[2], v[1].decode(), dict_of(_fields(v[4]))))
    assert scalars == [
        (7, "loss/total", 0.25),
        (7, "train/lr", pytest.approx(2e-4, rel=1e-7)),
        (300, "val/x1/psnr", 21.5),
    ]
    ((step, tag, img),) = image_events
    assert (step, tag, img[1], img[2], img[3]) == (300, "train/grid", 5, 6, 3)
    decoded = torch.from_numpy(iio.imread(io.BytesIO(img[4]), extension=".png")).permute(2, 0, 1)
    assert torch.equal(decoded, (image * 255 + 0.5).to(torch.uint8))
