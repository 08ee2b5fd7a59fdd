"""gsplat's own pure-PyTorch reference of 2DGS and 3DGS rasterization, runnable on a CPU.

gsplat (pinned in the test extra) ships `gsplat.cuda._torch_impl` and `_torch_impl_2dgs`: the
functions its CUDA kernels are tested against. Two pieces they call are not pure PyTorch: the
pair selection `rasterize_to_indices_in_range[_2dgs]` (a CUDA kernel) and nerfacc's compositing
scans. `stand_ins()` replaces them, for the duration of a `with` block, by the small torch
versions below, written from the kernel's and nerfacc's definitions:

* pair selection: per tile, per pixel, the tile's Gaussians front to back whose alpha reaches
  1/255, stopping (exclusively) where transmittance would fall to 1e-4 or below;
* `render_weight_from_alpha`: w_i = a_i prod_{j<i} (1 - a_j) along each ray (rays sorted);
* `accumulate_along_rays`: the per-ray sum of w_i v_i.

`render_2dgs` and `render_3dgs` then run gsplat's reference pipeline (projection, SH, tile
intersection, rasterization) and return the maps in this project's layout: colour [C, 3, H, W],
alpha [C, 1, H, W], centre depth [C, 1, H, W] and (2DGS) world-frame normals [C, 3, H, W].
With `full_coverage` every Gaussian is listed in every tile, so gsplat's tile boxes (3.33 sigma
around its own centre) cannot truncate a footprint and the result is the rasterized function itself.

`reference_scene` and `with_intrinsics` build the seeded scenes that the test suite and
`benchmarks/renderer_agreement.py` compare on. Importing this module needs gsplat (the test extra).
"""

from __future__ import annotations

import contextlib
import math
import sys
import types

import torch
import torch.nn.functional as F
from gsplat.cuda import _torch_impl as ref
from gsplat.cuda import _torch_impl_2dgs as ref2d
from gsplat.cuda import _wrapper
from torch import Tensor

from surfsplat import Cameras, Gaussians

ALPHA_THRESHOLD = 1.0 / 255.0  # gsplat's ALPHA_THRESHOLD
ALPHA_CAP = 0.999  # gsplat's alpha cap (2DGS and 3DGS)
TILE = 16


def _select_pairs(
    pair_alpha, n, range_start, range_end, transmittances, image_width, image_height, tile_size, offsets, flat
):
    """Torch twin of gsplat's rasterize_to_indices kernels, for n Gaussians per image.

    pair_alpha(image, gaussians [K], px [P], py [P]) -> [P, K] alpha of a tile's pixels and Gaussians.
    Returns (Gaussian ids, pixel ids, image ids) as the kernels do.
    """
    offsets = offsets.reshape(-1, *offsets.shape[-2:])
    transmittances = transmittances.reshape(-1, image_height, image_width)
    n_images, tiles_h, tiles_w = offsets.shape
    n_isects = flat.shape[0]
    starts = offsets.reshape(-1).tolist() + [n_isects]
    block = tile_size * tile_size
    gauss, pixels, images = [], [], []
    for image in range(n_images):
        for ty in range(tiles_h):
            for tx in range(tiles_w):
                t = (image * tiles_h + ty) * tiles_w + tx
                lo, hi = starts[t], starts[t + 1]
                lo, hi = lo + block * range_start, min(hi, lo + block * range_end)
                if hi <= lo:
                    continue
                rows = torch.arange(ty * tile_size, min((ty + 1) * tile_size, image_height))
                cols = torch.arange(tx * tile_size, min((tx + 1) * tile_size, image_width))
                ii, jj = torch.meshgrid(rows, cols, indexing="ij")
                pix = (ii * image_width + jj).reshape(-1)
                ids = flat[lo:hi].long() % n  # flattened (image, Gaussian) index -> Gaussian
                alpha = pair_alpha(image, ids, jj.reshape(-1), ii.reshape(-1)).detach()
                take = alpha >= ALPHA_THRESHOLD
                trans = transmittances[image].reshape(-1)[pix].detach()
                t_incl = trans[:, None] * torch.cumprod(1 - torch.where(take, alpha, 0.0), dim=1)
                keep = take & (t_incl > 1e-4)
                p_idx, k_idx = keep.nonzero(as_tuple=True)  # row-major: by pixel, then front to back
                gauss.append(ids[k_idx])
                pixels.append(pix[p_idx])
                images.append(torch.full_like(p_idx, image))
    if not gauss:
        empty = torch.zeros(0, dtype=torch.long)
        return empty, empty, empty
    g, p, i = torch.cat(gauss), torch.cat(pixels), torch.cat(images)
    order = torch.argsort(i * image_width * image_height + p, stable=True)  # the kernel's per-pixel chunks
    return g[order], p[order], i[order]


