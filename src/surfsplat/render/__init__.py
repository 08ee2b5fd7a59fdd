"""`surfsplat.render`: Gaussians + cameras -> colour, alpha, depth and normal maps."""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..utils.checks import SurfSplatInputError, check_tensor
from .cpu import CpuRenderSettings
from .cpu import backend_unavailable as cpu_backend_unavailable
from .torch_backend import TorchRenderSettings, render_torch
from .types import BACKENDS, Backend, RenderConventions, RenderMode, RenderOutput, check_render_args

__all__ = [
    "render",
    "RenderOutput",
    "TorchRenderSettings",
    "CpuRenderSettings",
    "RenderConventions",
    "normalize_by_alpha",
    "gsplat_available",
    "resolve_backend",
]

DEFAULT_ALPHA_THRESHOLD = 0.001  # SurfSplat's evaluation tau_alpha (paper Sec. 3.4); training uses 0.1


def gsplat_available(device: torch.device) -> bool:
    """True when the gsplat CUDA backend can run on `device`."""
    if device.type != "cuda":
        return False
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def render(
    gaussians: Gaussians,
    cameras: Cameras,
    width: int,
    height: int,
    *,
    mode: RenderMode = "surfel",
    backend: Backend = "auto",
    background: Tensor | Sequence[float] | None = None,
    alpha_threshold: float | None = DEFAULT_ALPHA_THRESHOLD,
    settings: TorchRenderSettings | CpuRenderSettings | None = None,
    distortion: bool = False,
    antialiased: bool = False,
    absgrad: bool = False,
    supersample: int = 1,
    filter_zoom: float = 1.0,
) -> RenderOutput:
    """Render unbatched Gaussians ([N, ...]) from C cameras at width x height pixels.

    mode:            "surfel" - exact ray-splat intersection of 2DGS with its screen-space low-pass
                     fallback; "ewa" - 3DGS's affine projection of the 3D covariance plus 0.3 px^2
                     (a surfel becomes a thin 3D Gaussian; explicit covariances are used when given).
    background:      RGB added where the image is not fully covered (default black, as the release).
    alpha_threshold: forced alpha blending (paper Sec. 3.4): colour, depth and normal are divided by
                     alpha wherever alpha >= threshold, and such pixels count as opaque for the
                     background. None disables it (plain 2DGS/3DGS compositing, the "w/o FAB" ablation).
    backend:         "torch" (reference, any device), "cpu" (compiled numba kernels), "gsplat" (CUDA) or
                     "auto": see `resolve_backend`.
    settings:        TorchRenderSettings or CpuRenderSettings of the chosen backend; with "auto" the
                     settings' type picks that backend. Both carry the `RenderConventions` (low-pass
                     centre, EWA Jacobian clamp and support) that every backend, gsplat's too, follows.
    distortion:      also return 2DGS's depth distortion map (its Eq. 13) in `RenderOutput.distortion`
                     [C, 1, H, W], differentiable; "surfel" mode only. Off by default: nothing else pays for it.
    antialiased:     the antialiasing filter (`surfsplat.render.antialias`): each Gaussian's opacity, per
                     camera, times the compensation that keeps its integrated opacity under the screen-space
                     widening (gsplat's "antialiased" mode in "ewa"; its surfel twin in "surfel"), so a
                     render at 1/s of the size is close to the full-size render averaged down. Off by
                     default: the function is then SPEC section 3's, bit for bit.
    absgrad:         also return `RenderOutput.absgrad` [C, N, 2], a zero tensor whose `.grad` after the
                     loss's backward is, per camera and surfel, the sum over the pixels p of |dL_p/dc_x| and
                     of |dL_p/dc_y|: each pixel's own share of the gradient with respect to the projected
                     centre c in pixels, the surfel moved parallel to the image at its depth (AbsGS, Ye et al.
                     2024; gsplat's `absgrad`, which sums the two axes apart the same way). Without the
                     absolute values the sums are the plain centre gradient (gsplat's `gradient_2dgs`),
                     where shares of opposite sign cancel. "surfel" mode, "torch" and "cpu" backends
                     (gsplat's 2DGS kernel takes absolute values on its low-pass branch only); the torch
                     backend leaves the depth distortion out of it, so it refuses both at once. Off by
                     default: the backward computes nothing of it.
    supersample:     k > 1 renders at k times the width and height (K scaled exactly, k^2 times the pixels)
                     and averages each k x k block of every map (colour, alpha, depth, normal, distortion):
                     the image a camera with k times larger pixels records of the full-size render, its
                     area integral rather than point samples. What a render far smaller than the size the
                     scene was fitted at needs (`Scene.supersampling`): the antialiasing filter keeps each
                     surfel's integrated opacity, but cannot undo the occlusion between surfels that a
                     pixel covering many of them averages over. Differentiable; not with `absgrad`.
    filter_zoom:     z >= 1 draws with the screen-space filter of a camera z times coarser: 2DGS's low-pass
                     rho2d = 2 |p - c|^2 / z^2 in "surfel" mode, 3DGS's dilation 0.3 z^2 px^2 in "ewa" (and the
                     antialiasing compensation for that filter). What a view zoomed in z times on a scene
                     fitted at its own pixels needs (`Scene.filter_zoom`): each surfel then keeps the least
                     footprint the fit gave it, where at 2DGS's own filter surfels thinner than a fitted
                     pixel shrink to slivers and seams (fern's held-out views at x2 and x4: 25.80 and 25.79 dB
                     against the bicubic-upsampled photos with it, 24.16 and 23.60 without; x1 25.45).
                     "torch" and "cpu" backends (gsplat's 2DGS kernels fix the filter at compile time);
                     not with `absgrad` or `supersample`. 1 (default): the function is SPEC section 3's.
    Returns RenderOutput with colour [C, 3, H, W], alpha [C, 1, H, W], depth [C, 1, H, W], normal [C, 3, H, W]
    (and distortion [C, 1, H, W] when asked).

    Depth distortion, per ray: D = sum over ordered pairs i != j of w_i w_j |z_i - z_j| (2DGS Eq. 13),
    computed front to back from two running moments, the weights' sum A_i = 1 - T_i and M_i = sum_{j<i}
    w_j z_j, as D = 2 sum_i w_i (z_i A_i - M_i) - 2DGS's rasterizer's scheme. The choices where the
    field's implementations differ are gsplat's (`rasterization_2dgs(distloss=True)`, `render_distort`),
    the maintained one, so every backend computes one function and the gsplat backend returns gsplat's
    own map: z is each surfel's centre depth (camera z, the depth sort key, hence |z_i - z_j| is exact
    from the moments), the distance is linear, and both orders of each pair count (gsplat's factor 2).
    2DGS's own rasterizer instead uses the ray-splat intersection depth mapped to NDC,
    m = f / (f - n) (1 - n / z) with n = 0.2, f = 100, and squared distances; neither is used here.
    The map is the raw per-ray sum: no forced-alpha normalization, no background.
    """
    _validate(gaussians, cameras, width, height, mode, alpha_threshold)
    if isinstance(supersample, bool) or not isinstance(supersample, int) or supersample < 1:
        raise SurfSplatInputError(f"supersample: expected an integer >= 1, got {supersample!r}")
    if isinstance(filter_zoom, bool) or not isinstance(filter_zoom, int | float) or not 1 <= filter_zoom < math.inf:
        raise SurfSplatInputError(f"filter_zoom: expected a finite number >= 1, got {filter_zoom!r}")
    filter_zoom = float(filter_zoom)
    if filter_zoom != 1 and (supersample > 1 or absgrad):
        which = "supersample" if supersample > 1 else "absgrad"
        raise SurfSplatInputError(f"filter_zoom: a zoomed-in view's filter, not with {which}")
    if supersample > 1:
        if absgrad:
            raise SurfSplatInputError("supersample: the absolute screen gradient is of one render; use supersample=1")
        k = supersample
        fine = render(
            gaussians,
            cameras.scaled(k),
            width * k,
            height * k,
            mode=mode,
            backend=backend,
            background=background,
            alpha_threshold=alpha_threshold,
            settings=settings,
            distortion=distortion,
            antialiased=antialiased,
        )
        pool = lambda t: None if t is None else torch.nn.functional.avg_pool2d(t, k)  # noqa: E731
        return RenderOutput(
            color=pool(fine.color),
            alpha=pool(fine.alpha),
            depth=pool(fine.depth),
            normal=pool(fine.normal),
            distortion=pool(fine.distortion),
        )
    if not isinstance(distortion, bool):
        raise SurfSplatInputError(f"distortion: expected True or False, got {distortion!r}")
    if distortion and mode != "surfel":
        raise SurfSplatInputError("distortion: 2DGS's depth distortion is computed in mode 'surfel' only")
    if not isinstance(antialiased, bool):
        raise SurfSplatInputError(f"antialiased: expected True or False, got {antialiased!r}")
    if not isinstance(absgrad, bool):
        raise SurfSplatInputError(f"absgrad: expected True or False, got {absgrad!r}")
    if absgrad and mode != "surfel":
        raise SurfSplatInputError("absgrad: the absolute screen gradient is computed in mode 'surfel' only")
    device = gaussians.means.device
    dtype = gaussians.means.dtype
    bg = _background(background, dtype, device)
    backend = resolve_backend(backend, device, settings, cameras)
    factors = None
    if antialiased:
        from .antialias import compensations

        rules = settings if isinstance(settings, RenderConventions) else RenderConventions()
        clamp = rules.ewa_jacobian_clamp
        factors = compensations(gaussians, cameras, width, height, mode, clamp, filter_zoom).to(dtype)  # [C, N]
    probe = None
    if absgrad:
        if backend == "gsplat":
            raise SurfSplatInputError(
                "absgrad: the gsplat backend cannot give it for surfels (gsplat's 2DGS kernel takes absolute "
                "values on its low-pass branch only); use backend='torch' or 'cpu'"
            )
        if backend == "torch" and distortion:
            raise SurfSplatInputError("absgrad: the torch backend computes it without the depth distortion")
        probe = torch.zeros(len(cameras), len(gaussians), 2, dtype=dtype, device=device, requires_grad=True)
    if backend == "gsplat" and filter_zoom != 1:
        raise SurfSplatInputError(
            "filter_zoom: gsplat's 2DGS kernels fix the screen-space filter when compiled; use backend='torch' "
            "or 'cpu', or widen the surfels instead (surfsplat.render.supersample.zoom_in_floor)"
        )
    if backend == "gsplat":
        if not gsplat_available(device):
            raise SurfSplatInputError(
                "backend: 'gsplat' needs a CUDA device and the gsplat package (pip install 'surfsplat[gsplat]'); "
                f"Gaussians are on {device}"
            )
        from .gsplat_backend import render_gsplat

        conventions = settings if isinstance(settings, RenderConventions) else None
        maps = render_gsplat(gaussians, cameras, width, height, mode, conventions, distortion, factors)
    elif backend == "cpu":
        from .cpu import render_cpu

        if factors is None:
            maps = render_cpu(gaussians, cameras, width, height, mode, settings, distortion, probe, filter_zoom)
        else:  # the kernels take one opacity per Gaussian: one call per camera
            per_camera = [
                render_cpu(
                    _scaled_opacities(gaussians, factors[c]),
                    cameras[c],
                    width,
                    height,
                    mode,
                    settings,
                    distortion,
                    None if probe is None else probe[c : c + 1],
                    filter_zoom,
                )
                for c in range(len(cameras))
            ]
            maps = tuple(torch.cat(parts) for parts in zip(*per_camera))
        if not bg.requires_grad:
            if alpha_threshold is None and background is None:
                # plain compositing over black: nothing is divided and the background adds zero, so the maps
                # are the blended ones as they are (a pass over the image each way saved: a 368x496 fit step
                # spent 3.5 ms of some 60 there)
                return RenderOutput(
                    color=maps[0],
                    alpha=maps[1],
                    depth=maps[2],
                    normal=maps[3],
                    distortion=maps[4] if distortion else None,
                    absgrad=probe,
                )
            # one compiled pass forward and one backward instead of some ten whole-image torch ops each way
            from .cpu.backend import normalize_cpu

            color, alpha, depth, normal = maps[:4]
            color, depth, normal = normalize_cpu(color, alpha, depth, normal, alpha_threshold, bg)
            return RenderOutput(
                color=color,
                alpha=alpha,
                depth=depth,
                normal=normal,
                distortion=maps[4] if distortion else None,
                absgrad=probe,
            )
    else:
        maps = _render_torch_all(
            gaussians, cameras, width, height, mode, settings, distortion, factors, probe, filter_zoom
        )
    color, alpha, depth, normal = maps[:4]
    color, depth, normal, coverage = normalize_by_alpha(color, alpha, depth, normal, alpha_threshold)
    color = color + (1 - coverage) * bg[None, :, None, None]
    return RenderOutput(
        color=color, alpha=alpha, depth=depth, normal=normal, distortion=maps[4] if distortion else None, absgrad=probe
    )


