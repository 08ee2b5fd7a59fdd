"""CUDA backend through the gsplat library (optional extra: pip install 'surfsplat[gsplat]').

One function on every backend: the projection is this project's own (`torch_backend`'s
`surfel_transforms` / `surfel_footprint` and `ewa_conics` / `ewa_pixel_box`, differentiable through
autograd, the same code as the torch backend), and gsplat supplies what runs per pixel - tile
intersection (`isect_tiles`, `isect_offset_encode`) and the rasterization kernels
(`rasterize_to_pixels_2dgs` for surfels, `rasterize_to_pixels` for EWA). gsplat's own projection
is not used, so its conventions do not leak in: the surfel low-pass term is centred where
`RenderConventions.lowpass_center_sigma` says, the EWA Jacobian is clamped and the footprint
supported as `ewa_jacobian_clamp` / `ewa_support` say, and a surfel whose footprint crosses the
camera plane is listed in every tile it reaches. Each Gaussian's tiles come from the same pixel
box as on the other backends; the kernels test every pixel of those tiles against the alpha
threshold, so the box only bounds the work.

How it runs at gsplat's own speed:
- every camera of a call goes through one batched projection ([C, N] tensors) and one call of each
  kernel (gsplat takes a camera dimension), not a loop over cameras;
- the projection runs in float32 (the kernels compute in float32 whatever they are given; the
  torch backend keeps float64 for its own per-pixel work);
- nothing in this module reads a device value on the host: culled Gaussians get tile radius 0,
  which `isect_tiles` skips, instead of being removed with a data-dependent `nonzero`. gsplat's own
  `isect_tiles` reads its intersection count once and its 2DGS backward synchronises the device,
  as they do inside gsplat's `rasterization_2dgs`.

Channel layout. The 2DGS kernels blend the colour channels and, separately, a per-Gaussian normal:
colour and centre depth go in as 4 channels ([r, g, b, depth], gsplat's own RGB+D layout) and the
camera-facing normals in the normal slot, whose gradient the kernel returns. The EWA kernels
blend [r, g, b, normal, depth, 0] (8 channels). Both counts are ones gsplat's kernels are compiled
for: for any other count gsplat's `rasterize_to_pixels_2dgs` pads the channels with
`torch.empty`, uninitialised memory, whose NaN or inf bit patterns the backward multiplies by the
padding's zero gradient - NaN in every geometry gradient (gsplat 1.5.3; the cause of training that
turned non-finite at its first step on a GPU). `tests/render/test_gsplat_backend.py` fills
uninitialised memory with NaN and proves no such channel is ever read.

Depth distortion (`distortion=True`, surfels): gsplat's kernel computes it with `distloss=True` from the
last colour channel, here the centre depth, and returns it as `render_distort`; that is the definition
every backend computes (see `render`), so it is returned as it is.

Differences that remain by design (gsplat's kernels, not configurable):
- depth: gsplat blends a per-Gaussian value, so the "surfel" depth map is the blended centre depth
  (camera z of each surfel's centre), not the ray-splat intersection depth of the other backends;
  the two agree exactly for fronto-parallel surfels and differ by at most a surfel's extent in depth.
- alpha cap: 0.999 in gsplat's kernels, 0.99 here; it binds only where opacity exceeds 0.99
  (SurfSplat's adapter caps opacity at 0.6).
- precision: float32 throughout.
Colours (SH per camera) and camera-facing normals are computed exactly as the torch backend computes
them. Forced-alpha normalization and the background are applied by the caller, identically for
every backend.
"""

from __future__ import annotations

from dataclasses import fields

import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..geometry.sh import sh_to_color
from .torch_backend import (
    TorchRenderSettings,
    _camera_facing,
    _pixel_box,
    ewa_conics,
    ewa_pixel_box,
    surfel_footprint,
    surfel_transforms,
)
from .types import ALPHA_MIN, RenderConventions, RenderMode

TILE = 16  # gsplat's tile edge in pixels
F32 = torch.float32


def _kernels():
    """gsplat's CUDA entry points (one module, so tests can swap in gsplat's pure-PyTorch references)."""
    from gsplat.cuda import _wrapper

    return _wrapper


def tile_boxes(pixel_box: Tensor) -> tuple[Tensor, Tensor]:
    """Centres [..., 2] and integer radii [..., 2] whose gsplat tiles are exactly those the pixel boxes
    [..., 4] touch (an empty box gets radius 0: no tile).

    gsplat lists a Gaussian in tiles floor((m - r) / 16) up to, exclusive, ceil((m + r) / 16). The
    tile-aligned range [L, R) around an inclusive box has m = (L + R) / 2 and r = (R - L) / 2 (a
    multiple of 8), so no neighbouring tile is added: for "ewa" with the release support, whose
    boxes are whole 16-pixel tiles, that is the release's own tile set.
    """
    first, last = pixel_box[..., 0::2], pixel_box[..., 1::2]  # (col0, row0), (col1, row1); slices: no index upload
    lo = torch.div(first, TILE, rounding_mode="floor") * TILE
    hi = (torch.div(last, TILE, rounding_mode="floor") + 1) * TILE
    empty = (last < first).any(-1, keepdim=True)
    radii = torch.div(hi - lo, 2, rounding_mode="floor").masked_fill(empty, 0)
    return (0.5 * (lo + hi)).to(F32), radii.to(torch.int32)


