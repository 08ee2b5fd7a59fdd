"""How a render of a fitted scene at another zoom is drawn: zoomed out, finer than asked and averaged down
(`render(..., supersample=k)`); zoomed in, with the fitted pixels' filter (`render(..., filter_zoom=z)`).

    plan = zoom_plan(gaussians, scene_cameras, scene_width, scene_height, cameras, w, h)
    out = render(plan.gaussians, cameras, w, h, supersample=plan.supersample, filter_zoom=plan.filter_zoom)

Why. A scene fitted to photos of one size holds detail at that size's pixels: fern's leaves are
surfels a pixel or two wide, in front of one another. Rendered at a quarter of the size, each small
pixel should show the average of the 4 x 4 pixels it covers (what a camera with larger pixels
records). The antialiasing filter (`antialias.py`) keeps each surfel's integrated opacity when it
shrinks below a pixel, but it composites the widened, fainter surfels one after the other, so a leaf
hidden behind another at full size shows through at a quarter: on LLFF fern fitted with the filter,
the x1/4 render scored 26.5 dB where the full-size render averaged down scores 30.7 dB (the filter's
widening alone, a Gaussian of 1/2 px^2, also blurs). Drawing the render at the pixel size the scene
was fitted at and averaging it down is that average itself, at the cost of the fitted size's pixels.

The zoom of a view is the size of its pixels on the surfaces it sees against the fitted views' own:
per camera the median, over the surfels whose centre it sees, of depth / f_x (a pixel's width on a
surface facing it, in world units), divided by the same median of the fitted cameras. It catches a
smaller image, a shorter focal length and a camera moved back alike. The factor is that ratio
rounded, 1 (no supersampling) below 1.5, at most `MAX_SUPERSAMPLE`; one factor serves a batch of
cameras (the largest). Nothing here is in a library: gsplat and nerfstudio render at the size asked.

Zoomed in, the other way round (`filter_zoom`). At the fitted zoom the surfel renderer's screen-space
low-pass (2DGS's, a Gaussian of variance 1/2 px^2 where it exceeds the surfel) draws every surfel smaller
than a pixel as that pixel's blob, and the fit made the picture from those blobs: on LLFF fern a quarter of
the fitted surfels are thinner than their pixel's low-pass, and many are seen edge on, as lines. Zoomed in,
the low-pass shrinks with the pixel, those surfels shrink to the slivers they are, and the surface they drew
breaks into lines and seams (fern's held-out views: x1 25.45 dB; x2 24.16 and x4 23.60 against the
bicubic-upsampled photos). Mip-Splatting's 3D filter bounds each Gaussian below by the finest sampling of
the views it was fitted from. Here a view zoomed in by z (the ratio above, inverted, from 1.5 on) is drawn
with the filter of the fitted pixels, `render(..., filter_zoom=z)`: the low-pass of a camera z times
coarser, the same width on the surfaces as at the fitted zoom, so each surfel keeps the footprint the fit
made its picture from, edge-on ones too (x2 25.80, x4 25.79 dB; the x1 render bicubic-upsampled scores
25.99 and 25.97). Surfels wider than the filter are drawn as they are, sharp; renders below 1.5 x the fitted
zoom are untouched, bit for bit.

gsplat's 2DGS kernels fix the filter when compiled, so on the gsplat backend a zoomed-in view widens the
surfels instead (`zoom_in_floor`): each surfel's tangent scales at least the fitted low-pass width at its
finest fitted footprint (`geometry.pixels.pixel_footprints`) times sqrt(1 - 1 / z^2), with the view's own
low-pass the fitted filter's variance. It is the floor the bake for standard viewers applies
(`export.bake`), and falls short where surfels are seen edge on (fern x2 24.81, x4 24.62 dB).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from .types import LOWPASS_RHO_SCALE

MAX_SUPERSAMPLE = 4  # a render is drawn at most 4 x 4 times its pixels (x1/4 of the fitted size: the fitted size)
MIN_ZOOM = 1.5  # renders closer to the fitted zoom than this, either way, are drawn as asked


def pixel_footprints(means: Tensor, cameras: Cameras, width: int, height: int) -> Tensor:
    """[C] per camera the median over the surfel centres it sees (in front, inside the width x height image)
    of depth / f_x; NaN for a camera that sees none."""
    c2w = cameras.c2w.to(means)
    K = cameras.K.to(means)
    R, t = c2w[:, :3, :3], c2w[:, :3, 3]
    local = torch.einsum("cji,cnj->cni", R, means[None] - t[:, None])  # world -> camera: R^T (x - t)
    z = local[..., 2]
    safe = torch.where(z > 1e-9, z, torch.ones_like(z))
    u = K[:, None, 0, 0] * local[..., 0] / safe + K[:, None, 0, 2]
    v = K[:, None, 1, 1] * local[..., 1] / safe + K[:, None, 1, 2]
    seen = (z > 1e-9) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    sizes = torch.where(seen, z / K[:, None, 0, 0], torch.full_like(z, float("nan")))
    return sizes.nanmedian(dim=1).values


def _zooms(
    gaussians: Gaussians,
    fitted: Cameras,
    fitted_width: int,
    fitted_height: int,
    cameras: Cameras,
    width: int,
    height: int,
) -> tuple[int, float]:
    """(`supersampling`, `filter_zoom`) from one reading of the fitted cameras' median pixel footprint and
    each asked camera's, over the surfels' centres: a view's zoom against the fitted ones, either way."""
    if len(gaussians.means) == 0:
        return 1, 1.0
    with torch.no_grad():
        means = gaussians.means.detach()
        reference = pixel_footprints(means, fitted, fitted_width, fitted_height).nanmedian()
        asked = pixel_footprints(means, cameras, width, height)
    out = float((asked / reference).nan_to_num(1.0).max())  # the most zoomed-out camera of the batch
    inward = float((reference / asked).nan_to_num(1.0).min())  # the least zoomed-in one
    supersample = min(MAX_SUPERSAMPLE, round(out)) if out >= MIN_ZOOM else 1  # NaN (nothing seen): 1 too
    return supersample, inward if inward >= MIN_ZOOM else 1.0