def resolve_backend(
    backend: str, device: torch.device, settings: TorchRenderSettings | CpuRenderSettings | None, cameras: Cameras
) -> str:
    """The concrete backend for a request. "auto" picks, first match wins:

    gsplat on CUDA when installed; torch for TorchRenderSettings, for tensors off the CPU, or when
    the cameras require gradients (only torch differentiates them); cpu for CpuRenderSettings;
    otherwise the compiled cpu backend, or torch with a one-line warning if that cannot load.
    """
    if backend not in BACKENDS:
        raise SurfSplatInputError(f"backend: expected 'auto', 'torch', 'cpu' or 'gsplat', got {backend!r}")
    if backend == "auto":
        if gsplat_available(device):
            return "gsplat"
        if isinstance(settings, TorchRenderSettings) or device.type != "cpu":
            backend = "torch"
        elif cameras.c2w.requires_grad or cameras.K.requires_grad:
            backend = "torch"
        elif isinstance(settings, CpuRenderSettings):
            backend = "cpu"
        else:
            reason = cpu_backend_unavailable()
            if reason is None:
                return "cpu"
            warnings.warn(
                f"surfsplat.render: compiled CPU backend unavailable, using the torch backend: {reason}", stacklevel=3
            )
            backend = "torch"
    if backend == "cpu":
        reason = cpu_backend_unavailable()
        if reason is not None:
            raise SurfSplatInputError(f"backend: 'cpu' cannot load: {reason}")
    wanted = CpuRenderSettings if backend == "cpu" else TorchRenderSettings
    if settings is not None and backend != "gsplat" and not isinstance(settings, wanted):
        raise SurfSplatInputError(
            f"settings: backend {backend!r} takes {wanted.__name__}, got {type(settings).__name__}"
        )
    return backend


