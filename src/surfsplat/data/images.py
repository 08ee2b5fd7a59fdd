"""Image files and encoded bytes <-> float tensors [3, H, W] in [0, 1], with one clear error per bad file.

Decoding goes through Pillow (a dependency of imageio). Every failure names the file (or the
chunk entry) and the reason; nothing is silently replaced.

What is read is the photo as its owner sees it:
- EXIF orientation (tag 0x0112, values 1-8) is applied first, on every decode path (files and
  encoded bytes), by Pillow's `ImageOps.exif_transpose`; `read_image_size` gives the size as
  displayed (width and height swapped for orientations 5-8) from the header alone, and
  `image_orientation` the tag itself. A damaged EXIF block does not stop the decode: the photo is
  read as stored and one warning names the file.
- HEIC/HEIF (recognised by its `ftyp` box, whatever the suffix) through the optional extra
  pillow-heif, whose Pillow opener is registered on first need. libheif applies the container's
  irot/imir transforms itself and pillow-heif then resets the EXIF Orientation tag to 1 (keeping
  the original in `info["original_orientation"]`), so `exif_transpose` never rotates a HEIC twice.
- TIFF alike: Pillow's own TIFF plugin reports the displayed size when it opens a file and turns
  the pixels itself when it decodes them (it calls `exif_transpose` and drops the tag), so for
  HEIF and TIFF the size Pillow gives is the displayed one and nothing is applied again.
"""

from __future__ import annotations

import io
import logging
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

import numpy as np
import torch
from PIL import Image, ImageOps, UnidentifiedImageError
from torch import Tensor

from ..utils.checks import SurfSplatInputError

logger = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".heic", ".heif")
ORIENTATION_TAG = 0x0112  # EXIF / TIFF Orientation (CIPA DC-008): 1 upright, 2-8 the flips and turns below
HEIF_EXTRA = "HEIC/HEIF photos need the optional extra: pip install 'surfsplat[heic]'"
_SELF_ORIENTING = ("HEIF", "TIFF")  # Pillow formats whose opener applies the orientation itself
# Major brands of HEIF still images (ISO/IEC 23008-12): HEVC-coded ones and the generic image brands.
# AVIF ("avif", "avis") is Pillow's own plugin's, not pillow-heif's.
_HEIF_BRANDS = {b"heic", b"heix", b"heim", b"heis", b"hevc", b"hevx", b"hevm", b"hevs", b"mif1", b"msf1"}

# What Pillow raises for unreadable data: unknown format, truncated stream, corrupt chunks.
_DECODE_ERRORS = (UnidentifiedImageError, OSError, SyntaxError, ValueError, Image.DecompressionBombError)
_heif_registered = False
_warned: set[str] = set()  # files whose damaged EXIF block was reported (once a process)
_DAMAGE_KEY = "surfsplat_exif_damage"  # image.info entry: what the opener's EXIF parse warned


def is_heif(head: bytes) -> bool:
    """Whether the first bytes of a file are a HEIF container (an ISO BMFF `ftyp` box with a HEIF brand)."""
    if len(head) < 12 or head[4:8] != b"ftyp":
        return False
    major = head[8:12]
    return major in _HEIF_BRANDS and not (major in (b"mif1", b"msf1") and b"avif" in head[12:64])


def _require_heif(source: str) -> None:
    """pillow-heif's opener registered with Pillow, or the one line that names the extra."""
    global _heif_registered
    try:
        import pillow_heif
    except ImportError:
        raise SurfSplatInputError(f"{source}: {HEIF_EXTRA}") from None
    if not _heif_registered:
        pillow_heif.register_heif_opener()
        _heif_registered = True


@contextmanager
def open_image(stream: BinaryIO | str | Path, source: str, action: str = "read image header") -> Iterator[Image.Image]:
    """Pillow's lazy open (header only) of a file or stream, HEIF included; a file Pillow cannot open
    is one line: "<source>: cannot <action> (<why>)"."""
    try:
        if isinstance(stream, (str, Path)):
            with open(stream, "rb") as f:
                head = f.read(64)
        else:
            head = stream.read(64)
            stream.seek(0)
    except OSError as err:
        raise SurfSplatInputError(f"{source}: cannot {action} ({type(err).__name__}: {err})") from None
    if is_heif(head):
        _require_heif(source)
    try:
        with warnings.catch_warnings(record=True) as caught:  # JPEG's opener parses EXIF for its dpi
            warnings.simplefilter("always")
            image = Image.open(stream)
        damage = _exif_warnings(caught)
        if damage:  # reported with the orientation it leaves (orientation_of)
            image.info[_DAMAGE_KEY] = damage
    except _DECODE_ERRORS as err:
        raise SurfSplatInputError(f"{source}: cannot {action} ({type(err).__name__}: {err})") from None
    with image:
        yield image


