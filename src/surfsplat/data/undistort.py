"""Undistortion of photos, masks and depth maps: an image of a lens resampled to its pinhole, once, at load.

    pinhole = undistorted_pinhole(lens)                 # COLMAP's image_undistorter's choice
    photo = undistort(photo, lens, pinhole)             # [3, H, W] at the lens's size -> the pinhole's
    depth = undistort(depth, lens, pinhole, "nearest")  # depth is never blended across edges

How: for each pixel centre of the output, the pixel of the input it shows comes from this project's
own projection (`surfsplat.geometry.lens`, tested against pycolmap and OpenCV to 1e-6 px), and
OpenCV's `cv2.remap` samples there. Why not pycolmap's `undistort_image`: it warps pycolmap
`Bitmap`s of 8-bit colour, so masks, float32 photos and depth maps (which must not be interpolated
bilinearly) would each need a round trip through it; the maps from our projection serve them all,
and the inverse warp (`distort`, which pycolmap has no function for) is the same code run the other
way. Why cv2.remap and not a hand-written sampler: it is the library function for this, fast on
the CPU; its bilinear weights are quantized to 1/32 pixel (OpenCV's INTER_TAB_SIZE), an error of at
most 1/64 of the local difference between neighbouring pixels.

On 8-bit photos the result is COLMAP's `image_undistorter`'s (pycolmap's `undistort_image`): the
same size and, for every model 2-10, every value within one level (tests/data/test_undistort.py).

Where an output pixel shows no pixel of the input (its ray leaves the input image, or has no pixel
at all), it is 0; the input image's area is [0, W] x [0, H] in pixel coordinates, so a sample within
half a pixel of the border takes the border pixel's value (OpenCV's BORDER_REPLICATE) rather than
a blend with black. With the pinhole `undistorted_pinhole` chooses, no output pixel is blank.

The maps are cached per lens pair (`functools.lru_cache`): the photos of one camera compute them once.
Images are resampled on the host (OpenCV) and returned on the device and in the dtype they came in.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
import torch
from torch import Tensor

from ..geometry.lens import Lens, image_from_normalized, project, unproject
from ..utils.checks import SurfSplatInputError

MODES = {"bilinear": cv2.INTER_LINEAR, "bicubic": cv2.INTER_CUBIC, "nearest": cv2.INTER_NEAREST}
_MAP_CACHE = 16  # lens pairs whose maps are kept (16 maps of a 1920x1080 photo: about 265 MB)
_ROUND_TRIP_PX = 1e-3  # a pixel whose ray does not project back within this has no ray (fisheye > 90 deg)
_BLOCK_PIXELS = 1 << 19  # pixels of the maps computed at once (about 40 MB of float64 temporaries)


def _pixel_centres(width: int, rows: Tensor) -> Tensor:
    """[R, W, 2] pixel centres (x, y) of the given rows, top-left pixel centre (0.5, 0.5)."""
    ys, xs = torch.meshgrid(rows.to(torch.float64) + 0.5, torch.arange(width, dtype=torch.float64) + 0.5, indexing="ij")
    return torch.stack([xs, ys], dim=-1)


def _remap_coords(source: Lens, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """Pixels (x, y) of `source` (top-left centre at 0.5) -> cv2.remap's coordinates (top-left centre
    at 0), float32, NaN where the pixel lies outside the source image's area [0, W] x [0, H]."""
    inside = (x >= 0) & (x <= source.width) & (y >= 0) & (y <= source.height)  # False for NaN
    nan = torch.full_like(x, float("nan"))
    return torch.where(inside, x - 0.5, nan).to(torch.float32), torch.where(inside, y - 0.5, nan).to(torch.float32)


