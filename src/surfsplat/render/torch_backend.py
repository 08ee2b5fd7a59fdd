"""Pure-PyTorch tile renderer for 2D Gaussian surfels and EWA-splatted 3D Gaussians.

The reference backend: runs on any device, differentiable through autograd, and memory-bounded.

Pipeline for one camera:
1. `project_*`: per-Gaussian screen-space quantities (float64 for the geometry, so large images
   keep sub-pixel precision) and the opacity-aware bounding box of every pixel where the
   Gaussian's alpha can reach ALPHA_MIN.
2. Binning: each Gaussian is listed in every tile its box touches; one stable sort by tile id
   of the depth-sorted list gives, per tile, its Gaussians front to back.
3. Compositing in work blocks of (group of tiles) x (block of depth slots) x (tile pixels): a
   Gaussian's response at a pixel is one small matrix product in tile-local coordinates, then
   front-to-back alpha compositing with the early-termination rule of 3DGS/2DGS, carried across
   depth blocks. Each block's backward pass is written out by hand and recomputes the block from
   its small inputs, so peak memory is bounded by one block at any resolution.
4. Depth distortion (surfels, only when asked): each block's weights again, in plain autograd ops,
   with two running moments carried across depth blocks (`_distortion_block`); it is the reference
   the other backends' hand-written gradients are checked against, and activation checkpointing
   keeps its memory to one block too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
import torch.utils.checkpoint
from torch import Tensor

from ..geometry.sh import sh_to_color
from .types import (
    ALPHA_MAX,
    ALPHA_MIN,
    EWA_DILATION,
    EWA_LAMBDA_GAP_MIN,
    EWA_RADIUS_SIGMAS,
    EWA_TILE,
    LOG_ALPHA_MIN,
    LOWPASS_RHO_SCALE,
    TRANSMITTANCE_MIN,
    RenderConventions,
    RenderMode,
    screen_filter,
)


@dataclass
class TorchRenderSettings(RenderConventions):
    tile_size: int = 4  # tile edge in pixels (small tiles waste fewer pair-pixel slots)
    block_elements: int = 1 << 22  # pair-pixel slots evaluated per work block (bounds peak memory)
    max_block_depth: int = 128  # at most this many Gaussians per tile in one block
    near_plane: float = 0.01  # Gaussians closer than this (camera z) are culled
    far_plane: float = 1e10  # Gaussians farther than this are culled


# ---------------------------------------------------------------------------------------------
# Projection
# ---------------------------------------------------------------------------------------------


@dataclass
class Projected:
    """Per-Gaussian screen quantities for the Gaussians kept after culling, sorted front to back."""

    index: Tensor  # [M] index into the input Gaussians
    center: Tensor  # [M, 2] projected centre (pixels, float64)
    geometry: Tensor  # [M, G] mode-specific coefficients (float64), see `_pair_coefficients`
    opacity: Tensor  # [M]
    features: Tensor  # [M, 6 or 7] colour (3), normal (3) [, centre depth (1) for ewa]
    pixel_box: Tensor  # [M, 4] int64 inclusive pixel ranges: col0, col1, row0, row1
    transform: Tensor | None = None  # surfel: [M, 3, 3] T = K [R S e1, R S e2, mu] (rows T_x, T_y, T_w)
    # surfel, for the absolute screen gradient (`absgrad`): [M, 5] constants, detached: (c_x T_w - T_x)[:2],
    # (c_y T_w - T_y)[:2] and d c_lp / d T_x[2] (= d c_lp,y / d T_y[2]), see `_abs_centre_gradients`
    abs_coef: Tensor | None = None
    lowpass: float = LOWPASS_RHO_SCALE  # surfel: rho2d = lowpass |p - c_lp|^2 (`render`'s filter_zoom)


def _take(x: Tensor, index: Tensor) -> Tensor:
    """x[index] along dim 0 for an index of any shape, with a deterministic backward.

    Advanced indexing's backward accumulates with parallel atomic adds on multi-threaded CPUs
    (float32), so repeated runs differed in the last bits; index_select's backward (index_add_)
    adds in index order.
    """
    return x.index_select(0, index.reshape(-1)).reshape(*index.shape, *x.shape[1:])


def _opacity_extent(opacity: Tensor, dtype: torch.dtype = torch.float64) -> Tensor:
    """k^2 such that alpha = o exp(-rho / 2) >= ALPHA_MIN exactly when rho <= k^2."""
    return 2.0 * torch.log((opacity.to(dtype) / ALPHA_MIN).clamp_min(1.0))


def _pixel_box(xmin: Tensor, xmax: Tensor, ymin: Tensor, ymax: Tensor, width: int, height: int) -> Tensor:
    """Inclusive ranges of pixels whose centres (j + 0.5, i + 0.5) lie in the continuous box."""
    col0 = torch.ceil(xmin - 0.5).clamp(0, width).long()
    col1 = torch.floor(xmax - 0.5).clamp(-1, width - 1).long()
    row0 = torch.ceil(ymin - 0.5).clamp(0, height).long()
    row1 = torch.floor(ymax - 0.5).clamp(-1, height - 1).long()
    return torch.stack((col0, col1, row0, row1), dim=-1)


def _release_tile_box(center: Tensor, a: Tensor, b: Tensor, c: Tensor, width: int, height: int) -> Tensor:
    """Pixels diff-gaussian-rasterization lets an EWA Gaussian reach: its 16x16 tiles (see `RenderConventions`).

    (a, b, c) is the dilated 2D covariance. The square of radius r = ceil(3 sqrt(lambda_max)),
    lambda_max = mid + sqrt(max(0.1, mid^2 - det)), around the centre in that rasterizer's pixel
    frame (pixel centres at integers: our centre - 0.5) selects the tiles floor((p - r) / 16) up
    to, exclusive, floor((p + r + 15) / 16), clamped to the grid; every pixel of those tiles is
    then tested against the alpha threshold. An empty tile range culls the Gaussian.
    """
    mid = 0.5 * (a + c)
    lam = mid + (mid * mid - (a * c - b * b)).clamp_min(EWA_LAMBDA_GAP_MIN).sqrt()
    radius = torch.ceil(EWA_RADIUS_SIGMAS * lam.clamp_min(0).sqrt())
    ranges = []
    # Per axis with Python bounds (no tensor built from host numbers: no host-to-device copy on a GPU).
    for p, size in ((center[..., 0] - 0.5, width), (center[..., 1] - 0.5, height)):
        tiles = -(-size // EWA_TILE)
        t0 = torch.floor((p - radius) / EWA_TILE).clamp(0, tiles)
        t1 = torch.floor((p + radius + EWA_TILE - 1) / EWA_TILE).clamp(0, tiles)
        ranges.append((t0, t1))
    empty = (ranges[0][1] <= ranges[0][0]) | (ranges[1][1] <= ranges[1][0])
    box = []
    for (t0, t1), size in zip(ranges, (width, height)):
        first = t0 * EWA_TILE
        last = (t1 * EWA_TILE).clamp_max(size) - 1
        box += [first, torch.where(empty, first - 1, last)]  # an empty range, culled below
    return torch.stack(box, dim=-1).long()


def _cull_and_sort(depth: Tensor, box: Tensor, opacity: Tensor, settings: TorchRenderSettings) -> Tensor:
    keep = (depth > settings.near_plane) & (depth < settings.far_plane) & (opacity >= ALPHA_MIN)
    keep &= (box[:, 0] <= box[:, 1]) & (box[:, 2] <= box[:, 3])
    index = keep.nonzero().squeeze(1)
    order = torch.sort(depth[index].detach(), stable=True).indices
    return index[order]


def _camera_facing(normals: Tensor, means_cam: Tensor, R_cw: Tensor) -> Tensor:
    """World normals [N, 3] flipped to face the camera (n . view direction <= 0): [..., N, 3] for
    camera-frame means [..., N, 3] and world-to-camera rotations [..., 3, 3]."""
    n_cam = normals @ R_cw.mT
    flip = (n_cam * means_cam).sum(-1, keepdim=True) > 0
    return torch.where(flip, -normals, normals)


def _colors(sh: Tensor, means: Tensor, center: Tensor) -> Tensor:
    dirs = F.normalize(means - center, dim=-1)
    return sh_to_color(sh, dirs)


def projected_center(Tx: Tensor, Ty: Tensor, z: Tensor) -> Tensor:
    """[..., N, 2] the surfel centre's pixel (T_x[2], T_y[2]) / z (z guarded away from 0)."""
    safe_z = torch.where(z.abs() > 1e-12, z, torch.ones_like(z))
    return torch.stack((Tx[..., 2] / safe_z, Ty[..., 2] / safe_z), dim=-1)