def orientation_of(image: Image.Image, source: str) -> int:
    """The EXIF orientation (1-8) that maps the stored pixels to the displayed photo; 1 when absent,
    invalid or unreadable. A damaged EXIF block is one warning naming the file (what Pillow could
    still read of it is used). A PNG's eXIf chunk is read where it precedes the pixels (Pillow reads
    a later one only when decoding them)."""
    reasons = list(image.info.get(_DAMAGE_KEY, ()))  # what the opener's own EXIF parse said
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            value = _orientation_value(image)
        except _DECODE_ERRORS + (TypeError, KeyError, IndexError) as err:
            value = None
            reasons.append(f"{type(err).__name__}: {err}")
    reasons += _exif_warnings(caught)
    orientation = value if isinstance(value, int) and value in range(1, 9) else 1
    if reasons and source not in _warned:  # once per file: its size and its pixels are read apart
        _warned.add(source)
        listed = "; ".join(sorted(set(reasons)))
        outcome = f"its orientation {orientation} is applied" if orientation != 1 else "read without an orientation"
        logger.warning(f"{source}: damaged EXIF block ({listed}); {outcome}")
    return orientation


def _orientation_value(image: Image.Image) -> object:
    if image.format == "HEIF":  # pillow-heif applied it already and reset the tag; the original is kept
        return image.info.get("original_orientation") or 1
    if image.format == "TIFF":  # before decoding; Pillow's decode turns the pixels and drops the tag
        return image.tag_v2.get(ORIENTATION_TAG, 1)
    if image.format == "PNG" and "exif" not in image.info:
        return 1  # Pillow's PngImageFile.getexif() would decode the pixels to look further
    return image.getexif().get(ORIENTATION_TAG, 1)


def _exif_warnings(caught: list[warnings.WarningMessage]) -> list[str]:
    """The messages of Pillow's warnings about an EXIF block it could not parse (its TIFF-IFD reader
    warns them); any other warning is passed on as it was."""
    reasons = []
    for w in caught:
        if w.filename.endswith("TiffImagePlugin.py"):
            reasons.append(str(w.message).strip())
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return reasons


def image_orientation(path: str | Path) -> int:
    """EXIF orientation of a photo, 1-8 (1 when the tag is absent or unreadable), from its header.

    It is the transform from the stored pixels to the photo as displayed, which `read_image` applies
    (see `surfsplat.geometry.orientation` for the camera of each). For a HEIC it is the original EXIF
    tag, which libheif has applied already through the container's irot/imir boxes."""
    with open_image(path, str(path)) as image:
        return orientation_of(image, str(path))


def _displayed_size(image: Image.Image, source: str) -> tuple[int, int]:
    width, height = image.size
    if image.format not in _SELF_ORIENTING and orientation_of(image, source) >= 5:  # a transpose: axes swap
        return height, width
    return width, height


