"""Captures whose photos differ in size or orientation (portrait and landscape, two phones).

Each view keeps its own intrinsics, in pixels of its own photo as displayed (`view_cameras`);
the network then sees every view at one working size, each view rescaled and centre-cropped on
its own by `surfsplat.data.transforms.rescale_and_crop` (its K follows exactly). The working
size's aspect is the reference view's (`inputs.reference_size`: the most common orientation), so
a view of another aspect loses the part of its frame outside that aspect: `crop_report` says
which views and how much, and `reconstruct` logs it as a warning.

Which image a camera file's K describes: K in pixels of the calibrated width x height, rescaled
uniformly to each photo. A photo whose EXIF orientation turns it by 90 degrees (5-8) and whose
displayed size is the transpose of the calibrated aspect was calibrated on its STORED pixels (as
COLMAP, nerfstudio and instant-ngp do): its camera is turned with it
(`surfsplat.geometry.orientation.displayed_camera`).
"""

from __future__ import annotations

import torch

from ..data.cameras import CameraSet, is_uniform_rescale
from ..geometry.cameras import Cameras
from ..geometry.orientation import TRANSPOSED, displayed_camera, stored_size
from ..utils.checks import SurfSplatInputError

CROP_WARN_SHARE = 0.9  # a view keeping less than this share of its pixels is named in the warning


def view_cameras(
    given: CameraSet,
    sizes: list[tuple[int, int]],
    orientations: list[int],
    names: list[str],
    source: str,
    own_pixels: bool = False,
) -> Cameras:
    """The cameras of the views, each K in pixels of that view's displayed photo (sizes[i]).

    own_pixels: each K is already in pixels of its own view (Cameras given one per view), kept as they are.
    Otherwise K is in pixels of given.width x given.height, rescaled uniformly per view; a view turned by
    its EXIF orientation (5-8) whose stored size fits the calibrated one is turned with its camera, and so
    is every view an orientation turns (3, 6, 8) where the cameras are of the stored pixels
    (`CameraSet.stored_pixels`); a mirrored one is one error line."""
    if own_pixels:
        return given.cameras
    calibrated = (given.width, given.height)
    crop = given.crop
    Ks, c2ws = [], []
    for i, (w, h) in enumerate(sizes):
        K, c2w = given.cameras.K[i], given.cameras.c2w[i]
        turn = orientations[i] if orientations else 1
        if given.stored_pixels and turn != 1:
            # cameras of the stored pixels (a COLMAP model read without its photos): the photo's stored
            # size is the calibrated one or a uniform rescale of it, and its camera turns with the photo
            sw, sh = stored_size(turn, w, h)
            if not is_uniform_rescale(calibrated, (sw, sh)):
                raise SurfSplatInputError(
                    f"{source}: {names[i]} is {w}x{h} as displayed (EXIF orientation {turn}; stored {sw}x{sh}) but "
                    f"the cameras are for {given.width}x{given.height} (only a uniform rescale of the calibrated "
                    "size is accepted)"
                )
            stored = K * torch.tensor([sw / given.width, sh / given.height, 1.0], dtype=K.dtype)[:, None]
            K2, c2w2, _ = displayed_camera(stored, c2w, sw, sh, turn, source=f"{source}: {names[i]}")
            Ks.append(K2)
            c2ws.append(c2w2)
        elif given.fits(w, h):  # a uniform rescale, or the photos a working crop was cut from
            resized = given.resized(w, h, f"{source}: {names[i]}")
            Ks.append(resized.K[i])
            c2ws.append(resized.c2w[i])
        elif orientations[i] in TRANSPOSED and is_uniform_rescale(calibrated, (h, w)):
            # calibrated on the stored pixels: the camera turns with the photo
            stored = K * torch.tensor([h / given.width, w / given.height, 1.0], dtype=K.dtype)[:, None]
            K2, c2w2, _ = displayed_camera(stored, c2w, h, w, orientations[i], source=f"{source}: {names[i]}")
            Ks.append(K2)
            c2ws.append(c2w2)
        else:
            also = f" or the {crop.source_width}x{crop.source_height} photos they were cropped from" if crop else ""
            raise SurfSplatInputError(
                f"{source}: {names[i]} is {w}x{h} but the cameras are for {given.width}x{given.height}{also} (only "
                "a uniform rescale of the calibrated size is accepted, or of its transpose for a photo its EXIF "
                "orientation turns by 90 degrees)"
            )
    return Cameras(torch.stack(c2ws), torch.stack(Ks))


def kept_share(size: tuple[int, int], shape: tuple[int, int]) -> float:
    """The share of a width x height view's frame that rescale_and_crop to shape = (height, width) keeps."""
    (w, h), (H, W) = size, shape
    scale = max(H / h, W / w)
    return (H * W) / (max(H, round(h * scale)) * max(W, round(w * scale)))


def crop_report(sizes: list[tuple[int, int]], names: list[str], shape: tuple[int, int]) -> str | None:
    """One line naming the views that lose more than 1 - CROP_WARN_SHARE of their frame to the working
    size, and what they keep; None when every view keeps (nearly) all of it, or when the photos share
    one shape (a working size of another shape given with --size crops them all alike, as it always did)."""
    aspects = [w / h for w, h in sizes]
    if max(aspects) <= min(aspects) * 1.01:
        return None
    cut = []
    for name, size in zip(names, sizes):
        share = kept_share(size, shape)
        if share < CROP_WARN_SHARE:
            (w, h), (H, W) = size, shape
            sides = "top and bottom" if h / w > H / W else "left and right"
            cut.append(f"{name} ({w}x{h}) keeps {share:.0%}, its {sides} cut")
    if not cut:
        return None
    return (
        f"the photos differ in shape: every view is cropped to the working size {shape[1]}x{shape[0]}; "
        + "; ".join(cut)
        + " (give --size for another working size, or photos of one orientation)"
    )
