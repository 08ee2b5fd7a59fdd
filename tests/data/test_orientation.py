"""Photos read as their owner sees them: EXIF orientations 1-8 on every decode path and format that
carries the tag (PNG, lossless WebP, TIFF exactly; JPEG at quality 100 within a tolerance), HEIC
through pillow-heif (never turned twice), one clear line without the extra, and a damaged EXIF block.

The stored images are made from the upright one with numpy, from the tag's definition in CIPA
DC-008 (where the stored image's row 0 and column 0 lie in the displayed photo), not through Pillow,
so a wrong transform in the reader (or one applied twice) fails."""

from __future__ import annotations

import io
import logging
import struct
import sys

import numpy as np
import pytest
import torch
from PIL import Image

from surfsplat.data.images import (
    HEIF_EXTRA,
    decode_image_bytes,
    image_bytes_size,
    image_orientation,
    is_image_file,
    read_image,
    read_image_size,
)
from surfsplat.utils.checks import SurfSplatInputError

ORIENTATIONS = range(1, 9)


def upright(height: int = 16, width: int = 24, block: int = 1, seed: int = 0) -> np.ndarray:
    """An asymmetric uint8 [H, W, 3] image: random colours in block x block squares (no symmetry
    maps it onto itself, so every wrong turn or flip changes it)."""
    rng = np.random.default_rng(seed)
    cells = rng.integers(0, 256, (height // block, width // block, 3), dtype=np.uint8)
    return np.kron(cells, np.ones((block, block, 1), dtype=np.uint8))


def stored_from_upright(image: np.ndarray, orientation: int) -> np.ndarray:
    """The pixels a camera stores with this tag for a photo displayed as `image` (CIPA DC-008 Table:
    the stored row 0 / column 0 are the displayed photo's 1 top/left, 2 top/right, 3 bottom/right,
    4 bottom/left, 5 left/top, 6 right/top, 7 right/bottom, 8 left/bottom)."""
    U = image
    return {
        1: U,
        2: U[:, ::-1],
        3: U[::-1, ::-1],
        4: U[::-1, :],
        5: U.transpose(1, 0, 2),  # stored row i = displayed column i, read top to bottom
        6: U[:, ::-1].transpose(1, 0, 2),  # stored row i = displayed column W-1-i, top to bottom
        7: U[::-1, ::-1].transpose(1, 0, 2),  # stored row i = displayed column W-1-i, bottom to top
        8: U[::-1, :].transpose(1, 0, 2),  # stored row i = displayed column i, bottom to top
    }[orientation].copy()


def _exif(orientation: int) -> bytes:
    exif = Image.Exif()
    exif[0x0112] = orientation
    return exif.tobytes()


def _save(path, array: np.ndarray, orientation: int, fmt: str, **options) -> None:
    Image.fromarray(array).save(path, fmt, exif=_exif(orientation), **options)


def _as_uint8(rgb: torch.Tensor) -> np.ndarray:
    return (rgb.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)


def test_convention_stored_images_differ_for_every_orientation():
    """The fixture can fail: the eight stored images of one upright photo are eight different arrays."""
    U = upright()
    stored = [stored_from_upright(U, o).tobytes() + bytes(stored_from_upright(U, o).shape) for o in ORIENTATIONS]
    assert len(set(stored)) == 8


@pytest.mark.parametrize("orientation", ORIENTATIONS)
@pytest.mark.parametrize("fmt, suffix, options", [("PNG", "png", {}), ("WEBP", "webp", {"lossless": True})])
def test_lossless_photo_with_orientation_reads_upright_exactly(tmp_path, orientation, fmt, suffix, options):
    U = upright()
    path = tmp_path / f"photo.{suffix}"
    _save(path, stored_from_upright(U, orientation), orientation, fmt, **options)
    rgb, _ = read_image(path)
    np.testing.assert_array_equal(_as_uint8(rgb), U)
    assert read_image_size(path) == (U.shape[1], U.shape[0])  # (width, height) as displayed
    assert image_orientation(path) == orientation


@pytest.mark.parametrize("orientation", ORIENTATIONS)
def test_tiff_with_orientation_reads_upright_exactly_and_is_turned_once(tmp_path, orientation):
    """Pillow's TIFF plugin turns the pixels itself when it decodes them: nothing is applied twice."""
    U = upright()
    path = tmp_path / "photo.tif"
    Image.fromarray(stored_from_upright(U, orientation)).save(path, "TIFF", tiffinfo={0x0112: orientation})
    assert image_orientation(path) == orientation
    assert read_image_size(path) == (U.shape[1], U.shape[0])
    rgb, _ = read_image(path)
    np.testing.assert_array_equal(_as_uint8(rgb), U)


@pytest.mark.parametrize("orientation", ORIENTATIONS)
def test_encoded_bytes_with_orientation_decode_upright(orientation):
    U = upright()
    buffer = io.BytesIO()
    _save(buffer, stored_from_upright(U, orientation), orientation, "PNG")
    data = torch.frombuffer(bytearray(buffer.getvalue()), dtype=torch.uint8)
    np.testing.assert_array_equal(_as_uint8(decode_image_bytes(data, "chunk[0]")), U)
    assert image_bytes_size(data, "chunk[0]") == (U.shape[1], U.shape[0])


@pytest.mark.parametrize("orientation", ORIENTATIONS)
def test_jpeg_quality_100_with_orientation_reads_upright(tmp_path, orientation):
    """As phones write them: 8x8 blocks of one colour at 4:4:4, so JPEG's loss stays far below the
    difference any wrong orientation makes (checked: every other reading is far off)."""
    U = upright(32, 48, block=8)
    stored = stored_from_upright(U, orientation)
    path = tmp_path / "photo.jpg"
    _save(path, stored, orientation, "JPEG", quality=100, subsampling=0)
    got = _as_uint8(read_image(path)[0]).astype(int)
    assert np.abs(got - U).max() <= 8
    for other in ORIENTATIONS:  # the stored pixels read under any other tag are far from upright
        candidate = _undo(stored, other)
        if other != orientation and candidate.shape == U.shape:
            assert np.abs(candidate.astype(int) - U).mean() > 20


def _undo(stored: np.ndarray, orientation: int) -> np.ndarray:
    """The displayed photo of stored pixels under a tag (the inverse of stored_from_upright)."""
    for_shape = stored.transpose(1, 0, 2) if orientation >= 5 else stored
    basis = np.arange(for_shape.shape[0] * for_shape.shape[1]).reshape(for_shape.shape[:2])
    index = stored_from_upright(basis[:, :, None], orientation)[:, :, 0]
    out = np.empty(for_shape.shape, stored.dtype)  # C order: the flat view below writes into it
    out.reshape(-1, 3)[index.reshape(-1)] = stored.reshape(-1, 3)
    return out


def test_undo_inverts_the_fixture():
    U = upright()
    for orientation in ORIENTATIONS:
        np.testing.assert_array_equal(_undo(stored_from_upright(U, orientation), orientation), U)


def test_displayed_size_comes_from_the_header_without_decoding(tmp_path):
    """A JPEG cut off after its header and first scan bytes: its displayed size and orientation still
    read (nothing but the header is looked at), while decoding its pixels is one clear error."""
    U = upright(32, 48, block=8)
    buffer = io.BytesIO()
    _save(buffer, stored_from_upright(U, 6), 6, "JPEG", quality=100)
    path = tmp_path / "cut.jpg"
    path.write_bytes(buffer.getvalue()[:700])
    assert read_image_size(path) == (48, 32) and image_orientation(path) == 6
    with pytest.raises(SurfSplatInputError, match="cut.jpg: cannot decode image"):
        read_image(path)


def test_invalid_orientation_value_reads_as_stored(tmp_path):
    U = upright()
    path = tmp_path / "nine.png"
    _save(path, U, 9, "PNG")
    np.testing.assert_array_equal(_as_uint8(read_image(path)[0]), U)
    assert image_orientation(path) == 1


def test_damaged_exif_block_still_decodes_with_one_warning(tmp_path, caplog):
    U = upright(16, 24, block=8)
    buffer = io.BytesIO()
    Image.fromarray(U).save(buffer, "JPEG", quality=100, subsampling=0)
    # an APP1 "Exif" segment whose TIFF header says one entry follows, then stops after 4 bytes
    payload = b"Exif\x00\x00MM\x00\x2a\x00\x00\x00\x08\x00\x05\x01\x12\x00\x03"
    data = buffer.getvalue()
    path = tmp_path / "broken_exif.jpg"
    path.write_bytes(data[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + data[2:])
    clean = decode_image_bytes(data, "clean")
    with caplog.at_level(logging.WARNING, logger="surfsplat"):
        rgb, _ = read_image(path)
        assert read_image_size(path) == (24, 16)
    assert torch.equal(rgb, clean)  # the pixels are the same photo's, read as stored
    warned = [r.getMessage() for r in caplog.records if "damaged EXIF block" in r.getMessage()]
    assert len(warned) == 1 and str(path) in warned[0], warned


def test_damaged_exif_block_with_a_readable_orientation_applies_it_and_says_so(tmp_path, caplog):
    """An IFD whose second entry points past the block's end: Pillow still reads Orientation 6 and warns
    'Truncated File Read'; the photo is turned and the warning says the orientation was applied."""
    U = upright(16, 24, block=8)
    buffer = io.BytesIO()
    Image.fromarray(stored_from_upright(U, 6)).save(buffer, "JPEG", quality=100, subsampling=0)
    ifd = struct.pack("<H", 2) + struct.pack("<HHII", 0x0112, 3, 1, 6) + struct.pack("<HHII", 0x010E, 2, 100, 0x1000)
    payload = b"Exif\x00\x00II*\x00" + struct.pack("<I", 8) + ifd + struct.pack("<I", 0)
    data = buffer.getvalue()
    path = tmp_path / "partial_exif.jpg"
    path.write_bytes(data[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + data[2:])
    with caplog.at_level(logging.WARNING, logger="surfsplat"):
        assert image_orientation(path) == 6
        got = _as_uint8(read_image(path)[0]).astype(int)
    assert got.shape == U.shape and np.abs(got - U).max() <= 8
    warned = [r.getMessage() for r in caplog.records if "damaged EXIF block" in r.getMessage()]
    assert warned == [f"{path}: damaged EXIF block (Truncated File Read); its orientation 6 is applied"]


# ----------------------------------------------------------------------------------------- HEIC
def _heif_or_skip():
    return pytest.importorskip("pillow_heif", reason="pillow-heif (the 'heic' extra) is not installed")


@pytest.mark.parametrize("orientation", ORIENTATIONS)
def test_heic_with_orientation_reads_upright_once(tmp_path, orientation):
    """pillow-heif writes the tag as irot/imir boxes, libheif applies them when decoding and the EXIF
    tag is reset to 1: the photo comes out upright, turned once (lossless HEVC, within YCbCr rounding)."""
    pillow_heif = _heif_or_skip()
    pillow_heif.register_heif_opener()
    U = upright(32, 48)
    path = tmp_path / "photo.heic"
    stored = Image.fromarray(stored_from_upright(U, orientation))
    stored.save(path, "HEIF", exif=_exif(orientation), quality=-1, chroma=444)
    assert is_image_file(path)
    assert image_orientation(path) == orientation
    assert read_image_size(path) == (48, 32)
    got = _as_uint8(read_image(path)[0]).astype(int)
    assert got.shape == U.shape
    assert np.abs(got - U).max() <= 2  # measured 1: lossless HEVC of YCbCr, not of RGB


def test_heic_without_the_extra_is_one_line_naming_it(tmp_path, monkeypatch):
    path = tmp_path / "IMG_0001.HEIC"
    path.write_bytes(b"\x00\x00\x00\x18ftypheic\x00\x00\x00\x00mif1heic" + bytes(64))  # the header decides
    monkeypatch.setitem(sys.modules, "pillow_heif", None)  # import pillow_heif now raises ImportError
    for read in (read_image, read_image_size, image_orientation):
        with pytest.raises(SurfSplatInputError) as err:
            read(path)
        assert str(err.value) == f"{path}: {HEIF_EXTRA}"
    assert HEIF_EXTRA == "HEIC/HEIF photos need the optional extra: pip install 'surfsplat[heic]'"