def normalize_by_alpha(
    color: Tensor, alpha: Tensor, depth: Tensor, normal: Tensor, threshold: float | None
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Forced-alpha normalization C / alpha where alpha >= threshold (paper Sec. 3.4, Eq. 9).

    Returns the normalized (color, depth, normal) and the coverage used for the background:
    1 where normalized, alpha elsewhere.
    """
    if threshold is None:
        return color, depth, normal, alpha
    mask = alpha >= threshold
    safe = torch.where(mask, alpha, torch.ones_like(alpha))
    coverage = torch.where(mask, torch.ones_like(alpha), alpha)
    return color / safe, depth / safe, normal / safe, coverage


def _render_torch_all(
    g: Gaussians,
    cameras: Cameras,
    width: int,
    height: int,
    mode: RenderMode,
    settings: TorchRenderSettings | None,
    distortion: bool = False,
    factors: Tensor | None = None,  # [C, N] opacity factors (antialiasing), None: none
    probe: Tensor | None = None,  # [C, N, 2] (`render`'s absgrad)
    filter_zoom: float = 1.0,
) -> tuple[Tensor, ...]:
    settings = settings or TorchRenderSettings()
    rotations = g.rotations
    covariances = g.covariances if mode == "ewa" else None
    w2c = cameras.w2c.to(g.means)
    K = cameras.K.to(g.means)
    centers = cameras.centers.to(g.means)
    outs = [
        render_torch(
            g.means,
            rotations,
            g.scales,
            covariances,
            g.opacities if factors is None else g.opacities * factors[c],
            g.sh,
            w2c[c],
            K[c],
            centers[c],
            width,
            height,
            mode,
            settings,
            distortion=distortion,
            abs_probe=None if probe is None else probe[c],
            filter_zoom=filter_zoom,
        )
        for c in range(len(cameras))
    ]
    color = torch.stack([o[0] for o in outs]).permute(0, 3, 1, 2)
    alpha = torch.stack([o[1] for o in outs])[:, None]
    depth = torch.stack([o[2] for o in outs])[:, None]
    normal = torch.stack([o[3] for o in outs]).permute(0, 3, 1, 2)
    if distortion:
        return color, alpha, depth, normal, torch.stack([o[4] for o in outs])[:, None]
    return color, alpha, depth, normal


def _scaled_opacities(g: Gaussians, factor: Tensor) -> Gaussians:
    """The Gaussians with their opacities times `factor` [N] (one camera's compensations)."""
    from dataclasses import replace

    return replace(g, opacities=g.opacities * factor, validate=False)


def _background(background: Tensor | Sequence[float] | None, dtype: torch.dtype, device: torch.device) -> Tensor:
    if background is None:
        return torch.zeros(3, dtype=dtype, device=device)
    bg = torch.as_tensor(background, dtype=dtype, device=device)
    check_tensor("background", bg, (3,))
    return bg


def _validate(
    g: Gaussians, cameras: Cameras, width: int, height: int, mode: str, alpha_threshold: float | None
) -> None:
    check_render_args("", g, cameras, width, height, mode, alpha_threshold=alpha_threshold)
