"""The losses of a per-scene fit, each a function of renders and photos.

* `colour_loss`: the mean squared error (the refinement's), or 3DGS's (1 - w) L1 + w (1 - SSIM) with
  w = 0.2, SSIM being the project's metric (scikit-image's Gaussian window), so the fit climbs the
  figure it is scored on.
* `depth_normal_error`: 2DGS's depth-normal consistency (its Eq. 14).
* `distortion_error`: 2DGS's depth distortion (its Eq. 13) as gsplat computes it, the mean over the
  pixels of the map every backend accumulates front to back (`render(..., distortion=True)`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry.cameras import Cameras


def colour_loss(prediction: Tensor, target: Tensor, kind: str, ssim_weight: float = 0.2) -> Tensor:
    """The colour term of a fit: the mean squared error ("mse"), or 3DGS's (1 - w) L1 + w (1 - SSIM)
    ("l1_dssim"), SSIM being the project's metric (`surfsplat.metrics.ssim`, scikit-image's Gaussian
    window of 11 taps, sigma 1.5) so the fit climbs the figure it is scored on.
    prediction, target: [V, 3, H, W]."""
    if kind == "mse":
        return (prediction - target).square().mean()
    from ..metrics import ssim

    l1 = (prediction - target).abs().mean()
    if ssim_weight == 0:
        return l1
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - ssim(prediction, target, check_finite=False).mean())


def depth_normal_error(
    depth: Tensor,  # [V, 1, H, W] camera z, rendered
    normal: Tensor,  # [V, 3, H, W] world frame, facing the camera, rendered
    alpha: Tensor,  # [V, 1, H, W]
    cameras: Cameras,  # [V] K in pixels of W x H
) -> Tensor:
    """2DGS's depth-normal consistency (its Eq. 14): 1 - n . N, where n is the rendered normal and N
    the normal of the surface the rendered depth describes (the cross product of its central
    differences, in the world frame, facing the camera), weighted by alpha as 2DGS does; the mean
    over the inner pixels. Differentiable in both maps."""
    v, _, h, w = depth.shape
    rows = torch.arange(h, dtype=depth.dtype, device=depth.device) + 0.5
    cols = torch.arange(w, dtype=depth.dtype, device=depth.device) + 0.5
    pixels = torch.stack(
        (
            cols[None, :].expand(h, w),
            rows[:, None].expand(h, w),
            torch.ones(h, w, dtype=depth.dtype, device=depth.device),
        )
    )
    # inv_ex: no error flag read on the host (a GPU would wait for it every step)
    rays = torch.einsum("vij,jhw->vihw", torch.linalg.inv_ex(cameras.K.to(depth)).inverse, pixels)  # z = 1
    c2w = cameras.c2w.to(depth)
    points = torch.einsum("vij,vjhw->vihw", c2w[:, :3, :3], rays * depth) + c2w[:, :3, 3, None, None]
    right = points[..., 1:-1, 2:] - points[..., 1:-1, :-2]
    down = points[..., 2:, 1:-1] - points[..., :-2, 1:-1]
    # down x right faces the camera: for a fronto-parallel plane (0, 1, 0) x (1, 0, 0) = (0, 0, -1)
    surface = F.normalize(torch.cross(down, right, dim=1), dim=1)
    agreement = (normal[..., 1:-1, 1:-1] * surface).sum(1, keepdim=True)
    return ((1 - agreement) * alpha[..., 1:-1, 1:-1]).mean()


def distortion_error(distortion: Tensor) -> Tensor:  # [V, 1, H, W] RenderOutput.distortion
    """2DGS's depth-distortion term: the mean over pixels of sum_{i != j} w_i w_j |z_i - z_j| (the
    renderer's map; gsplat's `render_distort` and its trainer's mean). It pulls the surfels a ray
    meets together in depth, so a surface is one thin layer rather than a cloud."""
    return distortion.mean()
