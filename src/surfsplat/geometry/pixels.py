"""Pixels in the world: the pixel grid a model's output is laid out on, and the pixel footprint.

Every per-pixel surfel output is ordered (view, row, column); `pixel_grid` gives those indices
and `pixel_cells` the same with a block size of one (compaction's cells), `views_of_pixels` the
view of each.

The footprint of a pixel at camera depth z is z / f: the world size one pixel covers there. One
focal convention holds everywhere: f = sqrt(fx fy), the geometric mean, so that footprint^2 is
the area a pixel covers (for square pixels, fx = fy, it is fx). Compaction, the bake for standard
viewers, fusion, training's validation and the closure metrics all use `pixel_footprints`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..utils.checks import SurfSplatInputError
from .cameras import Cameras
from .gaussians import Gaussians


def pixel_grid(views: int, height: int, width: int, device: torch.device | str | None = None) -> Tensor:
    """[V*H*W, 3] int64 (view, row, column) of every pixel, in that order, on `device` (default: the CPU)."""
    v, r, c = torch.meshgrid(
        torch.arange(views, device=device),
        torch.arange(height, device=device),
        torch.arange(width, device=device),
        indexing="ij",
    )
    return torch.stack((v.flatten(), r.flatten(), c.flatten()), dim=-1)


def pixel_cells(views: int, height: int, width: int, device: torch.device | str | None = None) -> Tensor:
    """[V*H*W, 4] the cells of a model's output: (view, row, column, size 1), in (view, row, column) order."""
    grid = pixel_grid(views, height, width, device)
    return torch.cat((grid, torch.ones_like(grid[:, :1])), dim=-1)


def views_of_pixels(views: int, height: int, width: int, device: torch.device | str | None = None) -> Tensor:
    """[V*H*W] the view each surfel of a model output came from ((view, row, column) order)."""
    # output_size given: the length is known, so a device need not report it to the host
    n = height * width
    return torch.arange(views, device=device).repeat_interleave(n, output_size=views * n)


def focal_lengths(K: Tensor) -> Tensor:
    """[...] the focal length in pixels of intrinsics [..., 3, 3]: sqrt(fx fy)."""
    return (K[..., 0, 0] * K[..., 1, 1]).sqrt()


def pixel_footprints(
    gaussians: Gaussians,
    cameras: Cameras,
    width: int | None = None,
    height: int | None = None,
    views: Tensor | None = None,
) -> Tensor:
    """[N] world size z / f of one pixel at each surfel's centre, in the dtype of its means.

    views: [N] index of the camera that sampled each surfel (`views_of_pixels` for model outputs):
    its footprint there (0 behind that camera). None: per surfel, the finest footprint among the
    cameras that see its centre inside their width x height frame (a loaded PLY, a fused scene), or
    the finest among the cameras it is in front of when none does (0 when it is behind them all).
    """
    means = gaussians.means.detach().to(torch.float64)
    w2c = cameras.w2c.to(means)
    K = cameras.K.to(means)
    z = torch.einsum("cj,nj->nc", w2c[:, 2, :3], means) + w2c[:, 2, 3]  # [N, C] camera depths
    footprint = z / focal_lengths(K)
    if views is not None:
        views = views.to(means.device).long()
        if views.shape != (len(gaussians),) or bool((views < 0).any() | (views >= len(cameras)).any()):
            raise SurfSplatInputError(f"views: expected {len(gaussians)} camera indices below {len(cameras)}")
        return footprint.gather(1, views[:, None])[:, 0].clamp_min(0).to(gaussians.means.dtype)
    if width is None or height is None:
        raise SurfSplatInputError("pixel_footprints: give the frame's width and height, or the views")
    cam = torch.einsum("cij,nj->nci", w2c[:, :3, :3], means) + w2c[:, :3, 3]  # [N, C, 3]
    uv = torch.einsum("cij,ncj->nci", K, cam)
    front = z > 1e-9
    u = uv[..., 0] / z.where(front, torch.ones_like(z))
    v = uv[..., 1] / z.where(front, torch.ones_like(z))
    sees = front & (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
    inf = torch.full_like(footprint, float("inf"))
    best = footprint.where(sees, inf).min(1).values
    fallback = footprint.where(front, inf).min(1).values
    out = torch.where(torch.isfinite(best), best, fallback)
    return torch.where(torch.isfinite(out), out, torch.zeros_like(out)).to(gaussians.means.dtype)
