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


def _sampling_grid(K: Tensor, ref_to_src: Tensor, depth: Tensor, height: int, width: int) -> Tensor:
    """[N, D, H, W, 2] normalised sampling positions in the source view.

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
    rays = ref_to_src[:, :3, :3] @ (torch.linalg.inv(K) @ pixels)  # [N, 3, H*W]
    points = rays[:, :, None, :] * depth[:, None] + ref_to_src[:, :3, 3, None, None]  # [N, 3, D, H*W]
    proj = (K @ points.flatten(2)).view(n, 3, -1, height * width)
    xy = proj[:, :2] / proj[:, 2:].clamp(min=1e-3)
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
        ref_to_src = torch.linalg.inv(src_c2w) @ ref_c2w[:, None]  # [N, M, 4, 4]
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
