"""How much finer than asked a zoomed-out render of a fitted scene is drawn (`render(..., supersample=k)`).

    k = supersampling(gaussians, scene_cameras, cameras)     # 1 at the fitted zoom, up to 4 zoomed out
    out = render(gaussians, cameras, w, h, antialiased=True, supersample=k)

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

Zoomed in, the other way round (`zoom_in_floor`). At the fitted zoom the surfel renderer's screen-space
low-pass (2DGS's, a Gaussian of variance 1/2 px^2 where it exceeds the surfel) draws every surfel smaller
than a pixel as that pixel's blob, and the fit made the picture from those blobs: on LLFF fern a quarter of
the fitted surfels are thinner than their pixel's low-pass. Zoomed in, the low-pass shrinks with the pixel,
those surfels shrink to the slivers they are, and the surface they drew breaks into lines (fern x4: 0.67 dB
below x1 against the bicubic-upsampled photos). Mip-Splatting's 3D filter bounds each Gaussian below by the
finest sampling of the views it was fitted from; here, for a view zoomed in by z (the ratio above,
inverted, from 1.5 on), each surfel's tangent scales are raised to at least the fitted low-pass width at
its finest fitted footprint (`geometry.pixels.pixel_footprints`: depth / f of the finest fitted camera that
sees it) times sqrt(1 - 1 / z^2): with the view's own low-pass, whose variance is 1 / z^2 of the fitted
one in world units, that is the fitted filter's variance, so each surfel is drawn at least as wide as the
fit saw it. The floor is the one the bake for standard viewers applies (`export.bake`) at every zoom; a
surfel already wider is unchanged, and renders below 1.5 x the fitted zoom are untouched, bit for bit.
"""

from __future__ import annotations

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


def _footprints(
    gaussians: Gaussians,
    fitted: Cameras,
    fitted_width: int,
    fitted_height: int,
    cameras: Cameras,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """The fitted cameras' median pixel footprint (a scalar) and each asked camera's ([C]), over the surfels'
    centres: what a view's zoom against the fitted ones is read from, either way."""
    with torch.no_grad():
        means = gaussians.means.detach()
        reference = pixel_footprints(means, fitted, fitted_width, fitted_height).nanmedian()
        return reference, pixel_footprints(means, cameras, width, height)


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
    if len(gaussians.means) == 0:
        return 1
    reference, asked = _footprints(gaussians, fitted, fitted_width, fitted_height, cameras, width, height)
    ratio = float((asked / reference).nan_to_num(1.0).max())
    if not ratio >= MIN_ZOOM:  # NaN (nothing seen) too
        return 1
    return min(MAX_SUPERSAMPLE, round(ratio))


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
    from dataclasses import replace

    from ..geometry.pixels import pixel_footprints as surfel_footprints

    if len(gaussians.means) == 0 or gaussians.explicit_covariances is not None:
        return gaussians
    reference, asked = _footprints(gaussians, fitted, fitted_width, fitted_height, cameras, width, height)
    zoom = float((reference / asked).nan_to_num(1.0).min())
    if not zoom >= MIN_ZOOM:
        return gaussians
    share = (1.0 - 1.0 / zoom**2) ** 0.5
    with torch.no_grad():
        floor = surfel_footprints(gaussians, fitted, fitted_width, fitted_height) * (share / LOWPASS_RHO_SCALE**0.5)
    return replace(gaussians, scales=torch.maximum(gaussians.scales, floor[:, None].to(gaussians.scales)))
