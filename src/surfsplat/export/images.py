"""Writing renders as PNG images: colour, depth (colour-mapped) and normal maps."""

from __future__ import annotations

import os
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
from torch import Tensor

from ..utils.atomic import atomic_path


def to_uint8(image: Tensor) -> np.ndarray:
    """[3, H, W] or [1, H, W] in [0, 1] -> [H, W, 3] uint8."""
    img = image.detach().float().clamp(0, 1).cpu()
    if img.shape[0] == 1:
        img = img.expand(3, -1, -1)
    return (img.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)


def colorize_depth(
    depth: Tensor, alpha: Tensor | None = None, near: float | None = None, far: float | None = None
) -> Tensor:
    """Depth [1, H, W] -> [3, H, W]: near yellow, far blue (inverse depth, robust range), black where empty."""
    d = depth.detach().float()[0]
    valid = d > 0 if alpha is None else (alpha.detach()[0] > 0.5) & (d > 0)
    inv = torch.where(valid, 1 / d.clamp_min(1e-6), torch.zeros_like(d))
    if valid.any():
        vals = inv[valid]
        lo = 1 / far if far else float(torch.quantile(vals, 0.01))
        hi = 1 / near if near else float(torch.quantile(vals, 0.99))
        t = ((inv - lo) / max(hi - lo, 1e-12)).clamp(0, 1)
    else:
        t = torch.zeros_like(d)
    # A short piecewise-linear ramp: dark blue -> teal -> green -> yellow.
    stops = d.new_tensor([[0.15, 0.10, 0.45], [0.10, 0.45, 0.60], [0.35, 0.75, 0.35], [0.98, 0.90, 0.15]])
    x = t * (len(stops) - 1)
    i = x.floor().long().clamp(max=len(stops) - 2)
    f = (x - i)[..., None]
    rgb = stops[i] * (1 - f) + stops[i + 1] * f
    rgb = torch.where(valid[..., None], rgb, torch.zeros_like(rgb))
    return rgb.permute(2, 0, 1)


def colorize_error(error: Tensor, valid: Tensor | None = None, vmax: float = 1.0) -> Tensor:
    """Error [1, H, W] >= 0 -> [3, H, W]: black at 0, through red and orange to yellow at vmax and
    above; pixels outside `valid` ([1, H, W] bool) are dark grey, so "no data" never reads as "no error"."""
    e = (error.detach().float()[0] / vmax).clamp(0, 1)
    stops = e.new_tensor([[0.0, 0.0, 0.0], [0.75, 0.05, 0.05], [1.0, 0.55, 0.0], [1.0, 0.95, 0.3]])
    x = e * (len(stops) - 1)
    i = x.floor().long().clamp(max=len(stops) - 2)
    f = (x - i)[..., None]
    rgb = stops[i] * (1 - f) + stops[i + 1] * f
    if valid is not None:
        rgb = torch.where(valid.detach()[0][..., None], rgb, torch.full_like(rgb, 0.22))
    return rgb.permute(2, 0, 1)


def normal_to_rgb(normal: Tensor) -> Tensor:
    """Unit normals [3, H, W] in [-1, 1] -> [0, 1] colours (zero normals stay black)."""
    n = normal.detach().float()
    empty = n.norm(dim=0, keepdim=True) < 1e-6
    return torch.where(empty, torch.zeros_like(n), (n * 0.5 + 0.5).clamp(0, 1))


def write_png(path: str | os.PathLike, image: Tensor) -> Path:
    """Write [3|1, H, W] in [0, 1] atomically."""
    path = Path(path)
    with atomic_path(path, suffix=".png") as tmp:  # imageio picks the format from the suffix
        iio.imwrite(tmp, to_uint8(image))
    return path