def lowpass_center(Tx: Tensor, Ty: Tensor, Tw: Tensor, projected: Tensor, sigma: float | None) -> Tensor:
    """[..., N, 2] centre c of the surfel low-pass term rho2d = 2 |p - c|^2 (see `RenderConventions`).

    With k = sigma, the k-sigma ellipse u^2 + v^2 = k^2 maps under T to a conic whose dual is
    T diag(1, 1, -1/k^2) T^T; its box centre is (C02, C12) / C22 while C22 < 0 (an ellipse).
    This is 2DGS's `compute_aabb` point (t = (k^2, k^2, -1) there, the same ratio). Elsewhere,
    and for sigma None, c is the `projected` centre.
    """
    if sigma is None:
        return projected
    e = -1.0 / (sigma * sigma)
    c02 = Tx[..., 0] * Tw[..., 0] + Tx[..., 1] * Tw[..., 1] + e * Tx[..., 2] * Tw[..., 2]
    c12 = Ty[..., 0] * Tw[..., 0] + Ty[..., 1] * Tw[..., 1] + e * Ty[..., 2] * Tw[..., 2]
    c22 = Tw[..., 0] * Tw[..., 0] + Tw[..., 1] * Tw[..., 1] + e * Tw[..., 2] * Tw[..., 2]
    bounded = c22 < -1e-12
    safe22 = torch.where(bounded, c22, -torch.ones_like(c22))
    box = torch.stack((c02 / safe22, c12 / safe22), dim=-1)
    return torch.where(bounded[..., None], box, projected)


def surfel_transforms(
    means: Tensor, rotations: Tensor, scales: Tensor, w2c: Tensor, K: Tensor, dtype: torch.dtype
) -> tuple[Tensor, Tensor]:
    """2DGS's T = K [R S e1, R S e2, mu_cam] [..., N, 3, 3] and the camera-frame means [..., N, 3].

    means [N, 3], rotations [N, 3, 3], scales [N, 2+]; the leading dimensions are the cameras'
    (w2c [..., 4, 4], K [..., 3, 3]: one camera, or a batch of them). T's rows T_x, T_y, T_w map the
    surfel's (u, v, 1) to homogeneous pixels.
    """
    R_cw, t_cw = w2c[..., :3, :3].to(dtype), w2c[..., :3, 3].to(dtype)
    mu = means.to(dtype) @ R_cw.mT + t_cw[..., None, :]
    Rc = R_cw[..., None, :, :] @ rotations.to(dtype)  # [..., N, 3, 3]
    s = scales.to(dtype)
    M = torch.stack((Rc[..., 0] * s[:, :1], Rc[..., 1] * s[:, 1:], mu), dim=-1)  # columns tu, tv, mu
    return K.to(dtype)[..., None, :, :] @ M, mu


