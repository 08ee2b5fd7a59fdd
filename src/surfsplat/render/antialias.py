"""Antialiasing (`render(..., antialiased=True)`): the screen-space filter that keeps each Gaussian's
integrated opacity when its footprint is widened to the pixel (Mip-Splatting's 2D filter, Yu et al.
2024; gsplat's `rasterize_mode="antialiased"`).

Why. Both modes widen a small footprint to about a pixel so that it cannot fall between pixel
centres: "ewa" adds 0.3 px^2 to the 2D covariance, "surfel" takes min(rho_3d, 2 |p - c|^2), a
low-pass Gaussian of variance s = 1/2 px^2 (2DGS). With the opacity unchanged, a surfel far smaller
than a pixel then covers about a pixel at full opacity: a scene fitted at one size and rendered
smaller (every surfel shrinks on screen) comes out too opaque and washed out. The filter scales
each Gaussian's opacity, per camera, by the ratio of its true footprint's area to the widened
one's, so the sum of alpha over the pixels is the Gaussian's own integrated opacity at any scale.
The per-pixel function is unchanged (the same kernels, on every backend); only the opacity each
backend is handed differs. Off (the default), nothing here runs and every backend computes the
function of SPEC section 3, bit for bit.

"ewa": exactly gsplat's antialiased mode (gsplat 1.5.3 `_fully_fused_projection`,
`calc_compensations=True`): with Sigma the projected 2D covariance and eps = 0.3,
    compensation = sqrt(max(0, det(Sigma) / max(det(Sigma + eps I), 1e-10))).
The area of exp(-d^T (Sigma + eps I)^-1 d / 2) is 2 pi sqrt(det(Sigma + eps I)), so the compensated
integral is 2 pi sqrt(det Sigma) o, the unfiltered Gaussian's.

"surfel" (designed here: gsplat's 2DGS has no antialiased mode). The surfel's screen-space
covariance is that of the affine approximation of its homography at its centre, Sigma_s = J J^T,
J the 2x2 Jacobian of the pixel with respect to (u, v) at (0, 0): with T's rows T_x, T_y, T_w and
the projected centre (p_x, p_y) = (T_x[2], T_y[2]) / T_w[2],
    J = [[T_x[0] - p_x T_w[0], T_x[1] - p_x T_w[1]], [T_y[0] - p_y T_w[0], T_y[1] - p_y T_w[1]]] / T_w[2].
The per-pixel exponent stays 2DGS's 0.5 min(rho_3d, rho_2d) - the exact ray-splat intersection
where the surfel is larger than the filter, the low-pass Gaussian of variance s = 1 / 2 px^2
(rho_2d = |d|^2 / s) where it is smaller - so in the affine approximation (rho_3d = d^T Sigma_s^-1 d)
a pixel sees exp(-0.5 min(q_3(d), q_lp(d))), the larger of two concentric Gaussians of peak 1. Its
integral over the plane has a closed form. In polar coordinates along a unit direction theta, the
radial integral of exp(-Q r^2 / 2) r dr is 1 / Q, so I = integral over theta of 1 / min(Q_3, 1/s),
Q_3 = cos^2 / l1 + sin^2 / l2 in the eigenbasis of Sigma_s (eigenvalues l1 >= l2). Three cases:
- l2 >= s (larger than the filter in every direction): Q_3 <= 1/s everywhere, I = 2 pi sqrt(l1 l2);
- l1 <= s (smaller in every direction): I = 2 pi s;
- l2 < s < l1: Q_3 < 1/s inside the double wedge |theta| < theta0 about the long axis, with
  tan^2 theta0 = (1/s - 1/l1) / (1/l2 - 1/s); with the primitive of 1 / (A cos^2 + B sin^2),
  atan(sqrt(B/A) tan theta) / sqrt(AB),
      I = 4 sqrt(l1 l2) phi + s (2 pi - 4 theta0),
      phi = atan2(sqrt(l1 - s), sqrt(s - l2)),  theta0 = atan2(sqrt(l2 (l1 - s)), sqrt(l1 (s - l2)))
  (both arguments multiplied out so that nothing divides by l2; I is continuous with the other
  two cases at l2 = s and l1 = s).
The compensation is 2 pi sqrt(det Sigma_s) / I = 2 pi |det J| / I: exactly 1 for every surfel at
least as large as the filter in both directions (they render bit for bit as without the filter),
|det J| / s for one far smaller than a pixel, and in between the value that keeps its integral.
Every alpha is o c exp(-...), and the cut at 1/255 removes exactly the share (1/255) / (o c) of
each radial profile, so a surfel's integrated alpha is I (o c - 1/255) = 2 pi |det J| o - I / 255
(pixel sampling aside) - `tests/render/test_antialias.py` checks this on renders at x1, x1/2 and
x1/4. The convolution of the surfel with the low-pass (the exponent of Sigma_s + s I) would need
another per-pixel function on every backend and give up the exact intersection of large surfels;
the maximum of the two keeps 2DGS's per-pixel function and the closed form keeps its area. Where
the affine approximation is off (a surfel near the camera plane, seen at a grazing angle) the
compensation is that of its centre's tangent map; the low-pass term's centre
(`RenderConventions.lowpass_center_sigma`) is taken as the projected centre, which it is for any
surfel small enough for the filter to matter.

Everything is computed in float64 from the projection every backend shares (`surfel_transforms`,
`ewa_conics`) and is differentiable through autograd; no library computes the surfel case, hence
this module.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .types import EWA_DILATION, LOWPASS_RHO_SCALE, RenderMode, screen_filter

SURFEL_FILTER_VARIANCE = 1.0 / LOWPASS_RHO_SCALE  # s: 2DGS's low-pass 0.5 * 2 |d|^2 = |d|^2 / (2 s)
_EDGE_ON = 1e-12  # l2 below this share of s: the l2 -> 0 limit |det J| / s (no 1 / sqrt(l2) in a gradient)


def surfel_screen_jacobian(T: Tensor) -> Tensor:
    """[..., N, 2, 2] d pixel / d (u, v) at the surfel centre, for 2DGS's T [..., N, 3, 3] (rows T_x, T_y, T_w)."""
    Tx, Ty, Tw = T[..., 0, :], T[..., 1, :], T[..., 2, :]
    w = Tw[..., 2]
    w = torch.where(w.abs() > 1e-12, w, torch.ones_like(w))  # culled behind the near plane anyway
    px, py = Tx[..., 2] / w, Ty[..., 2] / w
    rows = (
        torch.stack((Tx[..., 0] - px * Tw[..., 0], Tx[..., 1] - px * Tw[..., 1]), -1),
        torch.stack((Ty[..., 0] - py * Tw[..., 0], Ty[..., 1] - py * Tw[..., 1]), -1),
    )
    return torch.stack(rows, -2) / w[..., None, None]