def _maps_by_rows(width: int, height: int, rows_to_maps) -> tuple[np.ndarray, np.ndarray]:
    """Maps [height, width] filled block of rows by block (memory bounded: float64 temporaries of at
    most _BLOCK_PIXELS pixels at a time), returned read-only."""
    map_x = np.empty((height, width), dtype=np.float32)
    map_y = np.empty((height, width), dtype=np.float32)
    step = max(1, _BLOCK_PIXELS // width)
    for start in range(0, height, step):
        rows = torch.arange(start, min(height, start + step))
        bx, by = rows_to_maps(rows)
        map_x[start : start + len(rows)] = bx.numpy()
        map_y[start : start + len(rows)] = by.numpy()
    map_x.flags.writeable = False
    map_y.flags.writeable = False
    return map_x, map_y


def _check_pinhole(pinhole: Lens, name: str) -> None:
    if not isinstance(pinhole, Lens) or not pinhole.is_pinhole:
        what = pinhole.model if isinstance(pinhole, Lens) else type(pinhole).__name__
        raise SurfSplatInputError(f"{name}: expected a pinhole Lens (PINHOLE or SIMPLE_PINHOLE), got {what}")


@lru_cache(maxsize=_MAP_CACHE)
def undistort_maps(lens: Lens, pinhole: Lens) -> tuple[np.ndarray, np.ndarray]:
    """For each pixel of `pinhole`, the pixel of `lens` it shows, as cv2.remap's maps.

    Returns (map_x, map_y), float32 [pinhole.height, pinhole.width], read-only, in cv2.remap's
    coordinates (the top-left pixel's centre at (0, 0)); NaN where the pixel's ray leaves the lens's
    image. Each pinhole pixel centre is lifted to its ray (pinhole K^-1) and projected by the lens
    (`project`'s `image_from_normalized`, COLMAP's ImgFromCam): no iteration.
    """
    _check_pinhole(pinhole, "undistort_maps: pinhole")
    fx, fy, cx, cy = pinhole.focal_and_centre
    # the pinhole's rays, K^-1 of its pixel centres: x/z depends on the column only, y/z on the row
    u = ((torch.arange(pinhole.width, dtype=torch.float64) + 0.5 - cx) / fx)[None, :]

    def rows_to_maps(rows: Tensor) -> tuple[Tensor, Tensor]:
        v = ((rows.to(torch.float64) + 0.5 - cy) / fy)[:, None]
        x, y = image_from_normalized(lens, u, v)
        shape = (len(rows), pinhole.width)
        return _remap_coords(lens, torch.broadcast_to(x, shape), torch.broadcast_to(y, shape))

    return _maps_by_rows(pinhole.width, pinhole.height, rows_to_maps)


@lru_cache(maxsize=_MAP_CACHE)
def distort_maps(pinhole: Lens, lens: Lens) -> tuple[np.ndarray, np.ndarray]:
    """For each pixel of `lens`, the pixel of `pinhole` it shows (the inverse warp of `undistort_maps`).

    Each lens pixel centre is lifted by `unproject` (COLMAP's CamFromImg, iterative where COLMAP's
    is); a pixel whose ray does not project back to it within 1e-3 px (no inverse there, or a fisheye
    ray at 90 degrees or more, where COLMAP's lift returns no ray) is NaN, as is a ray leaving the pinhole.
    """
    _check_pinhole(pinhole, "distort_maps: pinhole")

    def rows_to_maps(rows: Tensor) -> tuple[Tensor, Tensor]:
        pixels = _pixel_centres(lens.width, rows)
        rays = unproject(lens, pixels)
        rays3 = torch.cat([rays, torch.ones_like(rays[..., :1])], dim=-1)
        has_ray = (project(lens, rays3) - pixels).norm(dim=-1) <= _ROUND_TRIP_PX  # False for NaN
        target = project(pinhole, rays3)
        target = torch.where(has_ray[..., None], target, torch.full_like(target, float("nan")))
        return _remap_coords(pinhole, target[..., 0], target[..., 1])

    return _maps_by_rows(lens.width, lens.height, rows_to_maps)


def _remap(image: Tensor, source: Lens, maps: tuple[np.ndarray, np.ndarray], mode: str, name: str) -> Tensor:
    if mode not in MODES:
        raise SurfSplatInputError(f"{name}: mode must be one of {', '.join(MODES)}, got {mode!r}")
    if not isinstance(image, Tensor) or image.ndim not in (3, 4):
        shape = tuple(image.shape) if isinstance(image, Tensor) else type(image).__name__
        raise SurfSplatInputError(f"{name}: image must be [C, H, W] or [N, C, H, W], got {shape}")
    if tuple(image.shape[-2:]) != (source.height, source.width):
        raise SurfSplatInputError(
            f"{name}: image is {image.shape[-1]}x{image.shape[-2]} but its lens is {source.width}x{source.height} "
            "(a lens calibrated at another size: Lens.rescaled)"
        )
    if image.dtype not in (torch.float32, torch.float64, torch.uint8, torch.bool):
        raise SurfSplatInputError(f"{name}: image dtype must be float32, float64, uint8 or bool, got {image.dtype}")
    map_x, map_y = maps
    blank = np.isnan(map_x)
    # cv2.remap needs finite maps: blank pixels sample anywhere, then are set to 0
    mx = np.where(blank, 0.0, map_x).astype(np.float32)
    my = np.where(blank, 0.0, map_y).astype(np.float32)
    batch = image.reshape(-1, *image.shape[-2:])  # [N*C, H, W]
    host = batch.detach().cpu()
    if host.dtype == torch.bool:
        host = host.to(torch.uint8) if mode == "nearest" else host.to(torch.float32)
    hwc = np.ascontiguousarray(host.permute(1, 2, 0).numpy())  # [H, W, N*C]
    out = np.empty((mx.shape[0], mx.shape[1], hwc.shape[2]), dtype=hwc.dtype)
    for start in range(0, hwc.shape[2], 4):  # cv2.remap's cubic refuses more than 4 channels (OpenCV 5)
        chunk = np.ascontiguousarray(hwc[:, :, start : start + 4])
        res = cv2.remap(chunk, mx, my, MODES[mode], borderMode=cv2.BORDER_REPLICATE)
        out[:, :, start : start + 4] = res.reshape(mx.shape[0], mx.shape[1], -1)
    if mode == "bicubic" and hwc.size:
        # cubic weights overshoot: keep the result within the values the image holds ([0, 1] photos stay so)
        np.clip(out, hwc.min(axis=(0, 1)), hwc.max(axis=(0, 1)), out=out)
    out[blank] = 0
    result = torch.from_numpy(out).permute(2, 0, 1).reshape(*image.shape[:-2], *mx.shape)
    if image.dtype == torch.bool and mode == "nearest":
        result = result.to(torch.bool)
    return result.to(image.device)


def undistort(image: Tensor, lens: Lens, pinhole: Lens, mode: str = "bilinear") -> Tensor:
    """An image of `lens` resampled to `pinhole`: [C, H, W] or [N, C, H, W] at the lens's size ->
    the same at the pinhole's size. "bilinear" for photos and masks (float32 photos stay in [0, 1]:
    bilinear weights are convex; COLMAP's undistorter is bilinear too), "bicubic" for sharper photos
    (OpenCV's cubic, clipped to each channel's range in the image), "nearest" for depth maps.
    Pixels showing nothing of the lens's image are 0 (see the module docs). A bool mask comes back
    float32 under "bilinear" (its coverage) and bool under "nearest".

    A lens of turned photos (`Lens.orientation` 3, 6 or 8) takes the photo as displayed and `pinhole` as
    the displayed photo's (`surfsplat.data.cameras.pinhole_of`): the photo goes back to its stored pixels,
    is undistorted there to the stored pinhole, and the result is turned for display. Each turn is an
    exact permutation of pixels, so this is COLMAP's undistortion of the stored photo, displayed."""
    if lens.orientation != 1:
        from ..geometry.orientation import INVERSE, displayed_image, stored_image
        from .cameras import turned_pinhole

        o = lens.orientation
        stored_lens, stored_pinhole = lens.stored(), turned_pinhole(pinhole, INVERSE[o])
        flat = _remap(
            stored_image(image, o), stored_lens, undistort_maps(stored_lens, stored_pinhole), mode, "undistort"
        )
        return displayed_image(flat, o)
    return _remap(image, lens, undistort_maps(lens, pinhole), mode, "undistort")


def distort(image: Tensor, pinhole: Lens, lens: Lens, mode: str = "bilinear") -> Tensor:
    """The inverse warp: an image of `pinhole` resampled to what `lens` would have seen, [C, H, W] or
    [N, C, H, W] at the pinhole's size -> the lens's size. For tests and benchmarks: distorted photos
    with known coefficients, made from pinhole ones."""
    return _remap(image, pinhole, distort_maps(pinhole, lens), mode, "distort")