def surfel_footprint(
    T: Tensor, z: Tensor, opacities: Tensor, lowpass_sigma: float | None, rho_scale: float = LOWPASS_RHO_SCALE
) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor, Tensor, Tensor]]:
    """Projected centre [..., N, 2], low-pass centre [..., N, 2] and the continuous pixel box
    (xmin, xmax, ymin, ymax, each [..., N]) where the surfel's alpha can reach ALPHA_MIN, in T's dtype.

    The k-sigma ellipse u^2 + v^2 = k^2 is the conic diag(1, 1, -k^2); its image under T has the dual
    conic T diag(1, 1, -1/k^2) T^T, whose vertical and horizontal tangent lines give the exact
    axis-aligned box (valid while the conic is an ellipse, C22 < 0; unbounded otherwise, the surfel
    crossing the camera plane). The screen-space low-pass filter (rho2d = rho_scale |p - c_lp|^2) widens it
    by its own reach.
    """
    Tx, Ty, Tw = T[..., 0, :], T[..., 1, :], T[..., 2, :]
    k2 = _opacity_extent(opacities, T.dtype)
    D = torch.stack((torch.ones_like(k2), torch.ones_like(k2), -1.0 / k2.clamp_min(1e-12)), dim=-1)
    c00 = (Tx * D * Tx).sum(-1)
    c11 = (Ty * D * Ty).sum(-1)
    c02 = (Tx * D * Tw).sum(-1)
    c12 = (Ty * D * Tw).sum(-1)
    c22 = (Tw * D * Tw).sum(-1)
    bounded = c22 < -1e-12
    safe22 = torch.where(bounded, c22, -torch.ones_like(c22))
    cx_e, cy_e = c02 / safe22, c12 / safe22
    hx = (c02 * c02 - c00 * safe22).clamp_min(0).sqrt() / safe22.abs()
    hy = (c12 * c12 - c11 * safe22).clamp_min(0).sqrt() / safe22.abs()
    # The cross product is expanded around the projected centre (always next to the surfel, so
    # tile offsets stay small); the low-pass term has its own centre (see `RenderConventions`).
    center = projected_center(Tx, Ty, z)
    lowpass = lowpass_center(Tx, Ty, Tw, center, lowpass_sigma)
    r_lp = (k2 / rho_scale).sqrt()  # the screen-space filter's own reach
    inf = torch.full_like(hx, math.inf)
    xmin = torch.minimum(torch.where(bounded, cx_e - hx, -inf), lowpass[..., 0] - r_lp)
    xmax = torch.maximum(torch.where(bounded, cx_e + hx, inf), lowpass[..., 0] + r_lp)
    ymin = torch.minimum(torch.where(bounded, cy_e - hy, -inf), lowpass[..., 1] - r_lp)
    ymax = torch.maximum(torch.where(bounded, cy_e + hy, inf), lowpass[..., 1] + r_lp)
    return center, lowpass, (xmin, xmax, ymin, ymax)


def project_surfels(
    means: Tensor,
    rotations: Tensor,
    scales: Tensor,
    opacities: Tensor,
    sh: Tensor,
    w2c: Tensor,
    K: Tensor,
    cam_center: Tensor,
    width: int,
    height: int,
    settings: TorchRenderSettings,
    filter_zoom: float = 1.0,
) -> Projected:
    """2DGS projection (Huang et al. 2024): T = K [R S e1, R S e2, mu_cam] maps surfel (u, v, 1) to pixels.
    filter_zoom: `render`'s (the low-pass rho2d = 2 |p - c_lp|^2 / filter_zoom^2).

    For pixel p, with T's rows T_x, T_y, T_w, the ray-splat intersection is (u, v) = (h_u x h_v).xy /
    (h_u x h_v).z with h_u = p_x T_w - T_x, h_v = p_y T_w - T_y. The cross product is affine in p:
    h_u x h_v = A + p_x B + p_y C with A = T_x x T_y, B = T_y x T_w, C = T_w x T_x, so every pixel of
    a tile costs one 3x3 matrix product. The intersection's camera z is det(T) / (h_u x h_v).z.
    """
    T, mu = surfel_transforms(means, rotations, scales, w2c, K, torch.float64)
    z = mu[:, 2]
    rho_scale = screen_filter(filter_zoom)[0]
    center, lowpass, bounds = surfel_footprint(T, z, opacities, settings.lowpass_center_sigma, rho_scale)
    box = _pixel_box(*(b.detach() for b in bounds), width, height)

    idx = _cull_and_sort(z.detach(), box, opacities.detach(), settings)
    Tx, Ty, Tw = T[:, 0], T[:, 1], T[:, 2]
    Tx, Ty, Tw, center = _take(Tx, idx), _take(Ty, idx), _take(Tw, idx), _take(center, idx)
    lowpass_shift = _take(lowpass, idx) - center
    B = torch.linalg.cross(Ty, Tw)
    C = torch.linalg.cross(Tw, Tx)
    # Cross product at the projected centre, so that tiles expand it over small offsets only.
    A_c = torch.linalg.cross(Tx, Ty) + center[:, :1] * B + center[:, 1:] * C
    det = (Tw * torch.linalg.cross(Tx, Ty)).sum(-1)
    geometry = torch.cat((A_c, B, C, det[:, None], Tw[:, 2:3], lowpass_shift), dim=-1)  # [M, 13]

    normals = _camera_facing(_take(rotations[:, :, 2], idx), _take(mu, idx).to(means.dtype), w2c[:3, :3])
    colors = _colors(_take(sh, idx), _take(means, idx), cam_center)
    features = torch.cat((colors, normals), dim=-1)
    transform = torch.stack((Tx, Ty, Tw), dim=1)
    with torch.no_grad():
        abs_coef = _abs_coefficients(Tx, Ty, Tw, center, settings.lowpass_center_sigma)
    return Projected(idx, center, geometry, _take(opacities, idx), features, box[idx], transform, abs_coef, rho_scale)


def _abs_coefficients(Tx: Tensor, Ty: Tensor, Tw: Tensor, center: Tensor, sigma: float | None) -> Tensor:
    """[M, 5] per-surfel constants of the per-pixel centre gradients (`_abs_centre_gradients`):
    U = (c_x T_w - T_x)[:2] and V = (c_y T_w - T_y)[:2], so that h_u = p_x T_w - T_x and h_v = p_y T_w - T_y
    are U + dx T_w and V + dy T_w at the pixel's offset (dx, dy) from the centre c, and k = d c_lp,x / d T_x[2]
    = d c_lp,y / d T_y[2] of the low-pass centre (`lowpass_center`): e T_w[2] / C22 for the box centre,
    1 / z for the projected one."""
    z = Tw[:, 2]
    U = center[:, :1] * Tw[:, :2] - Tx[:, :2]
    V = center[:, 1:] * Tw[:, :2] - Ty[:, :2]
    safe_z = torch.where(z.abs() > 1e-12, z, torch.ones_like(z))
    k = 1.0 / safe_z
    if sigma is not None:
        e = -1.0 / (sigma * sigma)
        c22 = Tw[:, 0] * Tw[:, 0] + Tw[:, 1] * Tw[:, 1] + e * z * z
        bounded = c22 < -1e-12
        k = torch.where(bounded, e * z / torch.where(bounded, c22, -torch.ones_like(c22)), k)
    return torch.cat((U, V, k[:, None]), dim=-1)


