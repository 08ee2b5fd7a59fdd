"""What `reconstruct` takes, checked where it enters: photos (paths or arrays), a folder, a video.

Every check here runs before anything heavy (pose estimation, the model) and raises one
SurfSplatInputError (or FileNotFoundError) naming the file or the argument; the CLI prints it as
one line. The option names in brackets are the command line's.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..capture import FrameConfig, VideoFrames, is_video_file, select_video_frames
from ..utils.checks import SurfSplatInputError

logger = logging.getLogger(__name__)

ImageSource = str | os.PathLike | np.ndarray | Tensor  # a file, uint8 / float [H, W, 3] array, or [3, H, W] tensor


@dataclass
class CaptureInput:
    """The views of a capture, not yet decoded at full size (photos are read one pass at a time)."""

    names: list[str]  # one per view, unique (cameras are keyed by them)
    paths: list[Path | None]  # the file of each view (None for arrays and video frames)
    arrays: list[np.ndarray | None]  # uint8 [H, W, 3] of views given as arrays or decoded from a video
    width: int  # the reference size: the first view of the most common orientation (see reference_size)
    height: int
    ordered: bool  # the views follow a path (video frames): neighbours in the list overlap most
    video: VideoFrames | None = None
    sources: list[str] = field(default_factory=list)  # what each view came from, for the summary
    sizes: list[tuple[int, int]] = field(default_factory=list)  # (width, height) of each view as displayed
    orientations: list[int] = field(default_factory=list)  # EXIF orientation of each view's file (1: none)
    # each view's (source lens, pinhole) where the cameras have a lens: its photo is undistorted to the
    # pinhole as it is read, and width x height are the pinhole's (None: the photos are pinhole)
    lenses: list[tuple] | None = None

    def __len__(self) -> int:
        return len(self.names)

    def subset(self, keep: list[int]) -> CaptureInput:
        def pick(items: list) -> list:
            return [items[i] for i in keep]

        return CaptureInput(
            pick(self.names),
            pick(self.paths),
            pick(self.arrays),
            self.width,
            self.height,
            self.ordered,
            self.video,
            pick(self.sources),
            pick(self.sizes),
            pick(self.orientations),
            None if self.lenses is None else pick(self.lenses),
        )

    def image(self, i: int) -> Tensor:
        """View i as float32 [3, H, W] in [0, 1] (transparent photos composited on black, as the model saw in
        training), undistorted to its pinhole where the cameras have a lens."""
        from ..data.images import read_image

        if self.paths[i] is not None:
            rgb, _ = read_image(self.paths[i], background=(0.0, 0.0, 0.0))
        else:
            rgb = torch.from_numpy(np.ascontiguousarray(self.arrays[i])).permute(2, 0, 1).float() / 255
        if self.lenses is not None and not self.lenses[i][0].is_pinhole:
            from ..data.undistort import undistort

            rgb = undistort(rgb, *self.lenses[i])
        return rgb

    def pose_inputs(self) -> list:
        """What pose estimation reads: the files where there are files (EXIF focal), else the arrays."""
        return [p if p is not None else a for p, a in zip(self.paths, self.arrays)]


def read_capture(images: ImageSource | Sequence[ImageSource], frames: FrameConfig) -> CaptureInput:
    """The views of `images`: a list of photos (paths or arrays), a folder of photos, or a video file."""
    from ..data.images import image_orientation, list_images, read_image_size

    if isinstance(images, (str, os.PathLike)):
        path = Path(images)
        if path.is_dir():
            files = list_images(path)
            if not files:
                raise SurfSplatInputError(f"{path}: the folder holds no images (png, jpg, ...)")
            return read_capture(files, frames)
        if is_video_file(path):
            video = select_video_frames(path, frames)
            h, w = video.frames[0].shape[:2]
            sources = [f"{path}#{n}" for n in video.names]
            n = len(video.frames)
            return CaptureInput(
                video.names, [None] * n, video.frames, w, h, True, video, sources, [(w, h)] * n, [1] * n
            )
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such image folder or video file")
        raise SurfSplatInputError(
            f"images (--images): {path} is one file; expected two or more images, a folder of images or a video"
        )
    if isinstance(images, (np.ndarray, Tensor)):
        raise SurfSplatInputError("images: expected a list of images, a folder or a video, got a single array")
    items = list(images)
    if len(items) < 2:
        raise SurfSplatInputError(
            f"images (--images): the model matches views, expected at least 2 images, got {len(items)}"
        )
    names, paths, arrays, sizes, sources, orientations = [], [], [], [], [], []
    for i, item in enumerate(items):
        if isinstance(item, (str, os.PathLike)):
            path = Path(item)
            if not path.is_file():
                raise FileNotFoundError(f"{path}: image file not found")
            names.append(path.name)
            paths.append(path)
            arrays.append(None)
            sizes.append(read_image_size(path))  # as displayed: EXIF orientation applied
            orientations.append(image_orientation(path))
            sources.append(str(path))
        elif isinstance(item, (np.ndarray, Tensor)):
            array = _uint8_image(item, f"images[{i}]")
            names.append(f"view_{i:03d}")
            paths.append(None)
            arrays.append(array)
            sizes.append((array.shape[1], array.shape[0]))
            orientations.append(1)
            sources.append(f"images[{i}] (array)")
        else:
            raise SurfSplatInputError(f"images[{i}]: expected a path or an image array, got {type(item).__name__}")
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated and all(p is not None for p in paths) and len({Path(p).resolve() for p in paths}) == len(paths):
        raise SurfSplatInputError(
            f"images (--images): file names must be unique (cameras are keyed by name): {repeated}"
        )
    _warn_mirrored(names, orientations)
    width, height = reference_size(sizes)
    return CaptureInput(names, paths, arrays, width, height, False, None, sources, sizes, orientations)


def _warn_mirrored(names: list[str], orientations: list[int]) -> None:
    """Photos an EXIF orientation shows mirrored (2, 4, 5, 7) are read as shown: a mirror image of the
    scene, which matches unmirrored photos of it under no camera (see surfsplat.geometry.orientation)."""
    from ..geometry.orientation import MIRRORED

    mirrored = [f"{n} (orientation {o})" for n, o in zip(names, orientations) if o in MIRRORED]
    if mirrored:
        logger.warning(
            f"{', '.join(mirrored)}: shown mirrored by the EXIF orientation and read so; a mirror image fits "
            "no camera that also sees the unmirrored scene (save such photos unmirrored)"
        )


def reference_size(sizes: list[tuple[int, int]]) -> tuple[int, int]:
    """The (width, height) a capture of several sizes is worked at: the first view of the most common
    orientation (landscape, portrait or square; a tie goes to the first view's), so most views keep
    their whole frame and the others are cropped (`surfsplat.reconstruction.sizes`)."""

    def shape(size: tuple[int, int]) -> int:
        return (size[0] > size[1]) - (size[0] < size[1])  # 1 landscape, -1 portrait, 0 square

    counts = {k: sum(shape(s) == k for s in sizes) for k in (1, -1, 0)}
    most = max(counts.values())
    winner = next(shape(s) for s in sizes if counts[shape(s)] == most)
    return next(s for s in sizes if shape(s) == winner)


def _uint8_image(item: np.ndarray | Tensor, source: str) -> np.ndarray:
    """[H, W, 3] uint8 from an [H, W, 3] array (uint8, or float in [0, 1]) or a [3, H, W] tensor in [0, 1]."""
    if isinstance(item, Tensor):
        if item.ndim != 3 or item.shape[0] != 3:
            raise SurfSplatInputError(f"{source}: expected a [3, H, W] tensor, got shape {tuple(item.shape)}")
        item = item.detach().to("cpu", torch.float32).permute(1, 2, 0).numpy()
    if item.ndim != 3 or item.shape[2] != 3:
        raise SurfSplatInputError(f"{source}: expected an RGB image [H, W, 3], got shape {tuple(item.shape)}")
    if item.dtype == np.uint8:
        return np.ascontiguousarray(item)
    if not np.issubdtype(item.dtype, np.floating) or not np.isfinite(item).all():
        raise SurfSplatInputError(f"{source}: expected uint8 or finite float values in [0, 1], got {item.dtype}")
    if item.min() < 0 or item.max() > 1:
        raise SurfSplatInputError(
            f"{source}: expected float values in [0, 1], got [{item.min():.4g}, {item.max():.4g}]"
        )
    return np.round(item * 255).astype(np.uint8)