def _indices_3dgs(range_start, range_end, transmittances, means2d, conics, opacities, W, H, tile_size, offsets, flat):
    n = means2d.shape[-2]
    means2d, conics, opacities = means2d.reshape(-1, n, 2), conics.reshape(-1, n, 3), opacities.reshape(-1, n)

    def alpha(image, g, px, py):
        dx = means2d[image, g, 0][None] - (px[:, None] + 0.5)
        dy = means2d[image, g, 1][None] - (py[:, None] + 0.5)
        c = conics[image, g]
        sigma = 0.5 * (c[:, 0] * dx * dx + c[:, 2] * dy * dy) + c[:, 1] * dx * dy
        a = torch.clamp_max(opacities[image, g][None] * torch.exp(-sigma), ALPHA_CAP)
        return torch.where(sigma >= 0, a, 0.0)

    return _select_pairs(alpha, n, range_start, range_end, transmittances, W, H, tile_size, offsets, flat)


def _indices_2dgs(
    range_start, range_end, transmittances, means2d, ray_transforms, opacities, W, H, tile_size, offsets, flat
):
    n = means2d.shape[-2]
    means2d, M, opacities = means2d.reshape(-1, n, 2), ray_transforms.reshape(-1, n, 3, 3), opacities.reshape(-1, n)

    def alpha(image, g, px, py):
        x, y = px[:, None] + 0.5, py[:, None] + 0.5
        m = M[image, g]
        h_u = -m[None, :, 0, :] + m[None, :, 2, :] * x[..., None]
        h_v = -m[None, :, 1, :] + m[None, :, 2, :] * y[..., None]
        cr = torch.linalg.cross(h_u, h_v)
        ok = cr[..., 2] != 0
        safe = torch.where(ok, cr[..., 2], 1.0)
        s3 = (cr[..., 0] / safe) ** 2 + (cr[..., 1] / safe) ** 2
        d = means2d[image, g][None] - torch.stack((x.expand(-1, g.shape[0]), y.expand(-1, g.shape[0])), -1)
        s2 = 2 * (d**2).sum(-1)
        sigma = 0.5 * torch.minimum(s3, s2)
        a = torch.clamp_max(opacities[image, g][None] * torch.exp(-sigma), ALPHA_CAP)
        return torch.where(ok & (sigma >= 0), a, 0.0)

    return _select_pairs(alpha, n, range_start, range_end, transmittances, W, H, tile_size, offsets, flat)


def _render_weight_from_alpha(alphas: Tensor, ray_indices: Tensor, n_rays: int):
    """nerfacc's weights along sorted rays: w_i = a_i T_i with T_i the exclusive product of (1 - a)."""
    if alphas.numel() == 0:
        return alphas, alphas
    first = torch.ones_like(ray_indices, dtype=torch.bool)
    first[1:] = ray_indices[1:] != ray_indices[:-1]
    segment = torch.cumsum(first.long(), 0) - 1
    starts = first.nonzero().squeeze(1)
    position = torch.arange(alphas.shape[0]) - starts[segment]
    dense = alphas.new_zeros(int(segment[-1]) + 1, int(position.max()) + 1)
    dense = dense.index_put((segment, position), alphas)
    trans_incl = torch.cumprod(1 - dense, dim=1)
    trans = torch.cat((torch.ones_like(trans_incl[:, :1]), trans_incl[:, :-1]), dim=1)[segment, position]
    return alphas * trans, trans