def ewa_conics(
    means: Tensor,
    covariances: Tensor,
    w2c: Tensor,
    K: Tensor,
    width: int,
    height: int,
    jacobian_clamp: float | None,
    dtype: torch.dtype,
    dilation: float = EWA_DILATION,
) -> tuple[Tensor, Tensor, Tensor, tuple[Tensor, Tensor, Tensor]]:
    """3DGS's projection: camera-frame means [..., N, 3], centre [..., N, 2], conic [..., N, 3] (the inverse 2D
    covariance's a, b, c) and the dilated 2D covariance (a, b, c), in `dtype`.

    Sigma' = J W Sigma W^T J^T + 0.3 I (`dilation`) with the affine (local) Jacobian J at the mean; the
    leading dimensions are the cameras' (w2c [..., 4, 4], K [..., 3, 3]).
    """
    R_cw, t_cw = w2c[..., :3, :3].to(dtype), w2c[..., :3, 3].to(dtype)
    mu = means.to(dtype) @ R_cw.mT + t_cw[..., None, :]
    z = mu[..., 2]
    safe_z = torch.where(z.abs() > 1e-12, z, torch.ones_like(z))
    K = K.to(dtype)
    fx, fy, cx, cy, skew = (K[..., i, j, None] for i, j in ((0, 0), (1, 1), (0, 2), (1, 2), (0, 1)))
    x, y = mu[..., 0] / safe_z, mu[..., 1] / safe_z
    center = torch.stack((fx * x + skew * y + cx, fy * y + cy), dim=-1)
    if jacobian_clamp is not None:  # 3DGS: the Jacobian is taken at a point kept near the view
        lim_x = jacobian_clamp * width / (2 * fx)
        lim_y = jacobian_clamp * height / (2 * fy)
        x, y = x.clamp(-lim_x, lim_x), y.clamp(-lim_y, lim_y)
    zero = torch.zeros_like(z)
    # d(pixel)/d(camera point) at the (clamped) mean.
    J = torch.stack(
        (
            torch.stack((fx / safe_z, skew / safe_z, -(fx * x + skew * y) / safe_z), dim=-1),
            torch.stack((zero, fy / safe_z, -fy * y / safe_z), dim=-1),
        ),
        dim=-2,
    )  # [..., N, 2, 3]
    JW = J @ R_cw[..., None, :, :]
    cov2d = JW @ covariances.to(dtype) @ JW.transpose(-1, -2)
    a = cov2d[..., 0, 0] + dilation
    b = cov2d[..., 0, 1]
    c = cov2d[..., 1, 1] + dilation
    det = (a * c - b * b).clamp_min(1e-20)
    conic = torch.stack((c / det, -b / det, a / det), dim=-1)  # inverse of [[a, b], [b, c]]
    return mu, center, conic, (a, b, c)


def ewa_pixel_box(
    center: Tensor, cov2d: tuple[Tensor, Tensor, Tensor], opacities: Tensor, width: int, height: int, support: str
) -> Tensor:
    """[..., N, 4] inclusive pixel box (col0, col1, row0, row1) an EWA Gaussian reaches (`ewa_support`)."""
    a, b, c = (t.detach() for t in cov2d)
    center = center.detach()
    if support == "release":
        return _release_tile_box(center, a, b, c, width, height)
    k2 = _opacity_extent(opacities, center.dtype)
    hx, hy = (k2 * a).sqrt(), (k2 * c).sqrt()
    x, y = center[..., 0], center[..., 1]
    return _pixel_box(x - hx, x + hx, y - hy, y + hy, width, height)


def project_ewa(
    means: Tensor,
    covariances: Tensor,
    normals: Tensor,
    opacities: Tensor,
    sh: Tensor,
    w2c: Tensor,
    K: Tensor,
    cam_center: Tensor,
    width: int,
    height: int,
    settings: TorchRenderSettings,
    filter_zoom: float = 1.0,
) -> Projected:
    """3DGS projection: Sigma' = J W Sigma W^T J^T + 0.3 I with the affine (local) Jacobian J at the mean
    (0.3 filter_zoom^2: `render`'s filter_zoom)."""
    mu, center, conic, cov2d = ewa_conics(
        means,
        covariances,
        w2c,
        K,
        width,
        height,
        settings.ewa_jacobian_clamp,
        torch.float64,
        screen_filter(filter_zoom)[1],
    )
    z = mu[:, 2]
    box = ewa_pixel_box(center, cov2d, opacities, width, height, settings.ewa_support)
    idx = _cull_and_sort(z.detach(), box, opacities.detach(), settings)
    n = _camera_facing(_take(normals, idx), _take(mu, idx).to(means.dtype), w2c[:3, :3])
    colors = _colors(_take(sh, idx), _take(means, idx), cam_center)
    features = torch.cat((colors, n, _take(z, idx)[:, None].to(means.dtype)), dim=-1)
    return Projected(idx, _take(center, idx), _take(conic, idx), _take(opacities, idx), features, box[idx])


# ---------------------------------------------------------------------------------------------
# Binning
# ---------------------------------------------------------------------------------------------


@dataclass
class Bins:
    gaussian: Tensor  # [P] projected-Gaussian index per (tile, Gaussian) pair, sorted by tile then depth
    start: Tensor  # [T] first pair of each tile
    count: Tensor  # [T] pairs per tile
    tiles_x: int
    tiles_y: int


