"""Resize, crop and flip views while keeping their intrinsics exact.

With pixel (row i, column j) centred at (j + 0.5, i + 0.5), resizing an image from W x H to
W' x H' maps every continuous image coordinate u -> u W'/W, v -> v H'/H, so
K' = diag(W'/W, H'/H, 1) K holds exactly (no half-pixel terms). Cropping a window whose top-left
pixel is (row r, column c) shifts the principal point by (-c, -r). The release
(pixelSplat's crop shim) resizes so the target fits, with Pillow's Lanczos filter on 8-bit
images, then centre-crops; `rescale_and_crop` does the same with pixel K kept consistent.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor

from ..utils.checks import SurfSplatInputError, check_tensor

ResizeMethod = Literal["lanczos", "bicubic", "bilinear", "area"]
_FLIP_X = (-1.0, 1.0, 1.0, 1.0)  # mirror of the world x axis: diag(_FLIP_X) (numbers, not a module-level tensor)


def _check_size(name: str, size: tuple[int, int]) -> tuple[int, int]:
    h, w = size
    if int(h) != h or int(w) != w or h < 1 or w < 1:
        raise SurfSplatInputError(f"{name}: expected positive integer (height, width), got {size}")
    return int(h), int(w)


def _lanczos(image: Tensor, size: tuple[int, int]) -> Tensor:
    """Pillow's Lanczos resize of one [3, H, W] image through 8 bits, as the release does."""
    h, w = size
    arr = (image * 255).clamp(0, 255).to(torch.uint8).permute(1, 2, 0).numpy()
    out = Image.fromarray(arr).resize((w, h), Image.LANCZOS)
    return torch.from_numpy(np.asarray(out).astype(np.float32) / 255).permute(2, 0, 1).to(image.dtype)


def resize_views(
    images: Tensor,  # [V, 3, H, W]
    K: Tensor,  # [V, 3, 3]
    size: tuple[int, int],
    method: ResizeMethod = "lanczos",
    depths: Tensor | None = None,  # [V, 1, H, W]
) -> tuple[Tensor, Tensor, Tensor | None]:
    """Resize to size = (height, width); K' = diag(W'/W, H'/H, 1) K. Depth uses nearest
    neighbours (averaging depths across an edge would invent surfaces)."""
    check_tensor("images", images, ("V", 3, None, None))
    check_tensor("K", K, (images.shape[0], 3, 3))
    h, w = _check_size("size", size)
    H, W = images.shape[2:]
    if (h, w) != (H, W):
        if method == "lanczos":
            images = torch.stack([_lanczos(im, (h, w)) for im in images])
        elif method in ("bicubic", "bilinear"):
            images = F.interpolate(images, size=(h, w), mode=method, align_corners=False, antialias=True)
        elif method == "area":
            images = F.interpolate(images, size=(h, w), mode="area")
        else:
            raise SurfSplatInputError(f"method: expected one of lanczos, bicubic, bilinear, area, got {method!r}")
        if depths is not None:
            depths = F.interpolate(depths, size=(h, w), mode="nearest-exact")
    S = torch.tensor([w / W, h / H, 1.0], dtype=K.dtype, device=K.device)
    return images, K * S[:, None], depths


def center_crop(
    images: Tensor,  # [V, 3, H, W]
    K: Tensor,  # [V, 3, 3]
    size: tuple[int, int],
    depths: Tensor | None = None,  # [V, 1, H, W]
) -> tuple[Tensor, Tensor, Tensor | None]:
    """Crop the central (height, width) window; the principal point moves by (-col, -row)."""
    h, w = _check_size("size", size)
    H, W = images.shape[-2:]
    if h > H or w > W:
        raise SurfSplatInputError(f"size: crop {h}x{w} (HxW) is larger than the images ({H}x{W})")
    row, col = (H - h) // 2, (W - w) // 2
    images = images[..., row : row + h, col : col + w]
    if depths is not None:
        depths = depths[..., row : row + h, col : col + w]
    K = K.clone()
    K[..., 0, 2] -= col
    K[..., 1, 2] -= row
    return images, K, depths


