"""TensorBoard event files (scalars and images) without TensorBoard or protobuf installed.

`tensorboard --logdir <out_dir>/tensorboard` reads what `EventWriter` writes. The format is small
and stable, so it is written here directly instead of adding TensorBoard (and its protobuf and
gRPC stack) to the package's dependencies:

- a file `events.out.tfevents.<time>.<host>` holds records: little-endian uint64 length, the
  masked CRC-32C of those 8 bytes, the payload, the masked CRC-32C of the payload;
- each payload is a serialized `tensorflow.Event` protobuf: wall_time (field 1, double), step
  (2, int64), file_version (3, string, first record only) or summary (5); a Summary holds
  Values with tag (1), simple_value (2, float) or image (4: height 1, width 2, colorspace 3,
  encoded PNG 4).
"""

from __future__ import annotations

import io
import socket
import struct
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
from torch import Tensor

from ..checks import SurfSplatInputError, check_tensor

_CRC32C_POLY = 0x82F63B78  # Castagnoli polynomial, bit-reversed (as TFRecord uses it)
_CRC_MASK_DELTA = 0xA282EAD8  # TFRecord's CRC masking constant


def _crc_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ _CRC32C_POLY if crc & 1 else crc >> 1
        table.append(crc)
    return table


_TABLE = _crc_table()


def crc32c(data: bytes) -> int:
    """CRC-32C (Castagnoli) of `data`; crc32c(b"123456789") == 0xE3069283."""
    crc = 0xFFFFFFFF
    table = _TABLE
    for byte in data:
        crc = table[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


def masked_crc32c(data: bytes) -> int:
    """TFRecord's masked CRC: rotate right by 15 bits and add a constant (mod 2^32)."""
    crc = crc32c(data)
    return (((crc >> 15) | (crc << 17)) + _CRC_MASK_DELTA) & 0xFFFFFFFF


# ------------------------------------------------------------------------------ protobuf encoding
def _varint(value: int) -> bytes:
    if value < 0:
        value += 1 << 64  # two's complement, as protobuf encodes negative int64
    out = bytearray()
    while True:
        bits = value & 0x7F
        value >>= 7
        if value:
            out.append(bits | 0x80)
        else:
            out.append(bits)
            return bytes(out)


def _key(field: int, wire_type: int) -> bytes:
    return _varint(field << 3 | wire_type)


def _bytes_field(field: int, payload: bytes) -> bytes:
    return _key(field, 2) + _varint(len(payload)) + payload


def _event(wall_time: float, step: int, *, file_version: str | None = None, summary: bytes | None = None) -> bytes:
    out = _key(1, 1) + struct.pack("<d", wall_time) + _key(2, 0) + _varint(step)
    if file_version is not None:
        out += _bytes_field(3, file_version.encode())
    if summary is not None:
        out += _bytes_field(5, summary)
    return out


def _scalar_value(tag: str, value: float) -> bytes:
    return _bytes_field(1, _bytes_field(1, tag.encode()) + _key(2, 5) + struct.pack("<f", value))


def _image_value(tag: str, png: bytes, height: int, width: int, channels: int) -> bytes:
    image = (
        _key(1, 0)
        + _varint(height)
        + _key(2, 0)
        + _varint(width)
        + _key(3, 0)
        + _varint(channels)
        + _bytes_field(4, png)
    )
    return _bytes_field(1, _bytes_field(1, tag.encode()) + _bytes_field(4, image))


def record(payload: bytes) -> bytes:
    """One TFRecord: length, its masked CRC, payload, its masked CRC."""
    length = struct.pack("<Q", len(payload))
    return length + struct.pack("<I", masked_crc32c(length)) + payload + struct.pack("<I", masked_crc32c(payload))


def encode_png(image: Tensor) -> bytes:
    """[3, H, W] (or [1, H, W]) float image in [0, 1] -> 8-bit PNG bytes (values clamped)."""
    check_tensor("image", image, (None, "H", "W"), finite=False)
    if image.shape[0] not in (1, 3):
        raise SurfSplatInputError(f"image: expected 1 or 3 channels, got {image.shape[0]}")
    array = (image.detach().float().clamp(0, 1) * 255 + 0.5).to(torch.uint8).permute(1, 2, 0).cpu().numpy()
    if array.shape[2] == 1:
        array = array[:, :, 0]
    buffer = io.BytesIO()
    iio.imwrite(buffer, np.ascontiguousarray(array), extension=".png")
    return buffer.getvalue()


class EventWriter:
    """Appends scalars and images to one new event file in `log_dir`."""

    def __init__(self, log_dir: str | Path) -> None:
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        now = time.time()
        self.path = self.log_dir / f"events.out.tfevents.{int(now)}.{socket.gethostname()}"
        self._file = open(self.path, "ab")
        self._write(_event(now, 0, file_version="brain.Event:2"))

    def _write(self, payload: bytes) -> None:
        self._file.write(record(payload))

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        # NaN and inf are written as they are: TensorBoard shows them, so a diverging run is visible.
        self._write(_event(time.time(), step, summary=_scalar_value(tag, float(value))))

    def add_scalars(self, values: dict[str, float], step: int) -> None:
        summary = b"".join(_scalar_value(tag, float(v)) for tag, v in values.items())
        self._write(_event(time.time(), step, summary=summary))

    def add_image(self, tag: str, image: Tensor, step: int) -> None:
        """image: [3, H, W] or [1, H, W] in [0, 1]."""
        png = encode_png(image)
        c, h, w = image.shape
        self._write(_event(time.time(), step, summary=_image_value(tag, png, h, w, c)))

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        if not self._file.closed:
            self._file.flush()
            self._file.close()
