"""Renderer inputs and outputs shared by every backend."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, get_args

from torch import Tensor

from ..utils.checks import SurfSplatInputError

RenderMode = Literal["surfel", "ewa"]
Backend = Literal["auto", "torch", "cpu", "gsplat"]
BACKENDS: tuple[str, ...] = get_args(Backend)

# Compositing constants shared with 3DGS/2DGS/gsplat so every backend computes the same function.
ALPHA_MIN = 1.0 / 255.0  # a Gaussian contributes to a pixel only if its alpha reaches this
LOG_ALPHA_MIN = math.log(ALPHA_MIN)
ALPHA_MAX = 0.99  # alpha is clamped here so transmittance never reaches exactly zero
TRANSMITTANCE_MIN = 1e-4  # a pixel stops accepting Gaussians once transmittance would drop below this
LOWPASS_RHO_SCALE = 2.0  # 2DGS screen-space filter: rho2d = 2 |p - c|^2 (a 1/sqrt(2) px radius)
EWA_DILATION = 0.3  # px^2 added to projected 2D covariances (3DGS)
EWA_TILE = 16  # edge of the tiles through which diff-gaussian-rasterization lets a Gaussian reach pixels
EWA_RADIUS_SIGMAS = 3.0  # its square of radius ceil(3 sqrt(lambda_max)) picks those tiles
EWA_LAMBDA_GAP_MIN = 0.1  # and lambda_max = mid + sqrt(max(0.1, mid^2 - det)) there
EwaSupport = Literal["release", "alpha"]


def screen_filter(zoom: float = 1.0) -> tuple[float, float]:
    """The screen-space filter of a camera `zoom` times coarser (`render`'s filter_zoom), as every backend
    takes it: the surfels' low-pass coefficient LOWPASS_RHO_SCALE / zoom^2 (rho2d = that |p - c|^2) and EWA's
    dilation EWA_DILATION zoom^2 (px^2). zoom 1: 2DGS's and 3DGS's own."""
    return LOWPASS_RHO_SCALE / zoom**2, EWA_DILATION * zoom**2


@dataclass
class RenderConventions:
    """The rules where the field's reference rasterizers differ; every backend follows the same ones.

    lowpass_center_sigma: the surfel low-pass term rho2d = 2 |p - c|^2 is centred on c, the centre
        of the bounding box of the projected k-sigma ellipse with k = this value. 3 is 2DGS's
        reference rasterizer (diff-surfel-rasterization, `compute_aabb` with cutoff 3), the
        default; 1 is gsplat's `fully_fused_projection_2dgs`; None is the projected surfel centre
        (the paper's wording). Where the k-sigma ellipse is not bounded (it crosses the camera
        plane) the projected centre is used.
    ewa_jacobian_clamp: in "ewa" mode the affine Jacobian is taken at the camera point with x/z
        and y/z clamped to +-(this) tan(fov/2), tan(fov/2) = W / (2 fx) and H / (2 fy) (3DGS's
        1.3, the default; gsplat's limit is the same for a centred principal point). None: no clamp.
    ewa_support: which pixels an "ewa" Gaussian reaches. "release" (default): the pixels of the
        16x16 tiles overlapped by its square of radius ceil(3 sqrt(lambda_max)), as
        diff-gaussian-rasterization (the released SurfSplat's renderer) does; "alpha": exactly the
        pixels where its alpha can reach 1/255 (never truncated, as gsplat's 3.33-sigma boxes).
    """

    lowpass_center_sigma: float | None = 3.0
    ewa_jacobian_clamp: float | None = 1.3
    ewa_support: EwaSupport = "release"

    def __post_init__(self) -> None:
        for name in ("lowpass_center_sigma", "ewa_jacobian_clamp"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, int | float) and value > 0 and math.isfinite(value)):
                raise SurfSplatInputError(f"settings.{name}: expected a positive number or None, got {value!r}")
        if self.ewa_support not in get_args(EwaSupport):
            raise SurfSplatInputError(f"settings.ewa_support: expected 'release' or 'alpha', got {self.ewa_support!r}")


@dataclass
class RenderOutput:
    """Rendered maps for C cameras.

    color:  [C, 3, H, W] (after forced-alpha normalization and background)
    alpha:  [C, 1, H, W] accumulated opacity (never normalized)
    depth:  [C, 1, H, W] camera-z depth: the ray-splat intersection (surfel) or the centre depth (ewa),
            blended by the compositing weights and normalized like colour
    normal: [C, 3, H, W] world-frame normals facing the camera, blended and normalized like colour
    distortion: [C, 1, H, W] 2DGS's depth distortion per ray (`render(..., distortion=True)`, "surfel"
            mode; None otherwise): sum over ordered pairs i != j of w_i w_j |z_i - z_j|, w the
            compositing weights and z each surfel's centre depth (camera z), the field's maintained
            form (gsplat's `render_distort`). Never normalized; see `render` for the choices made.
    absgrad: [C, N, 2] (`render(..., absgrad=True)`, None otherwise): zeros that require a gradient, whose
            `.grad` after the loss's backward holds, per camera and surfel, the sums over the pixels of
            |dL_p/dc_x| and |dL_p/dc_y|, c the projected centre in pixels (AbsGS; see `render`).
    """

    color: Tensor
    alpha: Tensor
    depth: Tensor
    normal: Tensor
    distortion: Tensor | None = None
    absgrad: Tensor | None = None


def check_render_args(
    where: str,
    gaussians: object,
    cameras: object,
    width: object,
    height: object,
    mode: object,
    backend: object = "auto",
    alpha_threshold: object = None,
) -> None:
    """The checks every entry point that renders makes (`render`, compaction, the bake): unbatched
    Gaussians, Cameras, a positive integer size, a known mode and backend, and an alpha threshold in
    (0, 1] or None. `where` names the entry point in each message ("" for `render` itself)."""
    from ..geometry.cameras import Cameras
    from ..geometry.gaussians import Gaussians

    p = f"{where}: " if where else ""
    if not isinstance(gaussians, Gaussians):
        raise SurfSplatInputError(f"{p}gaussians: expected surfsplat.Gaussians, got {type(gaussians).__name__}")
    if gaussians.means.ndim != 2:
        raise SurfSplatInputError(
            f"{p}gaussians: expected unbatched Gaussians with means [N, 3], got {tuple(gaussians.means.shape)}; "
            "use one scene at a time (Gaussians.select(b))"
        )
    if not isinstance(cameras, Cameras):
        raise SurfSplatInputError(f"{p}cameras: expected surfsplat.Cameras, got {type(cameras).__name__}")
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (width, height)):
        raise SurfSplatInputError(f"{p}height and width: expected positive integers, got {height!r} x {width!r}")
    if mode not in get_args(RenderMode):
        raise SurfSplatInputError(f"{p}mode: expected 'surfel' or 'ewa', got {mode!r}")
    if backend not in BACKENDS:
        raise SurfSplatInputError(f"{p}backend: expected one of {BACKENDS}, got {backend!r}")
    if alpha_threshold is not None and not (isinstance(alpha_threshold, (int, float)) and 0 < alpha_threshold <= 1):
        raise SurfSplatInputError(f"{p}alpha_threshold: expected a value in (0, 1] or None, got {alpha_threshold!r}")