def _accumulate_along_rays(weights: Tensor, values: Tensor | None, ray_indices: Tensor, n_rays: int) -> Tensor:
    src = weights[:, None] if values is None else weights[:, None] * values
    out = torch.zeros(n_rays, src.shape[1], dtype=src.dtype)
    return out.index_add(0, ray_indices, src)


@contextlib.contextmanager
def stand_ins():
    """Run gsplat's references on a CPU: the pair selection and nerfacc's scans in torch."""
    nerfacc = types.ModuleType("nerfacc")
    nerfacc.render_weight_from_alpha = _render_weight_from_alpha
    nerfacc.accumulate_along_rays = _accumulate_along_rays
    saved = {
        name: getattr(_wrapper, name)
        for name in ("rasterize_to_indices_in_range", "rasterize_to_indices_in_range_2dgs")
    }
    previous = sys.modules.get("nerfacc")
    sys.modules["nerfacc"] = nerfacc
    _wrapper.rasterize_to_indices_in_range = _indices_3dgs
    _wrapper.rasterize_to_indices_in_range_2dgs = _indices_2dgs
    try:
        yield
    finally:
        for name, fn in saved.items():
            setattr(_wrapper, name, fn)
        if previous is None:
            sys.modules.pop("nerfacc", None)
        else:
            sys.modules["nerfacc"] = previous


def _colors(means: Tensor, sh: Tensor, campos: Tensor) -> Tensor:
    """gsplat's SH colours for one camera: SH(means - camera centre) + 0.5, clamped at 0 ([N, 3])."""
    degree = math.isqrt(sh.shape[-1]) - 1
    return torch.clamp_min(ref._spherical_harmonics(degree, means - campos, sh.transpose(1, 2)) + 0.5, 0.0)