def supersampling(
    gaussians: Gaussians,
    fitted: Cameras,
    fitted_width: int,
    fitted_height: int,
    cameras: Cameras,
    width: int,
    height: int,
) -> int:
    """The supersampling factor (1 to MAX_SUPERSAMPLE) of a render of `gaussians` from `cameras` at width x height,
    for a scene fitted from `fitted` at fitted_width x fitted_height (module docstring)."""
    return _zooms(gaussians, fitted, fitted_width, fitted_height, cameras, width, height)[0]


def zoom_in_floor(
    gaussians: Gaussians,
    fitted: Cameras,
    fitted_width: int,
    fitted_height: int,
    cameras: Cameras,
    width: int,
    height: int,
) -> Gaussians:
    """`gaussians` as a zoomed-in render from `cameras` at width x height draws them: each surfel's tangent
    scales at least its fitted low-pass width times sqrt(1 - 1 / z^2), z the least zoom-in of the batch
    (module docstring). The same object where no camera is zoomed in 1.5 x or more, or where the surfels carry
    explicit covariances (the release's EWA surfels, whose scales the renderer does not read)."""
    if gaussians.explicit_covariances is not None:
        return gaussians
    zoom = filter_zoom(gaussians, fitted, fitted_width, fitted_height, cameras, width, height)
    return _widened(gaussians, fitted, fitted_width, fitted_height, zoom)


def _widened(gaussians: Gaussians, fitted: Cameras, fitted_width: int, fitted_height: int, zoom: float) -> Gaussians:
    """`zoom_in_floor` for a zoom-in already read (`filter_zoom`; 1: the same object)."""
    from dataclasses import replace

    from ..geometry.pixels import pixel_footprints as surfel_footprints

    if zoom == 1.0 or gaussians.explicit_covariances is not None:
        return gaussians
    share = (1.0 - 1.0 / zoom**2) ** 0.5
    with torch.no_grad():
        floor = surfel_footprints(gaussians, fitted, fitted_width, fitted_height) * (share / LOWPASS_RHO_SCALE**0.5)
    return replace(gaussians, scales=torch.maximum(gaussians.scales, floor[:, None].to(gaussians.scales)))


def filter_zoom(
    gaussians: Gaussians,
    fitted: Cameras,
    fitted_width: int,
    fitted_height: int,
    cameras: Cameras,
    width: int,
    height: int,
) -> float:
    """`render`'s filter_zoom for a render of `gaussians` from `cameras` at width x height, for a scene fitted
    from `fitted` at fitted_width x fitted_height (module docstring): the least zoom-in of the batch where
    every camera is zoomed in 1.5 x or more, else 1."""
    return _zooms(gaussians, fitted, fitted_width, fitted_height, cameras, width, height)[1]


@dataclass(frozen=True)
class ZoomPlan:
    """How one render of a fitted scene is drawn (`zoom_plan`): `render(gaussians, ..., supersample=...,
    filter_zoom=...)`."""

    gaussians: Gaussians
    supersample: int = 1
    filter_zoom: float = 1.0


def zoom_plan(
    gaussians: Gaussians,
    fitted: Cameras | None,
    fitted_width: int | None,
    fitted_height: int | None,
    cameras: Cameras,
    width: int,
    height: int,
    backend: str = "auto",
) -> ZoomPlan:
    """A render of a scene fitted from `fitted` at fitted_width x fitted_height, from `cameras` at width x
    height, at the fitted zoom whichever way it is asked: zoomed out supersampled, zoomed in with the fitted
    pixels' filter (on gsplat, whose kernels cannot, with the surfels widened: `zoom_in_floor`). As asked
    where the scene records no fitted views."""
    if fitted is None or not fitted_width or not fitted_height:
        return ZoomPlan(gaussians)
    from . import resolve_backend

    supersample, zoom = _zooms(gaussians, fitted, fitted_width, fitted_height, cameras, width, height)
    if supersample > 1:
        return ZoomPlan(gaussians, supersample=supersample)
    if resolve_backend(backend, gaussians.means.device, None, cameras) == "gsplat":
        return ZoomPlan(_widened(gaussians, fitted, fitted_width, fitted_height, zoom))
    return ZoomPlan(gaussians, filter_zoom=zoom)