@dataclass(frozen=True)
class WorkingCrop:
    """What `rescale_and_crop` does to photos of source_width x source_height: a resize to
    scaled_width x scaled_height, then the window of width x height whose top-left pixel is (top, left)."""

    source_width: int
    source_height: int
    scaled_width: int
    scaled_height: int
    left: int
    top: int
    width: int
    height: int

    def to_dict(self) -> dict:
        return {k: int(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: object, source: str) -> WorkingCrop:
        names = [f.name for f in fields(cls)]
        if not isinstance(data, dict) or set(data) != set(names):
            raise SurfSplatInputError(f"{source}: expected an object with {', '.join(names)}, got {data!r}")
        if not all(isinstance(data[n], int) and not isinstance(data[n], bool) and data[n] >= 0 for n in names):
            raise SurfSplatInputError(f"{source}: every field must be a non-negative integer, got {data!r}")
        crop = cls(**{n: data[n] for n in names})
        if crop != working_crop(crop.source_width, crop.source_height, (crop.height, crop.width)):
            raise SurfSplatInputError(
                f"{source}: {crop.width}x{crop.height} is not the working crop of "
                f"{crop.source_width}x{crop.source_height} photos (rescale_and_crop)"
            )
        return crop

    def uncrop(self, K: Tensor) -> Tensor:
        """K [..., 3, 3] in pixels of the crop -> K in pixels of the source photos (the inverse of the crop)."""
        K = K.clone()
        K[..., 0, 2] += self.left
        K[..., 1, 2] += self.top
        S = torch.tensor(
            [self.source_width / self.scaled_width, self.source_height / self.scaled_height, 1.0],
            dtype=K.dtype,
            device=K.device,
        )
        return K * S[:, None]


def working_crop(width: int, height: int, shape: tuple[int, int]) -> WorkingCrop:
    """The resize and window `rescale_and_crop` applies to width x height photos for shape = (height, width)."""
    h, w = _check_size("shape", shape)
    scale = max(h / height, w / width)
    sh, sw = max(h, round(height * scale)), max(w, round(width * scale))
    return WorkingCrop(int(width), int(height), int(sw), int(sh), (sw - w) // 2, (sh - h) // 2, w, h)


def rescale_and_crop(
    images: Tensor,  # [V, 3, H, W]
    K: Tensor,  # [V, 3, 3]
    shape: tuple[int, int],
    method: ResizeMethod = "lanczos",
    depths: Tensor | None = None,  # [V, 1, H, W]
) -> tuple[Tensor, Tensor, Tensor | None]:
    """The release's crop shim with exact pixel K: scale by max(h/H, w/W) (rounded sizes, K
    scaled by the realised per-axis factors), then centre-crop to shape = (height, width)."""
    H, W = images.shape[-2:]
    crop = working_crop(W, H, shape)
    images, K, depths = resize_views(images, K, (crop.scaled_height, crop.scaled_width), method, depths)
    return center_crop(images, K, (crop.height, crop.width), depths)


def horizontal_flip(
    images: Tensor,  # [V, 3, H, W]
    c2w: Tensor,  # [V, 4, 4]
    K: Tensor,  # [V, 3, 3]
) -> tuple[Tensor, Tensor, Tensor]:
    """Mirror views left-right together with their cameras (the release's flip augmentation).

    The world is mirrored by M = diag(-1, 1, 1) (c2w' = M c2w M keeps a rotation); a pixel at
    image coordinate u then appears at W - u, so cx' = W - cx and the skew changes sign.
    """
    W = images.shape[-1]
    flip = c2w.new_tensor(_FLIP_X).diag()
    K = K.clone()
    K[..., 0, 2] = W - K[..., 0, 2]
    K[..., 0, 1] = -K[..., 0, 1]
    return images.flip(-1), flip @ c2w @ flip, K