def _tiles(means2d, radii, depths, width, height, full_coverage):
    tiles_w, tiles_h = -(-width // TILE), -(-height // TILE)
    if full_coverage:
        reach = (radii > 0).any(-1, keepdim=True).expand_as(radii)
        radii = torch.where(reach, width + height + 2 * TILE, 0).to(radii.dtype)
    _, isect_ids, flatten_ids = ref._isect_tiles(means2d, radii, depths, TILE, tiles_w, tiles_h)
    offsets = ref._isect_offset_encode(isect_ids, 1, tiles_w, tiles_h)
    return offsets, flatten_ids


def render_2dgs(
    g,
    w2c: Tensor,
    K: Tensor,
    campos: Tensor,
    width: int,
    height: int,
    full_coverage: bool = True,
    distortion: bool = False,
    opacities: Tensor | None = None,
):
    """gsplat's 2DGS reference for one camera: colour, alpha, centre depth, world normals, and with
    `distortion` the depth distortion of gsplat's kernel (`distortion_2dgs`) [1, 1, H, W]. `opacities`
    [N] replace the Gaussians' own (gsplat's 2DGS has no antialiased mode: the compensated opacities
    are handed to it, as `rasterization(rasterize_mode="antialiased")` does for 3DGS)."""
    # The third scale enters only gsplat's normal (R diag(s) e3): 1 gives unit normals.
    scales = torch.cat((g.scales, torch.ones_like(g.scales[:, :1])), -1)
    radii, means2d, depths, ray_transforms, normals = ref2d._fully_fused_projection_2dgs(
        g.means, g.quats, scales, w2c[None], K[None], width, height, near_plane=0.01
    )
    valid = (depths > 0.01) & (depths < 1e10)
    radii = torch.where(valid[..., None], radii.clamp_min(1), 0) if full_coverage else radii
    offsets, flat = _tiles(means2d, radii, depths, width, height, full_coverage)
    features = torch.cat((_colors(g.means, g.sh, campos)[None], depths[..., None]), -1)
    with stand_ins():
        color, alpha, normal = ref2d._rasterize_to_pixels_2dgs(
            means2d,
            ray_transforms,
            features,
            normals,
            (g.opacities if opacities is None else opacities)[None],
            width,
            height,
            TILE,
            offsets,
            flat,
            batch_per_iter=1 << 20,
        )
        if distortion:
            distort = distortion_2dgs(
                means2d, ray_transforms, features, g.opacities[None], width, height, TILE, offsets, flat
            )
    normal_world = normal[0] @ w2c[:3, :3].to(normal)  # rows n_cam^T R_cw = (R_cw^T n_cam)^T
    maps = (
        color[0, ..., :3].permute(2, 0, 1)[None],
        alpha[0].permute(2, 0, 1)[None],
        color[0, ..., 3:4].permute(2, 0, 1)[None],
        normal_world.permute(2, 0, 1)[None],
    )
    return (*maps, distort[0].permute(2, 0, 1)[None]) if distortion else maps


def render_3dgs(
    g,
    w2c: Tensor,
    K: Tensor,
    campos: Tensor,
    width: int,
    height: int,
    full_coverage: bool = True,
    extra: Tensor | None = None,
    antialiased: bool = False,
):
    """gsplat's 3DGS (EWA) reference for one camera: colour, alpha, centre depth and `extra` channels blended;
    `antialiased`: gsplat's `rasterize_mode="antialiased"` (the opacities times the projection's compensations)."""
    from surfsplat.geometry.gaussians import THIN_SCALE

    scales = torch.cat((g.scales, torch.full_like(g.scales[:, :1], THIN_SCALE)), -1)
    covars, _ = ref._quat_scale_to_covar_preci(F.normalize(g.quats, dim=-1), scales, compute_preci=False)
    radii, means2d, depths, conics, compensations = ref._fully_fused_projection(
        covars=covars,
        means=g.means,
        viewmats=w2c[None],
        Ks=K[None],
        width=width,
        height=height,
        eps2d=0.3,
        calc_compensations=antialiased,
    )
    opacities = g.opacities[None] if compensations is None else g.opacities[None] * compensations  # as rendering.py
    offsets, flat = _tiles(means2d, radii, depths, width, height, full_coverage)
    parts = [_colors(g.means, g.sh, campos)[None], depths[..., None]]
    if extra is not None:
        parts.append(extra[None])
    features = torch.cat(parts, -1)
    with stand_ins():
        out, alpha = ref._rasterize_to_pixels(
            means2d, conics, features, opacities, width, height, TILE, offsets, flat, batch_per_iter=1 << 20
        )
    maps = out[0].permute(2, 0, 1)[None]
    return maps[:, :3], alpha[0].permute(2, 0, 1)[None], maps[:, 3:4], maps[:, 4:]


def _isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height, **_):
    return ref._isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height)


def _isect_offset_encode(isect_ids, n_images, tile_width, tile_height):
    return ref._isect_offset_encode(isect_ids, n_images, tile_width, tile_height)


