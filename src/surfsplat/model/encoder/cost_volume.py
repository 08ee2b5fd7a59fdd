"""Multi-view branch, step 3: plane-sweep cost volume over inverse-depth candidates (Appendix A).

For reference view i and each partner view j, the partner's features are warped into view i at
every candidate depth d_m and compared with view i's features by a scaled dot product:

    C^i[m, y, x] = mean_j  < F^i(y, x), F^{j->i}_{d_m}(y, x) > / sqrt(channels)

As in the release, pixel (x, y) of the feature map sits at integer coordinates of the intrinsics
scaled to the feature resolution, the *reference* intrinsics are used to project into the partner
view, and sampling is bilinear with zero padding (align_corners=True). The warp is evaluated in
chunks of depth candidates so the [C, D, H, W] warped volume is never held whole.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

# Bytes of warped features held at once; the correlation is identical for any chunking.
WARP_CHUNK_BYTES = 16 * 2**20
# Bytes of pixel-pair correlations `gathered_cost_volume` holds at once (any blocking is exact).
CORRELATION_CHUNK_BYTES = 64 * 2**20
# Pixels per depth candidate below which the gathered formulation is faster than warping (measured
# with benchmarks/cost_volume.py on an AVX-512 CPU; see `prefers_gathered_cost_volume`).
GATHER_BREAK_EVEN = 64


def linear_inverse_depth_candidates(inv_min: Tensor, inv_max: Tensor, count: int) -> Tensor:
    """[N, D] candidates linear in inverse depth from inv_min (far plane) to inv_max (near plane)."""
    t = torch.linspace(0, 1, count, device=inv_min.device, dtype=inv_min.dtype)
    return inv_min[:, None] + t * (inv_max - inv_min)[:, None]


def local_inverse_depth_candidates(
    inv_depth: Tensor, inv_min: Tensor, inv_max: Tensor, count: int, interval: Tensor
) -> Tensor:
    """[N, D, H, W] per-pixel candidates around a coarse inverse depth (the cascade's finer scale).

    inv_depth [N, 1, H, W]; interval [N] candidate spacing. The window spans count/2 intervals
    below and count/2 - 1 above, clamped to the global range, then resampled linearly.
    """
    interval = interval.view(-1, 1, 1, 1)
    low = (inv_depth - interval * (count // 2)).clamp(min=inv_min.view(-1, 1, 1, 1))
    high = (inv_depth + interval * (count // 2 - 1)).clamp(max=inv_max.view(-1, 1, 1, 1))
    t = torch.linspace(0, 1, count, device=inv_depth.device, dtype=inv_depth.dtype).view(1, count, 1, 1)
    return low + t * (high - low)


def _source_pixels(K: Tensor, ref_to_src: Tensor, depth: Tensor, height: int, width: int) -> Tensor:
    """[N, 2, D, H*W] pixel positions (x, y) in the source view of every reference pixel and depth.

    K [N, 3, 3] reference intrinsics at feature resolution; ref_to_src [N, 4, 4];
    depth [N, D, H*W] (broadcast over pixels when the last dim is 1).
    """
    n = K.shape[0]
    ys, xs = torch.meshgrid(
        torch.arange(height, device=K.device, dtype=K.dtype),
        torch.arange(width, device=K.device, dtype=K.dtype),
        indexing="ij",
    )
    pixels = torch.stack((xs, ys, torch.ones_like(xs))).reshape(1, 3, -1).expand(n, -1, -1)
    # inv_ex: the same inverse without reading its error flag on the host (a GPU would wait for it)
    rays = ref_to_src[:, :3, :3] @ (torch.linalg.inv_ex(K).inverse @ pixels)  # [N, 3, H*W]
    points = rays[:, :, None, :] * depth[:, None] + ref_to_src[:, :3, 3, None, None]  # [N, 3, D, H*W]
    proj = (K @ points.flatten(2)).view(n, 3, -1, height * width)
    return proj[:, :2] / proj[:, 2:].clamp(min=1e-3)


def _sampling_grid(K: Tensor, ref_to_src: Tensor, depth: Tensor, height: int, width: int) -> Tensor:
    """[N, D, H, W, 2] positions of `_source_pixels` normalised for grid_sample (align_corners=True)."""
    n = K.shape[0]
    xy = _source_pixels(K, ref_to_src, depth, height, width)
    gx = 2 * xy[:, 0] / (width - 1) - 1
    gy = 2 * xy[:, 1] / (height - 1) - 1
    return torch.stack((gx, gy), dim=-1).view(n, -1, height, width, 2)


def plane_sweep_cost_volume(
    ref: Tensor, src: Tensor, K: Tensor, ref_c2w: Tensor, src_c2w: Tensor, inv_depth: Tensor
) -> Tensor:
    """Correlation cost volume averaged over partner views.

    ref:      [N, C, H, W]     reference features
    src:      [N, M, C, H, W]  features of the M partner views
    K:        [N, 3, 3]        reference intrinsics at feature resolution (pixels)
    ref_c2w:  [N, 4, 4], src_c2w: [N, M, 4, 4] camera-to-world
    inv_depth:[N, D] or [N, D, H, W] inverse-depth candidates
    returns   [N, D, H, W]
    """
    n, m, c, h, w = src.shape
    d = inv_depth.shape[1]
    with torch.no_grad():
        # relative pose: reference camera -> partner camera
        ref_to_src = torch.linalg.inv_ex(src_c2w).inverse @ ref_c2w[:, None]  # [N, M, 4, 4]
        depth = 1.0 / inv_depth.reshape(n, d, -1)  # [N, D, 1] or [N, D, H*W]
        grid = _sampling_grid(
            K.repeat_interleave(m, 0), ref_to_src.flatten(0, 1), depth.repeat_interleave(m, 0), h, w
        )  # [N*M, D, H, W, 2]
    src_flat = src.flatten(0, 1)
    ref_rep = ref.repeat_interleave(m, 0)[:, :, None]  # [N*M, C, 1, H, W]
    per_depth_bytes = n * m * c * h * w * src.element_size()
    chunk = max(1, min(d, WARP_CHUNK_BYTES // max(per_depth_bytes, 1)))
    costs = []
    for start in range(0, d, chunk):
        g = grid[:, start : start + chunk]
        dc = g.shape[1]
        warped = F.grid_sample(
            src_flat, g.reshape(n * m, dc * h, w, 2), mode="bilinear", padding_mode="zeros", align_corners=True
        ).view(n * m, c, dc, h, w)
        if torch.is_grad_enabled():
            costs.append((warped * ref_rep).sum(1))  # [N*M, dc, H, W]
        else:  # in place: no second chunk-sized buffer
            costs.append(warped.mul_(ref_rep).sum(1))
    cost = torch.cat(costs, dim=1)
    return (cost / c**0.5).view(n, m, d, h, w).mean(1)


def gathered_cost_volume(
    ref: Tensor, src: Tensor, K: Tensor, ref_c2w: Tensor, src_c2w: Tensor, inv_depth: Tensor
) -> Tensor:
    """`plane_sweep_cost_volume` computed without warping feature maps (same arguments, same result
    up to float summation order).

    Bilinear sampling is linear in the sampled map, so the correlation of F^i(p) with F^j sampled
    at q is the bilinear interpolation, at q, of F^i(p)'s correlations with F^j's pixels:

        < F^i(p), sum_k w_k F^j(q_k) > = sum_k w_k < F^i(p), F^j(q_k) >     (k: the 4 corners of q)

    One matrix product gives every pixel pair's correlation ([H*W, H*W] per view pair, computed in
    blocks of reference pixels), and each sample gathers its four corners from it, with zero weight
    for corners outside the map (grid_sample's zero padding). It replaces C*D*H*W bilinear taps by
    C*(H*W)^2 multiply-adds in a matrix product, which is cheaper on small maps (see
    `prefers_gathered_cost_volume`).
    """
    n, m, c, h, w = src.shape
    d = inv_depth.shape[1]
    with torch.no_grad():
        ref_to_src = torch.linalg.inv_ex(src_c2w).inverse @ ref_c2w[:, None]  # [N, M, 4, 4]
        depth = 1.0 / inv_depth.reshape(n, d, -1)
        xy = _source_pixels(
            K.repeat_interleave(m, 0), ref_to_src.flatten(0, 1), depth.repeat_interleave(m, 0), h, w
        )  # [N*M, 2, D, H*W]
        # positions far outside the map only need to stay outside it: bounded before flooring
        x = xy[:, 0].clamp(-2, w + 1).transpose(1, 2)  # [N*M, H*W, D]
        y = xy[:, 1].clamp(-2, h + 1).transpose(1, 2)
        x0, y0 = x.floor(), y.floor()
        fx, fy = x - x0, y - y0
        # bilinear weights of the left/right columns and top/bottom rows, zero outside the map
        wx = torch.stack(((1 - fx) * ((x0 >= 0) & (x0 <= w - 1)), fx * ((x0 >= -1) & (x0 <= w - 2))), -1)
        wy = torch.stack(((1 - fy) * ((y0 >= 0) & (y0 <= h - 1)), fy * ((y0 >= -1) & (y0 <= h - 2))), -1)
        weight = (wy[..., :, None] * wx[..., None, :]).flatten(-2)  # [N*M, H*W, D, 4]
        # corners (x0, y0), (x0 + 1, y0), (x0, y0 + 1), (x0 + 1, y0 + 1) as flat pixel indices;
        # those outside the map have zero weight, so any index in range serves them
        offsets = torch.tensor([0, 1, w, w + 1], device=x.device)
        index = ((y0 * w + x0).long()[..., None] + offsets).clamp(0, h * w - 1).flatten(-2)  # [N*M, H*W, 4 D]
    ref_pixels = ref.repeat_interleave(m, 0).flatten(2).transpose(1, 2)  # [N*M, H*W, C]
    src_pixels = src.flatten(0, 1).flatten(2)  # [N*M, C, H*W]
    block = max(1, CORRELATION_CHUNK_BYTES // max(n * m * h * w * src.element_size(), 1))
    costs = []
    for start in range(0, h * w, block):
        corr = torch.bmm(ref_pixels[:, start : start + block], src_pixels)  # [N*M, P, H*W]
        taps = torch.gather(corr, 2, index[:, start : start + block]).view(n * m, -1, d, 4)
        costs.append((taps * weight[:, start : start + block]).sum(-1))  # [N*M, P, D]
    cost = torch.cat(costs, dim=1).transpose(1, 2)  # [N*M, D, H*W]
    return (cost / c**0.5).reshape(n, m, d, h, w).mean(1)


def prefers_gathered_cost_volume(height: int, width: int, candidates: int) -> bool:
    """Whether `gathered_cost_volume` is the cheaper formulation for an H x W map and D candidates:
    its matrix product costs H*W multiply-adds per reference pixel and channel, the warp about
    GATHER_BREAK_EVEN * D (bilinear taps run far below a matrix product's rate)."""
    return height * width <= GATHER_BREAK_EVEN * candidates