def max_of_gaussians_area(l1: Tensor, l2: Tensor, det_root: Tensor, s: float) -> Tensor:
    """I = integral over the plane of exp(-0.5 min(d^T Sigma^-1 d, |d|^2 / s)) for Sigma of eigenvalues
    l1 >= l2 and sqrt(det Sigma) = det_root (see the module docstring; the three cases)."""
    big = (l2 >= s).detach()
    small = ((l1 <= s) | (l2 <= _EDGE_ON * s)).detach()
    mixed = ~(big | small)
    # placeholders off the mixed case, so no square root of zero enters a gradient there
    m1 = torch.where(mixed, l1, torch.full_like(l1, 2 * s))
    m2 = torch.where(mixed, l2, torch.full_like(l2, 0.5 * s))
    x1, x2 = m1 - s, s - m2
    phi = torch.atan2(x1.sqrt(), x2.sqrt())
    theta0 = torch.atan2((m2 * x1).sqrt(), (m1 * x2).sqrt())
    root = torch.where(mixed, det_root, (m1 * m2).sqrt())
    area_mixed = 4 * root * phi + s * (2 * math.pi - 4 * theta0)
    area = torch.where(big, 2 * math.pi * det_root, torch.full_like(det_root, 2 * math.pi * s))
    return torch.where(mixed, area_mixed, area)


def surfel_compensation(T: Tensor, s: float = SURFEL_FILTER_VARIANCE) -> Tensor:
    """[..., N] the opacity factor that keeps each surfel's integrated opacity under 2DGS's low-pass
    fallback of variance s (px^2), from T [..., N, 3, 3] (float64 recommended). 1 for surfels at least as
    large as the filter."""
    J = surfel_screen_jacobian(T)
    det_root = (J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]).abs()  # sqrt(det J J^T)
    trace = J.square().sum((-1, -2))  # l1 + l2
    gap = (trace.square() - 4 * det_root.square()).clamp_min(0)
    # the eigenvalues; the square root of the gap only where it is positive (isotropic surfels have none)
    positive = (gap > 1e-30 * trace.square()).detach()
    root_gap = torch.where(positive, gap, torch.ones_like(gap)).sqrt() * positive
    l1 = 0.5 * (trace + root_gap)
    l2 = det_root.square() / l1.clamp_min(1e-300)
    small = ((l1 <= s) | (l2 <= _EDGE_ON * s)).detach()
    big = (l2 >= s).detach()
    area = max_of_gaussians_area(l1, l2, det_root, s)
    ratio = 2 * math.pi * det_root / torch.where(big | small, torch.ones_like(area), area)
    return torch.where(big, torch.ones_like(det_root), torch.where(small, det_root / s, ratio))


def ewa_compensation(a: Tensor, b: Tensor, c: Tensor, eps: float = EWA_DILATION) -> Tensor:
    """[..., N] gsplat's compensation sqrt(max(0, det(Sigma) / max(det(Sigma + eps I), 1e-10))) from the
    dilated 2D covariance [[a, b], [b, c]] = Sigma + eps I (eps: EWA_DILATION, 3DGS's)."""
    det_orig = (a - eps) * (c - eps) - b * b
    ratio = det_orig / (a * c - b * b).clamp_min(1e-10)
    positive = (ratio > 0).detach()
    return torch.where(positive, torch.where(positive, ratio, torch.ones_like(ratio)).sqrt(), torch.zeros_like(ratio))


def compensations(
    gaussians,
    cameras,
    width: int,
    height: int,
    mode: RenderMode,
    jacobian_clamp: float | None,
    filter_zoom: float = 1.0,
) -> Tensor:
    """[C, N] each Gaussian's compensation in each camera (float64), from the projection every backend
    shares; `jacobian_clamp` is `RenderConventions.ewa_jacobian_clamp` (the EWA covariance's), `filter_zoom`
    `render`'s (the filter's variance times its square)."""
    from .torch_backend import ewa_conics, surfel_transforms

    g = gaussians
    w2c = cameras.w2c.to(g.means.device, torch.float64)
    K = cameras.K.to(g.means.device, torch.float64)
    if mode == "surfel":
        T, _ = surfel_transforms(g.means, g.rotations, g.scales, w2c, K, torch.float64)
        return surfel_compensation(T, SURFEL_FILTER_VARIANCE * filter_zoom**2)
    eps = screen_filter(filter_zoom)[1]
    _, _, _, cov2d = ewa_conics(g.means, g.covariances, w2c, K, width, height, jacobian_clamp, torch.float64, eps)
    return ewa_compensation(*cov2d, eps)