def distortion_2dgs(means2d, transforms, colors, opacities, W, H, tile, offsets, flat) -> Tensor:
    """The depth distortion of gsplat's 2DGS kernel (`rasterize_to_pixels_2dgs(distloss=True)`,
    `render_distort` [..., H, W, 1]) on the pairs, alphas and weights of gsplat's reference.

    gsplat's pure-PyTorch reference has no distortion, so this is its CUDA forward written in torch
    (differentiated by autograd): per pixel, front to back, with T the transmittance in front of a
    pair, w its weight and d the last colour channel (the depth),
        distort += 2 (w d (1 - T) - w sum_{j in front} w_j d_j).
    The pairs are the kernel's (`rasterize_to_indices_in_range_2dgs`) and alpha is computed as gsplat's
    `accumulate_2dgs` computes it.
    """
    image_dims = means2d.shape[:-2]
    n = means2d.shape[-2]
    images = math.prod(image_dims)
    ones = torch.ones(image_dims + (H, W), dtype=means2d.dtype)
    gs, pix, img = _wrapper.rasterize_to_indices_in_range_2dgs(
        0, 1 << 20, ones, means2d, transforms, opacities, W, H, tile, offsets, flat
    )
    means2d, M = means2d.reshape(images, n, 2), transforms.reshape(images, n, 3, 3)
    x, y = pix % W + 0.5, pix // W + 0.5
    m = M[img, gs]
    h_u = -m[..., 0, :] + m[..., 2, :] * x[:, None]
    h_v = -m[..., 1, :] + m[..., 2, :] * y[:, None]
    cr = torch.linalg.cross(h_u, h_v, dim=-1)
    s3 = (cr[..., 0] / cr[..., 2]) ** 2 + (cr[..., 1] / cr[..., 2]) ** 2
    delta = torch.stack((x, y), -1) - means2d[img, gs]
    s2 = 2 * (delta**2).sum(-1)
    alpha = torch.clamp_max(opacities.reshape(images, n)[img, gs] * torch.exp(-0.5 * torch.minimum(s3, s2)), ALPHA_CAP)
    rays = img * H * W + pix
    if rays.numel() == 0:
        return means2d.new_zeros(image_dims + (H, W, 1)) + 0 * colors.sum()
    weights, trans = _render_weight_from_alpha(alpha, rays, images * H * W)
    depth = colors.reshape(images, n, -1)[img, gs, -1]
    # The moment in front of each pair, summed along its ray only (a global running sum would lose the
    # float32 precision of a short ray to the length of the list).
    first = torch.ones_like(rays, dtype=torch.bool)
    first[1:] = rays[1:] != rays[:-1]
    segment = torch.cumsum(first.long(), 0) - 1
    position = torch.arange(rays.shape[0]) - first.nonzero().squeeze(1)[segment]
    dense = weights.new_zeros(int(segment[-1]) + 1, int(position.max()) + 1)
    wd = weights * depth
    dense = dense.index_put((segment, position), wd)
    in_front = (torch.cumsum(dense, 1) - dense)[segment, position]
    per_pair = 2 * (wd * (1 - trans) - weights * in_front)
    out = torch.zeros(images * H * W, dtype=per_pair.dtype).index_add(0, rays, per_pair)
    return out.reshape(image_dims + (H, W, 1))


class _Rasterize2DGS:
    """Stands in for gsplat's `_RasterizeToPixels2DGS` autograd function (its CUDA forward and
    backward): gsplat's reference, differentiated by autograd, and with `distloss` the distortion of
    its kernel (`distortion_2dgs`). The public wrapper around it - its input checks and its channel
    padding - stays gsplat's own."""

    @staticmethod
    def apply(
        means2d,
        transforms,
        colors,
        opacities,
        normals,
        densify,
        backgrounds,
        masks,
        W,
        H,
        tile,
        offsets,
        flat,
        absgrad=False,
        distloss=False,
    ):
        out, alpha, normal = ref2d._rasterize_to_pixels_2dgs(
            means2d, transforms, colors, normals, opacities, W, H, tile, offsets, flat, batch_per_iter=1 << 20
        )
        unused = alpha.new_zeros(alpha.shape)  # median depth: not part of the reference
        distort = unused
        if distloss:
            distort = distortion_2dgs(means2d, transforms, colors, opacities, W, H, tile, offsets, flat)
        return out, alpha, normal, distort, unused


class _Rasterize3DGS:
    """Stands in for gsplat's `_RasterizeToPixels` autograd function (see `_Rasterize2DGS`)."""

    @staticmethod
    def apply(means2d, conics, colors, opacities, backgrounds, masks, W, H, tile, offsets, flat, *_):
        return ref._rasterize_to_pixels(
            means2d, conics, colors, opacities, W, H, tile, offsets, flat, batch_per_iter=1 << 20
        )