def render_gsplat(
    g: Gaussians,
    cameras: Cameras,
    width: int,
    height: int,
    mode: RenderMode,
    conventions: RenderConventions | None = None,
    distortion: bool = False,
    factors: Tensor | None = None,
) -> tuple[Tensor, ...]:
    """Un-normalized colour [C, 3, H, W], alpha [C, 1, H, W], depth [C, 1, H, W], normal [C, 3, H, W],
    and with `distortion` (surfels) 2DGS's depth distortion [C, 1, H, W], every camera in one batched
    call, in the Gaussians' dtype. `factors` [C, N]: per-camera opacity factors (the antialiasing
    compensations of `render.antialias`), applied before the footprints, as on every backend."""
    rules = conventions or RenderConventions()
    settings = TorchRenderSettings(**{f.name: getattr(rules, f.name) for f in fields(RenderConventions)})
    dtype = g.means.dtype
    w2c = cameras.w2c.to(g.means.device, F32)  # [C, 4, 4]
    K = cameras.K.to(g.means.device, F32)  # [C, 3, 3]
    centers = cameras.centers.to(g.means.device, F32)  # [C, 3]
    means = g.means.to(F32)
    opacities = g.opacities.to(F32)
    if factors is not None:
        opacities = opacities * factors.to(F32)  # [C, N]
    rotations = g.rotations.to(F32)
    if mode == "surfel":
        T, mu = surfel_transforms(means, rotations, g.scales.to(F32), w2c, K, F32)  # [C, N, 3, 3], [C, N, 3]
        depth = mu[..., 2]
        center, lowpass, bounds = surfel_footprint(T, depth, opacities, settings.lowpass_center_sigma)
        box = _pixel_box(*(b.detach() for b in bounds), width, height)
    else:
        mu, center, conic, cov2d = ewa_conics(
            means, g.covariances.to(F32), w2c, K, width, height, settings.ewa_jacobian_clamp, F32
        )
        depth = mu[..., 2]
        box = ewa_pixel_box(center, cov2d, opacities, width, height, settings.ewa_support)
    middle, radii = tile_boxes(box)
    # The torch backend's culling, as a zero radius instead of a removal (no data-dependent size).
    z = depth.detach()
    keep = (z > settings.near_plane) & (z < settings.far_plane) & (opacities.detach() >= ALPHA_MIN)
    radii = radii * keep[..., None]

    colors = sh_to_color(g.sh.to(F32), F.normalize(means - centers[:, None], dim=-1))  # [C, N, 3]
    normals = _camera_facing(rotations[:, :, 2], mu, w2c[:, :3, :3])  # [C, N, 3]
    opacity = opacities.expand(len(cameras), -1)  # [C, N] (already per camera with factors)
    kernels = _kernels()
    tiles_w, tiles_h = -(-width // TILE), -(-height // TILE)
    _, isect_ids, flatten_ids = kernels.isect_tiles(middle, radii, z, TILE, tiles_w, tiles_h)
    offsets = kernels.isect_offset_encode(isect_ids, len(cameras), tiles_w, tiles_h)
    if mode == "surfel":
        out = kernels.rasterize_to_pixels_2dgs(
            lowpass,
            T,
            torch.cat((colors, depth[..., None]), dim=-1),  # [C, N, 4]: r, g, b, centre depth
            opacity,
            normals,
            torch.zeros_like(lowpass),  # gsplat's densification statistics (unused)
            width,
            height,
            TILE,
            offsets,
            flatten_ids,
            distloss=distortion,  # of the last channel: the centre depth
        )
        rgbd, alpha, normal = out[0], out[1], out[2]  # [C, H, W, 4], [C, H, W, 1], [C, H, W, 3]
        color, depth_map = rgbd[..., 0:3], rgbd[..., 3:4]
        if distortion:
            maps = (color, alpha, depth_map, normal, out[3])  # render_distort [C, H, W, 1]
            return tuple(t.permute(0, 3, 1, 2).to(dtype) for t in maps)
    else:
        features = torch.cat((colors, normals, depth[..., None], torch.zeros_like(depth[..., None])), dim=-1)
        maps, alpha = kernels.rasterize_to_pixels(
            center, conic, features, opacity, width, height, TILE, offsets, flatten_ids
        )
        color, normal, depth_map = maps[..., 0:3], maps[..., 3:6], maps[..., 6:7]
    return tuple(t.permute(0, 3, 1, 2).to(dtype) for t in (color, alpha, depth_map, normal))