def is_image_file(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES and not path.name.startswith(".")


def list_images(folder: Path) -> list[Path]:
    """Image files of a folder in sorted name order (the order LLFF, DTU and COLMAP tools assume)."""
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: image folder not found")
    return sorted(p for p in folder.iterdir() if is_image_file(p))


def _to_array(image: Image.Image, source: str) -> np.ndarray:
    """Pillow image -> float32 array [H, W, C] in [0, 1] (C = 1, 3 or 4)."""
    if image.mode in ("I;16", "I;16B", "I;16L", "I"):
        raise SurfSplatInputError(
            f"{source}: 16/32-bit single-channel image (mode {image.mode}); expected a colour image"
        )
    if image.mode == "P":
        image = image.convert("RGBA" if "transparency" in image.info else "RGB")
    elif image.mode in ("L", "LA", "RGB", "RGBA"):
        pass
    elif image.mode == "1":
        image = image.convert("L")
    else:
        image = image.convert("RGB")
    arr = np.asarray(image, dtype=np.uint8)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    return arr.astype(np.float32) / 255.0


def _decode(stream: BinaryIO, source: str) -> np.ndarray:
    with open_image(stream, source, "decode image") as image:
        # read from the header, as read_image_size does, so the two always agree; HEIF and TIFF turn themselves
        pending = 1 if image.format in _SELF_ORIENTING else orientation_of(image, source)
        try:
            image.load()  # forces the full decode, so truncation is detected here and not later
            if pending != 1:
                with warnings.catch_warnings(record=True) as caught:  # it parses the EXIF block again
                    warnings.simplefilter("always")
                    image = ImageOps.exif_transpose(image)
                _exif_warnings(caught)  # a damaged block was reported with its orientation; others pass on
            return _to_array(image, source)
        except _DECODE_ERRORS as err:
            raise SurfSplatInputError(f"{source}: cannot decode image ({type(err).__name__}: {err})") from None


def _compose(
    arr: np.ndarray, background: tuple[float, float, float] | None, source: str
) -> tuple[Tensor, Tensor | None]:
    """[H, W, C] array -> (rgb [3, H, W], alpha [1, H, W] or None)."""
    channels = arr.shape[2]
    alpha = None
    if channels in (2, 4):
        alpha = torch.from_numpy(np.ascontiguousarray(arr[:, :, -1:])).permute(2, 0, 1)
        arr = arr[:, :, :-1]
    rgb = torch.from_numpy(np.ascontiguousarray(arr)).permute(2, 0, 1)
    if rgb.shape[0] == 1:
        rgb = rgb.expand(3, -1, -1).clone()
    if alpha is not None:
        if background is None:
            raise SurfSplatInputError(
                f"{source}: image has an alpha channel; pass a background colour to composite it on"
            )
        bg = torch.tensor(background, dtype=rgb.dtype)[:, None, None]
        # Straight (non-premultiplied) alpha, as PNG stores it.
        rgb = rgb * alpha + bg * (1 - alpha)
    return rgb, alpha


def read_image(
    path: str | Path,
    background: tuple[float, float, float] | None = None,
) -> tuple[Tensor, Tensor | None]:
    """Read an image file.

    Returns (rgb [3, H, W] float32 in [0, 1], alpha [1, H, W] or None). An RGBA image is
    composited on `background` (an error when it is None, so transparency is never dropped silently).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: image file not found")
    with path.open("rb") as f:
        arr = _decode(f, str(path))
    return _compose(arr, background, str(path))


def decode_image_bytes(
    data: Tensor | bytes,
    source: str,
    background: tuple[float, float, float] | None = None,
) -> Tensor:
    """Decode an encoded image (a uint8 byte tensor as chunks store it, or bytes) -> [3, H, W] in [0, 1]."""
    if isinstance(data, Tensor):
        if data.dtype != torch.uint8 or data.ndim != 1:
            raise SurfSplatInputError(
                f"{source}: expected encoded image bytes as a 1-D uint8 tensor, got {data.dtype} {tuple(data.shape)}"
            )
        data = data.numpy().tobytes()
    if len(data) == 0:
        raise SurfSplatInputError(f"{source}: empty image data")
    arr = _decode(io.BytesIO(data), source)
    rgb, _ = _compose(arr, background, source)
    return rgb


def read_image_size(path: Path) -> tuple[int, int]:
    """(width, height) of the photo as displayed (EXIF orientations 5-8 swap the stored axes), from
    the file header, without decoding the pixels."""
    with open_image(path, str(path)) as image:
        return _displayed_size(image, str(path))


def image_bytes_size(data: Tensor, source: str) -> tuple[int, int]:
    """(width, height) of encoded image bytes (1-D uint8 tensor) as displayed, from the header only."""
    with open_image(io.BytesIO(data.numpy().tobytes()), source) as image:
        return _displayed_size(image, source)


def encode_image(image: Tensor, image_format: str = "png", quality: int = 95) -> Tensor:
    """[3, H, W] float image in [0, 1] -> encoded bytes as a 1-D uint8 tensor ("png" is lossless after
    8-bit quantization; "jpeg" is what RealEstate10K chunks hold)."""
    if image.ndim != 3 or image.shape[0] != 3:
        raise SurfSplatInputError(f"image: expected shape [3, H, W], got {tuple(image.shape)}")
    arr = (image.detach().float().clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).cpu().numpy()
    buf = io.BytesIO()
    fmt = image_format.lower()
    if fmt == "png":
        Image.fromarray(arr).save(buf, format="PNG")
    elif fmt in ("jpeg", "jpg"):
        Image.fromarray(arr).save(buf, format="JPEG", quality=quality)
    else:
        raise SurfSplatInputError(f"image_format: expected 'png' or 'jpeg', got {image_format!r}")
    return torch.frombuffer(bytearray(buf.getvalue()), dtype=torch.uint8)


def encode_depth_png(depth: Tensor, scale: float = 1000.0) -> Tensor:
    """[H, W] depth (metres) -> 16-bit PNG bytes in units of 1/scale (ScanNet stores millimetres)."""
    if depth.ndim != 2:
        raise SurfSplatInputError(f"depth: expected shape [H, W], got {tuple(depth.shape)}")
    q = (depth.detach().double() * scale).round()
    if bool((q < 0).any()) or bool((q > 65535).any()) or not bool(torch.isfinite(q).all()):
        raise SurfSplatInputError(f"depth: values must lie in [0, {65535 / scale:.3f}] to fit a 16-bit PNG")
    buf = io.BytesIO()
    Image.fromarray(q.to(torch.int32).numpy().astype(np.uint16)).save(buf, format="PNG")
    return torch.frombuffer(bytearray(buf.getvalue()), dtype=torch.uint8)


def decode_depth_png(data: Tensor | bytes, source: str, scale: float = 1000.0) -> Tensor:
    """16-bit PNG depth bytes -> [H, W] float32 metres (0 = no measurement, as in ScanNet)."""
    if isinstance(data, Tensor):
        data = data.numpy().tobytes()
    try:
        with Image.open(io.BytesIO(data)) as image:
            image.load()
            arr = np.asarray(image).astype(np.float32)
    except _DECODE_ERRORS as err:
        raise SurfSplatInputError(f"{source}: cannot decode depth image ({type(err).__name__}: {err})") from None
    if arr.ndim != 2:
        raise SurfSplatInputError(f"{source}: depth image must have one channel, got shape {arr.shape}")
    return torch.from_numpy(arr / scale)