@contextlib.contextmanager
def cpu_kernels():
    """gsplat's CUDA entry points (tile intersection, 2DGS and 3DGS rasterization) answered by its
    pure-PyTorch references, inside the block: the project's gsplat backend then runs on a CPU.

    The rasterizers are replaced below gsplat's public wrappers (`rasterize_to_pixels_2dgs`,
    `rasterize_to_pixels`), at their autograd functions, so everything the wrappers do on a GPU -
    shape checks, channel padding, the layout of their outputs - runs here too."""
    patched = {
        "isect_tiles": _isect_tiles,
        "isect_offset_encode": _isect_offset_encode,
        "_RasterizeToPixels2DGS": _Rasterize2DGS,
        "_RasterizeToPixels": _Rasterize3DGS,
    }
    saved = {name: getattr(_wrapper, name) for name in patched}
    try:
        for name, fn in patched.items():
            setattr(_wrapper, name, fn)
        with stand_ins():
            yield
    finally:
        for name, fn in saved.items():
            setattr(_wrapper, name, fn)


# Public options that align this project's conventions with gsplat's reference: the surfel
# low-pass term centred on the 1-sigma box, and no truncation of EWA footprints.
ALIGNED = {"lowpass_center_sigma": 1.0, "ewa_support": "alpha"}


def facing_normals(g, centre: Tensor) -> Tensor:
    """The surfels' world normals turned towards the camera at `centre`, as this project renders them
    (gsplat's 3DGS reference blends them as extra channels)."""
    n = g.rotations[:, :, 2]
    return torch.where((n * (g.means - centre)).sum(-1, keepdim=True) > 0, -n, n)


def reference_scene(
    n: int, seed: int, dtype: torch.dtype, sh_degree: int, fronto: bool = False
) -> tuple[Gaussians, Cameras]:
    """n surfels in a slab 2-4 units ahead of a camera posed off the axis, looking at the slab."""
    g = torch.Generator().manual_seed(seed)
    d = torch.float64
    means = (torch.rand(n, 3, generator=g, dtype=d) - 0.5) * torch.tensor([2.4, 1.8, 2.0], dtype=d)
    means[:, 2] += 3.0
    quats = torch.randn(n, 4, generator=g, dtype=d)
    if fronto:
        angle = torch.rand(n, generator=g, dtype=d) * math.pi
        quats = torch.stack((torch.cos(angle / 2), 0 * angle, 0 * angle, torch.sin(angle / 2)), -1)
    # log-uniform sizes: from about a fifth of a pixel to about 30 pixels at 64 px wide
    scales = torch.exp(torch.rand(n, 2, generator=g, dtype=d) * math.log(150.0)) * 0.0015
    opacities = torch.rand(n, generator=g, dtype=d) * 0.94 + 0.05
    sh = torch.randn(n, 3, (sh_degree + 1) ** 2, generator=g, dtype=d) * 0.3
    c2w = torch.eye(4, dtype=d)
    yaw = 0.15 if not fronto else 0.0
    c2w[:3, :3] = torch.tensor(
        [[math.cos(yaw), 0, math.sin(yaw)], [0, 1, 0], [-math.sin(yaw), 0, math.cos(yaw)]], dtype=d
    )
    c2w[:3, 3] = torch.tensor([-0.3 if not fronto else 0.0, 0.1, -0.2], dtype=d)
    gs = Gaussians(means=means, quats=quats, scales=scales, opacities=opacities, sh=sh)
    gs = Gaussians(**{k: getattr(gs, k).to(dtype) for k in ("means", "quats", "scales", "opacities", "sh")})
    return gs, Cameras(c2w[None].to(dtype), torch.eye(3, dtype=dtype)[None])


def with_intrinsics(cams: Cameras, width: int, height: int) -> Cameras:
    f = 0.9 * width
    K = torch.tensor([[[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]]], dtype=cams.c2w.dtype)
    return Cameras(cams.c2w, K)
