"""Image files and encoded bytes <-> float tensors [3, H, W] in [0, 1], with one clear error per bad file.

Decoding goes through Pillow (a dependency of imageio). Every failure names the file (or the
chunk entry) and the reason; nothing is silently replaced.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError
from torch import Tensor

from ..utils.checks import SurfSplatInputError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")

# What Pillow raises for unreadable data: unknown format, truncated stream, corrupt chunks.
_DECODE_ERRORS = (UnidentifiedImageError, OSError, SyntaxError, ValueError, Image.DecompressionBombError)


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


def _decode(stream: io.BufferedIOBase | io.BytesIO, source: str) -> np.ndarray:
    try:
        with Image.open(stream) as image:
            image.load()  # forces the full decode, so truncation is detected here and not later
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
    """(width, height) from the file header, without decoding the pixels."""
    try:
        with Image.open(path) as image:
            return image.size
    except _DECODE_ERRORS as err:
        raise SurfSplatInputError(f"{path}: cannot read image header ({type(err).__name__}: {err})") from None


def image_bytes_size(data: Tensor, source: str) -> tuple[int, int]:
    """(width, height) of encoded image bytes (1-D uint8 tensor), from the header only."""
    try:
        with Image.open(io.BytesIO(data.numpy().tobytes())) as image:
            return image.size
    except _DECODE_ERRORS as err:
        raise SurfSplatInputError(f"{source}: cannot read image header ({type(err).__name__}: {err})") from None


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
