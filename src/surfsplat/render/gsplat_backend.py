"""CUDA backend through the gsplat library (optional extra: pip install 'surfsplat[gsplat]').

One function on every backend: the projection is this project's own (`torch_backend.project_*`,
differentiable through autograd, the same code as the torch backend), and gsplat supplies what
runs per pixel - tile intersection (`isect_tiles`, `isect_offset_encode`) and the rasterization
kernels (`rasterize_to_pixels_2dgs` for surfels, `rasterize_to_pixels` for EWA). gsplat's own
projection is not used, so its conventions do not leak in: the surfel low-pass term is centred
where `RenderConventions.lowpass_center_sigma` says, the EWA Jacobian is clamped and the footprint
supported as `ewa_jacobian_clamp` / `ewa_support` say, and a surfel whose footprint crosses the
camera plane is listed in every tile it reaches. Each Gaussian's tiles come from the same pixel
box as on the other backends; the kernels test every pixel of those tiles against the alpha
threshold, so the box only bounds the work.

Differences that remain by design (gsplat's kernels, not configurable):
- depth: gsplat blends a per-Gaussian value, so the "surfel" depth map is the blended centre depth
  (camera z of each surfel's centre), not the ray-splat intersection depth of the other backends;
  the two agree exactly for fronto-parallel surfels and differ by at most a surfel's extent in depth.
- alpha cap: 0.999 in gsplat's kernels, 0.99 here; it binds only where opacity exceeds 0.99
  (SurfSplat's adapter caps opacity at 0.6).
- precision: the kernels compute in float32.
Colours (SH per camera) and camera-facing normals are blended as feature channels, computed
exactly as the torch backend computes them. Forced-alpha normalization and the background are
applied by the caller, identically for every backend.
"""

from __future__ import annotations

from dataclasses import fields

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from .torch_backend import Projected, TorchRenderSettings, project
from .types import RenderConventions, RenderMode

TILE = 16  # gsplat's tile edge in pixels


def _kernels():
    """gsplat's CUDA entry points (one module, so tests can swap in gsplat's pure-PyTorch references)."""
    from gsplat.cuda import _wrapper

    return _wrapper


def tile_boxes(pixel_box: Tensor) -> tuple[Tensor, Tensor]:
    """Centres [M, 2] and integer radii [M, 2] whose gsplat tiles are exactly those the pixel boxes touch.

    gsplat lists a Gaussian in tiles floor((m - r) / 16) up to, exclusive, ceil((m + r) / 16). The
    tile-aligned range [L, R) around an inclusive box has m = (L + R) / 2 and r = (R - L) / 2 (a
    multiple of 8), so no neighbouring tile is added: for "ewa" with the release support, whose
    boxes are whole 16-pixel tiles, that is the release's own tile set.
    """
    lo = torch.div(pixel_box[:, [0, 2]], TILE, rounding_mode="floor") * TILE
    hi = (torch.div(pixel_box[:, [1, 3]], TILE, rounding_mode="floor") + 1) * TILE
    return (0.5 * (lo + hi)).to(torch.float32), torch.div(hi - lo, 2, rounding_mode="floor").to(torch.int32)


def render_gsplat(
    g: Gaussians,
    cameras: Cameras,
    width: int,
    height: int,
    mode: RenderMode,
    conventions: RenderConventions | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Un-normalized colour [C, 3, H, W], alpha [C, 1, H, W], depth [C, 1, H, W], normal [C, 3, H, W]."""
    rules = conventions or RenderConventions()
    settings = TorchRenderSettings(**{f.name: getattr(rules, f.name) for f in fields(RenderConventions)})
    w2c = cameras.w2c.to(g.means)
    K = cameras.K.to(g.means)
    centers = cameras.centers.to(g.means)
    rotations = g.rotations
    covariances = g.covariances if mode == "ewa" else None
    maps = []
    for c in range(len(cameras)):
        proj = project(
            g.means,
            rotations,
            g.scales,
            covariances,
            g.opacities,
            g.sh,
            w2c[c],
            K[c],
            centers[c],
            width,
            height,
            mode,
            settings,
        )
        maps.append(_rasterize(proj, mode, width, height))
    return tuple(torch.stack([m[i] for m in maps]) for i in range(4))


def _rasterize(proj: Projected, mode: RenderMode, width: int, height: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """One camera's maps [3 or 1, H, W] from its projected Gaussians through gsplat's kernels."""
    dtype = proj.features.dtype
    if proj.index.numel() == 0:  # nothing in view
        zeros = proj.features.new_zeros(1, height, width)
        return zeros.expand(3, -1, -1), zeros, zeros, zeros.expand(3, -1, -1)
    kernels = _kernels()
    f32 = torch.float32
    if mode == "surfel":
        depth = proj.geometry[:, 10]  # T_w[2]: the camera z of the surfel's centre
        lowpass = proj.center + proj.geometry[:, 11:13]
        features = torch.cat((proj.features[:, :6], depth[:, None].to(dtype)), dim=-1)
    else:
        depth = proj.features[:, 6]
        features = proj.features
    tiles_w, tiles_h = -(-width // TILE), -(-height // TILE)
    middle, radii = tile_boxes(proj.pixel_box)
    _, isect_ids, flatten_ids = kernels.isect_tiles(
        middle[None], radii[None], depth.detach()[None].to(f32), TILE, tiles_w, tiles_h
    )
    offsets = kernels.isect_offset_encode(isect_ids, 1, tiles_w, tiles_h)
    opacity = proj.opacity[None].to(f32)
    if mode == "surfel":
        out = kernels.rasterize_to_pixels_2dgs(
            lowpass[None].to(f32),
            proj.transform[None].to(f32),
            features[None].to(f32),
            opacity,
            torch.zeros_like(features[None, :, :3], dtype=f32),  # gsplat's own normal channel (unused)
            torch.zeros_like(lowpass[None], dtype=f32),  # gsplat's densification statistics (unused)
            width,
            height,
            TILE,
            offsets,
            flatten_ids,
        )
    else:
        out = kernels.rasterize_to_pixels(
            proj.center[None].to(f32),
            proj.geometry[None].to(f32),
            features[None].to(f32),
            opacity,
            width,
            height,
            TILE,
            offsets,
            flatten_ids,
        )
    rendered = out[0][0].permute(2, 0, 1).to(dtype)  # [7, H, W]: colour, normal, depth
    alpha = out[1][0].permute(2, 0, 1).to(dtype)
    return rendered[0:3], alpha, rendered[6:7], rendered[3:6]