def bin_tiles(box: Tensor, width: int, height: int, tile: int) -> Bins:
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    tx0, tx1 = box[:, 0] // tile, box[:, 1] // tile
    ty0, ty1 = box[:, 2] // tile, box[:, 3] // tile
    nx, ny = tx1 - tx0 + 1, ty1 - ty0 + 1
    per_gaussian = nx * ny
    gid = torch.repeat_interleave(torch.arange(box.shape[0], device=box.device), per_gaussian)
    first = torch.cumsum(per_gaussian, 0) - per_gaussian
    local = torch.arange(gid.shape[0], device=box.device) - first[gid]
    tile_id = (ty0[gid] + local // nx[gid]) * tiles_x + tx0[gid] + local % nx[gid]
    # Gaussians are already front to back, so a stable sort by tile keeps depth order within a tile.
    tile_sorted, order = torch.sort(tile_id, stable=True)
    count = torch.bincount(tile_sorted, minlength=tiles_x * tiles_y)
    start = torch.cumsum(count, 0) - count
    return Bins(gid[order], start, count, tiles_x, tiles_y)


# ---------------------------------------------------------------------------------------------
# Compositing
# ---------------------------------------------------------------------------------------------


def _tile_basis(mode: RenderMode, tile: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """Polynomial terms of the pixel-centre offsets (dx, dy) inside a tile, pixels row-major.

    surfel: [5, P] rows 1, dx, dy, dx^2 + dy^2, 0;  ewa: [6, P] rows 1, dx, dy, dx^2, dx dy, dy^2.
    """
    r = torch.arange(tile, dtype=dtype, device=device) + 0.5
    dy, dx = (t.reshape(-1) for t in torch.meshgrid(r, r, indexing="ij"))
    one = torch.ones_like(dx)
    if mode == "surfel":
        return torch.stack((one, dx, dy, dx * dx + dy * dy, torch.zeros_like(dx)))
    return torch.stack((one, dx, dy, dx * dx, dx * dy, dy * dy))


def _pair_coefficients(
    mode: RenderMode, geometry: Tensor, offset: Tensor, lowpass: float = LOWPASS_RHO_SCALE
) -> tuple[Tensor, Tensor | None]:
    """Per-pair polynomial coefficients in the tile-local pixel offsets (autograd-tracked, [n, k]-sized).

    geometry: [n, k, G]; offset: [n, k, 2] = tile origin - projected centre.
    surfel: [4, n, k, 5] coefficients of the planes hx, hy, hz (h = A + dx B + dy C, the cross
            product at the tile origin expanded over the pixel offsets) and rho2d = lowpass |p - c_lp|^2
            (c_lp = projected centre + the geometry's low-pass shift), plus depth parameters
            [n, k, 2] = (det T, centre depth).
    ewa:    [n, k, 6] coefficients of rho = d^T conic d with d = offset + (dx, dy).
    """
    ex, ey = offset[..., 0], offset[..., 1]
    if mode == "surfel":
        A_c, B, C = geometry[..., 0:3], geometry[..., 3:6], geometry[..., 6:9]
        A = A_c + ex[..., None] * B + ey[..., None] * C
        lx, ly = ex - geometry[..., 11], ey - geometry[..., 12]  # tile origin - low-pass centre
        zero = torch.zeros_like(ex)
        coef = torch.stack(
            (
                torch.stack((A[..., 0], B[..., 0], C[..., 0], zero, zero), -1),
                torch.stack((A[..., 1], B[..., 1], C[..., 1], zero, zero), -1),
                torch.stack((A[..., 2], B[..., 2], C[..., 2], zero, zero), -1),
                lowpass * torch.stack((lx * lx + ly * ly, 2 * lx, 2 * ly, zero + 1, zero), -1),
            )
        )
        return coef, geometry[..., 9:11]
    ca, cb, cc = geometry[..., 0], geometry[..., 1], geometry[..., 2]
    coef = torch.stack(
        (
            ca * ex * ex + 2 * cb * ex * ey + cc * ey * ey,
            2 * (ca * ex + cb * ey),
            2 * (cb * ex + cc * ey),
            ca,
            2 * cb,
            cc,
        ),
        dim=-1,
    )
    return coef, None


def _block_state(
    coef: Tensor, depth_params: Tensor | None, log_opacity: Tensor, transmittance: Tensor, done: Tensor, basis: Tensor
):
    """Everything [n, k, P]-sized for one block, computed with in-place ops (no autograd).

    Returns a dict with alpha, one_minus, trans_excl, weight, keep, saturated (alpha clamped),
    depth (surfel), use3d/inv_hz (surfel), rho, and the block's transmittance after.
    """
    n, k = log_opacity.shape
    st: dict[str, Tensor] = {}
    if depth_params is not None:  # surfel
        hx, hy, hz, rho2d = (coef.reshape(4, n * k, -1) @ basis).reshape(4, n, k, -1).unbind(0)
        a = hx * hx
        a.addcmul_(hy, hy)
        # min(rho3d, rho2d) without dividing where the ray grazes the splat (hz -> 0): the 3D
        # branch is taken only where a < rho2d hz^2, which implies hz != 0.
        use3d = a < rho2d * (hz * hz)
        inv_hz = torch.where(use3d, hz, math.inf).reciprocal_()  # 1 / hz on the 3D branch, else 0
        rho = torch.where(use3d, a.mul_(inv_hz).mul_(inv_hz), rho2d)
        # 2DGS: the depth of the ray-splat intersection, det(T) / hz; the centre depth where the filter wins.
        det, mu_z = depth_params[..., 0:1], depth_params[..., 1:2]
        depth = torch.where(use3d, det * inv_hz, mu_z)
        st.update(hx=hx, hy=hy, use3d=use3d, inv_hz=inv_hz, depth=depth)
    else:
        rho = (coef.reshape(n * k, -1) @ basis).reshape(n, k, -1)
    st["rho"] = rho
    log_alpha = torch.add(log_opacity[..., None], rho, alpha=-0.5)  # log(o exp(-rho / 2))
    alpha = torch.exp(log_alpha)
    saturated = alpha > ALPHA_MAX
    alpha.clamp_max_(ALPHA_MAX).masked_fill_(log_alpha < LOG_ALPHA_MIN, 0.0)  # [n, k, P]
    one_minus = 1 - alpha
    trans_incl = torch.cumprod(one_minus, dim=1).mul_(transmittance[:, None, :])
    # 3DGS/2DGS rule: a Gaussian that would push transmittance below the floor ends the pixel and
    # is itself not blended, nor is anything behind it (`done` carries that across depth blocks);
    # transmittance only falls, so `keep` is a prefix along the depth axis.
    keep = (trans_incl >= TRANSMITTANCE_MIN).logical_and_(~done[:, None, :])
    trans_excl = trans_incl.div_(one_minus)  # transmittance in front of each Gaussian
    weight = (alpha * trans_excl).masked_fill_(~keep, 0.0)
    st.update(alpha=alpha, saturated=saturated, one_minus=one_minus, trans_excl=trans_excl, keep=keep, weight=weight)
    st["trans_out"] = transmittance - weight.sum(1)
    st["done_out"] = ~keep[:, -1, :]
    return st


class _CompositeBlock(torch.autograd.Function):
    """Front-to-back compositing of one block, with a hand-derived backward pass.

    The backward recomputes the block from its small inputs instead of storing [n, k, P]
    intermediates, so memory stays bounded by one block whatever the image size (as the CUDA
    rasterizers do), and it uses the closed-form gradient of alpha compositing:
      w_i = a_i T_i,  T_i = T_in prod_{j<i} (1 - a_j),  out = sum_i w_i v_i,  T_out = T_in prod_i (1 - a_i)
      d out / d a_i = T_i v_i - (sum_{j>i} w_j v_j) / (1 - a_i),   d T_out / d a_i = -T_out / (1 - a_i).

    `probe` [n, k, 2] (surfels, or None): rows of the absolute screen gradient's probe, whose "gradient"
    is the sum over the block's pixels of |dL_p / dc| (`_abs_centre_gradients`, with `abs_rows` its
    per-pair constants); nothing of it is computed when None.
    """

    @staticmethod
    def forward(ctx, coef, depth_params, log_opacity, features, transmittance, done, basis, probe=None, abs_rows=None):
        st = _block_state(coef, depth_params, log_opacity, transmittance, done, basis)
        feats = st["weight"].transpose(1, 2) @ features  # [n, P, F]
        depth = (st["weight"] * st["depth"]).sum(1) if depth_params is not None else torch.zeros_like(transmittance)
        ctx.save_for_backward(
            coef, depth_params, log_opacity, features, transmittance, done, basis, st["trans_out"], abs_rows
        )
        ctx.mark_non_differentiable(st["done_out"])
        return st["trans_out"], st["done_out"], feats, depth

    @staticmethod
    def backward(ctx, g_trans, _g_done, g_feats, g_depth):
        coef, depth_params, log_opacity, features, transmittance, done, basis, trans_out, abs_rows = ctx.saved_tensors
        surfel = depth_params is not None
        st = _block_state(coef, depth_params, log_opacity, transmittance, done, basis)
        w, alpha = st["weight"], st["alpha"]
        # Gradient of the loss with respect to each blending weight w_i.
        g_w = features @ g_feats.transpose(1, 2)  # [n, k, P]
        if surfel:
            g_w.addcmul_(st["depth"], g_depth[:, None, :])
        g_features = w @ g_feats  # [n, k, F]
        contrib = g_w * w  # w_j (dL/dw_j)
        total = contrib.sum(1)  # [n, P]
        behind = total[:, None, :] - contrib.cumsum(1)  # sum over j > i
        behind.add_((g_trans * trans_out)[:, None, :])
        g_alpha = (g_w * st["trans_excl"]).sub_(behind.div_(st["one_minus"])).masked_fill_(~st["keep"], 0.0)
        g_transmittance = (total + g_trans * trans_out) / transmittance
        # alpha = min(exp(log_alpha), 0.99) where log_alpha >= log(1/255), else 0.
        g_log_alpha = g_alpha.mul_(alpha).masked_fill_(st["saturated"], 0.0)
        g_log_opacity = g_log_alpha.sum(-1)
        g_rho = g_log_alpha.mul_(-0.5)
        n, k = log_opacity.shape
        if not surfel:
            g_coef = (g_rho.reshape(n * k, -1) @ basis.T).reshape(coef.shape)
            return g_coef, None, g_log_opacity, g_features, g_transmittance, None, None, None, None
        use3d, inv_hz, hx, hy = st["use3d"], st["inv_hz"], st["hx"], st["hy"]
        # rho = (hx^2 + hy^2) / hz^2 on the 3D branch, rho2d elsewhere; depth = det / hz or mu_z.
        g_depth_pair = w.mul_(g_depth[:, None, :])
        g_det_pair = g_depth_pair * inv_hz  # [n, k, P] dL/ddet pixel by pixel
        g_det = g_det_pair.sum(-1)
        g_mu_z = g_depth_pair.sum(-1) - torch.where(use3d, g_depth_pair, 0.0).sum(-1)
        g_planes = torch.empty(4, n, k, g_rho.shape[-1], dtype=g_rho.dtype, device=g_rho.device)
        g_r = torch.mul(g_rho, inv_hz).mul_(inv_hz).mul_(2)  # d rho / d hx = 2 hx / hz^2
        torch.mul(g_r, hx, out=g_planes[0])
        torch.mul(g_r, hy, out=g_planes[1])
        # d rho / d hz = -2 rho / hz; d depth / d hz = -depth / hz (both zero off the 3D branch).
        torch.mul(g_rho, st["rho"], out=g_planes[2]).mul_(-2).sub_(g_depth_pair.mul_(st["depth"])).mul_(inv_hz)
        g_planes[3].copy_(g_rho).masked_fill_(use3d, 0.0)
        g_probe = None if abs_rows is None else _abs_centre_gradients(g_planes, g_det_pair, abs_rows, basis)
        g_coef = (g_planes.reshape(4, n * k, -1) @ basis.T).reshape(coef.shape)
        g_depth_params = torch.stack((g_det, g_mu_z), dim=-1)
        return g_coef, g_depth_params, g_log_opacity, g_features, g_transmittance, None, None, g_probe, None


def _abs_centre_gradients(g_planes: Tensor, g_det: Tensor, abs_rows: Tensor, basis: Tensor) -> Tensor:
    """[n, k, 2] the sums over a block's pixels of |dL_p / dc_x| and |dL_p / dc_y|: each pixel's own share
    of the gradient with respect to the surfel's projected centre c in pixels, the surfel moved parallel
    to the image at its depth z (AbsGS, Ye et al. 2024; gsplat's `absgrad`, per axis, then summed).

    Moving c by (dx, dy) at depth z moves T's third column by z (dx, dy, 0) (T = K [.., .., mu_cam] and
    c = (T_x[2], T_y[2]) / z), so dL_p/dc = z (dL_p/dT_x[2], dL_p/dT_y[2]) - gsplat's 2DGS densification
    gradient (`gradient_2dgs`, z times the third entries of dL/dT) pixel by pixel. With h = h_u x h_v,
    h_u = p_x T_w - T_x, h_v = p_y T_w - T_y, det = T_w . (T_x x T_y) and the low-pass centre c_lp:
      dL_p/dT_x[2] = (g_h x h_v)_z + g_det B_z + k g_lp,x,   dL_p/dT_y[2] = (h_u x g_h)_z + g_det C_z + k g_lp,y
    (B = T_y x T_w, C = T_w x T_x, k = `_abs_coefficients`'s), where g_h = dL_p/dh on the ray-splat branch
    and g_lp = dL_p/dc_lp = -2 S (p - c_lp) dL_p/drho2d on the filter's. g_planes [4, n, k, P]: dL_p/dh
    (3) and dL_p/drho2d; g_det [n, k, P]; abs_rows [n, k, 9 + G]: U (2), V (2), T_w[:2], k, the tile
    origin's offset from c (2), then the pair's geometry row (B at 3:6, C at 6:9, z at 10, c_lp - c at 11:13).
    """
    U0, U1, V0, V1, tw0, tw1, k, ex, ey = (abs_rows[..., j : j + 1] for j in range(9))
    geo = abs_rows[..., 9:]
    B2, C2, z, sx, sy = (geo[..., j : j + 1] for j in (5, 8, 10, 11, 12))
    dx = ex + basis[1]  # [n, k, P] each pixel centre's offset from c
    dy = ey + basis[2]
    g_hx, g_hy, _, g_rho2d = g_planes.unbind(0)
    g_lp = g_rho2d * (-2.0 * LOWPASS_RHO_SCALE)
    gx = g_hx * (V1 + dy * tw1) - g_hy * (V0 + dy * tw0) + g_det * B2 + k * g_lp * (dx - sx)
    gy = (U0 + dx * tw0) * g_hy - (U1 + dx * tw1) * g_hx + g_det * C2 + k * g_lp * (dy - sy)
    return torch.stack((gx.abs().sum(-1), gy.abs().sum(-1)), dim=-1) * z


def _distortion_block(coef, depth_params, log_opacity, transmittance, moment, done, basis):
    """One block's share of 2DGS's depth distortion, in plain autograd-tracked ops (the reference).

    Recomputes the block's blending weights w_i = a_i T_i with the rules of `_block_state`, from its
    own transmittance `transmittance` [n, P] (differentiable, unlike the `done` mask), and walks
    front to back with two running moments, A_i = 1 - T_i (the weights in front) and M_i = sum_{j<i}
    w_j z_j: D += 2 w_i (z_i A_i - M_i), z the centre depth. Returns the transmittance and moment
    after the block and the block's D [n, P]. `composite` runs it under activation checkpointing, so
    its [n, k, P] intermediates live only while one block is (re)computed.
    """
    n, k = log_opacity.shape
    hx, hy, hz, rho2d = (coef.reshape(4, n * k, -1) @ basis).reshape(4, n, k, -1).unbind(0)
    q = hx * hx + hy * hy
    use3d = (q < rho2d * (hz * hz)).detach()
    inv_hz = torch.where(use3d, hz, torch.ones_like(hz)).reciprocal()  # no division off the 3D branch
    rho = torch.where(use3d, q * inv_hz * inv_hz, rho2d)
    log_alpha = log_opacity[..., None] - 0.5 * rho
    alpha = torch.where(log_alpha < LOG_ALPHA_MIN, 0.0, torch.exp(log_alpha).clamp_max(ALPHA_MAX))
    one_minus = 1 - alpha
    trans_incl = torch.cumprod(one_minus, dim=1) * transmittance[:, None, :]
    keep = ((trans_incl >= TRANSMITTANCE_MIN) & ~done[:, None, :]).detach()
    trans_excl = trans_incl / one_minus
    w = torch.where(keep, alpha * trans_excl, 0.0)
    z = depth_params[..., 1:2]  # [n, k, 1] centre depth
    wz = w * z
    moment_excl = moment[:, None, :] + wz.cumsum(1) - wz
    D = 2 * (w * (z * (1 - trans_excl) - moment_excl)).sum(1)
    return transmittance - w.sum(1), moment + wz.sum(1), D


def composite(
    mode: RenderMode,
    proj: Projected,
    bins: Bins,
    width: int,
    height: int,
    settings: TorchRenderSettings,
    distortion: bool = False,
    abs_probe: Tensor | None = None,
) -> tuple[Tensor, ...]:
    """Returns per-pixel (features [H, W, F], alpha [H, W], surfel depth sum [H, W]) before normalization,
    and with `distortion` (surfel mode) 2DGS's depth distortion [H, W] (`_distortion_block`).
    `abs_probe` [N, 2] (surfels, or None): a zero tensor whose gradient becomes each surfel's sum over the
    pixels of |dL_p / dc| (`_abs_centre_gradients`)."""
    tile = settings.tile_size
    P = tile * tile
    dtype = proj.features.dtype
    device = proj.features.device
    F_ = proj.features.shape[1]
    n_tiles = bins.tiles_x * bins.tiles_y
    basis = _tile_basis(mode, tile, dtype, device)
    # One table row per Gaussian so each block needs a single gather. The projected centre is
    # split into a working-precision value and its remainder, so tile offsets stay exact to
    # float64 accuracy on large images.
    center_hi = proj.center.to(dtype)
    center_lo = (proj.center - center_hi.to(proj.center.dtype)).to(dtype)
    G = proj.geometry.shape[1]
    table = torch.cat(
        (proj.geometry.to(dtype), proj.features, torch.log(proj.opacity)[:, None], center_hi, center_lo), dim=1
    )  # [M, G + F + 5]
    if abs_probe is not None:
        probe_sorted = _take(abs_probe, proj.index)  # [M, 2]
        # U, V, T_w[:2], k (slices, not a list index: that would be a host tensor on another device)
        coef = proj.abs_coef.to(dtype)
        abs_table = torch.cat((coef[:, :4], proj.transform[:, 2, :2].detach().to(dtype), coef[:, 4:5]), dim=1)

    tile_feats = torch.zeros(n_tiles, P, F_, dtype=dtype, device=device)
    tile_depth = torch.zeros(n_tiles, P, dtype=dtype, device=device)
    tile_trans = torch.ones(n_tiles, P, dtype=dtype, device=device)
    tile_dist = torch.zeros(n_tiles, P, dtype=dtype, device=device)

    counts = bins.count
    order = torch.argsort(counts, descending=True, stable=True)
    order = order[counts[order] > 0]
    counts_sorted = counts[order].tolist()
    block_k_cap = max(1, min(settings.max_block_depth, settings.block_elements // P))
    i = 0
    results: list[tuple[Tensor, ...]] = []
    while i < len(order):
        k_max = counts_sorted[i]
        kb = min(k_max, block_k_cap)
        n_group = max(1, settings.block_elements // (kb * P))
        group = order[i : i + n_group]
        i += group.shape[0]
        g_start, g_count = bins.start[group], bins.count[group]
        tiles_x = group % bins.tiles_x
        tiles_y = group // bins.tiles_x
        origin = torch.stack((tiles_x * tile, tiles_y * tile), dim=-1).to(dtype)  # [n, 2]
        trans = torch.ones(group.shape[0], P, dtype=dtype, device=device)
        done = torch.zeros(group.shape[0], P, dtype=torch.bool, device=device)
        feats = torch.zeros(group.shape[0], P, F_, dtype=dtype, device=device)
        depth = torch.zeros(group.shape[0], P, dtype=dtype, device=device)
        if distortion:  # the distortion's own differentiable transmittance, running moment and sum
            d_trans, d_moment, dist = trans, torch.zeros_like(trans), torch.zeros_like(trans)
        for k0 in range(0, k_max, kb):
            slot = k0 + torch.arange(kb, device=device)
            valid = slot[None, :] < g_count[:, None]  # [n, kb]
            if not bool(valid.any()):
                break
            pair = (g_start[:, None] + slot[None, :]).clamp_max(max(bins.gaussian.shape[0] - 1, 0))
            gi = torch.where(valid, bins.gaussian[pair], torch.zeros_like(pair))
            rows = _take(table, gi)  # [n, kb, G + F + 5]
            offset = (origin[:, None, :] - rows[..., -4:-2]) - rows[..., -2:]
            log_opac = torch.where(valid, rows[..., G + F_], -math.inf)
            coef, depth_params = _pair_coefficients(mode, rows[..., :G], offset, proj.lowpass)
            if distortion:
                d_trans, d_moment, dist_blk = torch.utils.checkpoint.checkpoint(
                    _distortion_block, coef, depth_params, log_opac, d_trans, d_moment, done, basis, use_reentrant=False
                )
                dist = dist + dist_blk
            probe = abs_rows = None
            if abs_probe is not None:
                probe = _take(probe_sorted, gi)
                abs_rows = torch.cat((_take(abs_table, gi), offset.detach(), rows[..., :G].detach()), dim=-1)
            trans, done, f_blk, d_blk = _CompositeBlock.apply(
                coef, depth_params, log_opac, rows[..., G : G + F_], trans, done, basis, probe, abs_rows
            )
            feats = feats + f_blk
            depth = depth + d_blk
            if bool(done.all()):
                break  # every pixel of the group is saturated: later blocks get zero weight (and gradient)
        results.append((group, feats, depth, trans, dist) if distortion else (group, feats, depth, trans))

    if results:
        groups = torch.cat([r[0] for r in results])
        tile_feats = tile_feats.index_copy(0, groups, torch.cat([r[1] for r in results]))
        tile_depth = tile_depth.index_copy(0, groups, torch.cat([r[2] for r in results]))
        tile_trans = tile_trans.index_copy(0, groups, torch.cat([r[3] for r in results]))
        if distortion:
            tile_dist = tile_dist.index_copy(0, groups, torch.cat([r[4] for r in results]))

    def untile(x: Tensor) -> Tensor:  # [tiles, P, ...] -> [H, W, ...]
        extra = x.shape[2:]
        x = x.reshape(bins.tiles_y, bins.tiles_x, tile, tile, *extra)
        x = x.transpose(1, 2).reshape(bins.tiles_y * tile, bins.tiles_x * tile, *extra)
        return x[:height, :width]

    if distortion:
        return untile(tile_feats), 1 - untile(tile_trans), untile(tile_depth), untile(tile_dist)
    return untile(tile_feats), 1 - untile(tile_trans), untile(tile_depth)


def project(
    means: Tensor,
    rotations: Tensor,
    scales: Tensor,
    covariances: Tensor | None,
    opacities: Tensor,
    sh: Tensor,
    w2c: Tensor,
    K: Tensor,
    cam_center: Tensor,
    width: int,
    height: int,
    mode: RenderMode,
    settings: TorchRenderSettings,
    filter_zoom: float = 1.0,
) -> Projected:
    """One camera's projection in either mode (covariances: the EWA mode's, None for surfels)."""
    if mode == "surfel":
        return project_surfels(
            means, rotations, scales, opacities, sh, w2c, K, cam_center, width, height, settings, filter_zoom
        )
    assert covariances is not None
    return project_ewa(
        means, covariances, rotations[:, :, 2], opacities, sh, w2c, K, cam_center, width, height, settings, filter_zoom
    )


def render_torch(
    means: Tensor,
    rotations: Tensor,
    scales: Tensor,
    covariances: Tensor | None,
    opacities: Tensor,
    sh: Tensor,
    w2c: Tensor,
    K: Tensor,
    cam_center: Tensor,
    width: int,
    height: int,
    mode: RenderMode,
    settings: TorchRenderSettings,
    distortion: bool = False,
    abs_probe: Tensor | None = None,
    filter_zoom: float = 1.0,
) -> tuple[Tensor, ...]:
    """Render one camera. Returns un-normalized (color [H, W, 3], alpha [H, W], depth [H, W], normal [H, W, 3])
    and, with `distortion` (surfel mode), 2DGS's depth distortion [H, W]. `abs_probe`: see `composite`;
    `filter_zoom`: `render`'s."""
    proj = project(
        means, rotations, scales, covariances, opacities, sh, w2c, K, cam_center, width, height, mode, settings,
        filter_zoom,
    )  # fmt: skip
    bins = bin_tiles(proj.pixel_box, width, height, settings.tile_size)
    feats, alpha, depth_sum, *dist = composite(mode, proj, bins, width, height, settings, distortion, abs_probe)
    color, normal = feats[..., 0:3], feats[..., 3:6]
    depth = feats[..., 6] if mode == "ewa" else depth_sum
    return color, alpha, depth, normal, *dist
