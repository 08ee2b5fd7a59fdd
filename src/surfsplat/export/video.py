"""MP4 videos of rendered camera paths (H.264 through the ffmpeg binary that imageio-ffmpeg ships).

    write_video("turntable.mp4", frames, fps=24)   # frames [T, 3, H, W] in [0, 1]

The file is encoded under a temporary name and renamed into place, so an interrupted export never
leaves a truncated video under the final name.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..utils.atomic import atomic_path
from ..utils.checks import SurfSplatInputError, check_tensor
from .images import to_uint8


def video_unavailable() -> str | None:
    """Why MP4 videos cannot be written here, or None when they can."""
    if importlib.util.find_spec("imageio_ffmpeg") is None:
        return "the imageio-ffmpeg package (which ships the ffmpeg binary) is not installed: pip install imageio-ffmpeg"
    return None


def write_video(path: str | os.PathLike, frames: Tensor, fps: float = 24.0, quality: float = 8.0) -> Path:
    """Encode frames [T, 3, H, W] in [0, 1] as an H.264 MP4 (yuv420p, playable everywhere).

    yuv420p halves the chroma resolution, so odd widths or heights are padded by one black
    column or row rather than resized (resizing would blur every frame). quality: 0-10 (ffmpeg's
    scale through imageio, 10 = best).
    """
    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise SurfSplatInputError(f"{path}: expected a .mp4 file name")
    check_tensor("frames", frames, ("T", 3, "H", "W"))
    if frames.shape[0] < 1:
        raise SurfSplatInputError("frames: expected at least one frame")
    if not fps > 0:
        raise SurfSplatInputError(f"fps: expected a positive frame rate, got {fps}")
    if not 0 <= quality <= 10:
        raise SurfSplatInputError(f"quality: expected a value in [0, 10], got {quality}")
    reason = video_unavailable()
    if reason is not None:
        raise SurfSplatInputError(f"{path}: cannot write MP4: {reason}")
    import imageio.v3 as iio

    data = np.stack([to_uint8(f) for f in frames.detach().to("cpu", torch.float32)])  # [T, H, W, 3]
    _, h, w, _ = data.shape
    data = np.pad(data, ((0, 0), (0, h % 2), (0, w % 2), (0, 0)))
    with atomic_path(path, suffix=".mp4") as tmp:  # ffmpeg picks the container from the suffix
        iio.imwrite(tmp, data, plugin="FFMPEG", fps=fps, codec="libx264", quality=quality, macro_block_size=1)
    return path


def read_video(path: str | os.PathLike) -> Tensor:
    """Decode an MP4 into frames [T, 3, H, W] in [0, 1] (for tests and previews)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such video file")
    reason = video_unavailable()
    if reason is not None:
        raise SurfSplatInputError(f"{path}: cannot read MP4: {reason}")
    import imageio.v3 as iio

    data = iio.imread(path, plugin="FFMPEG")  # [T, H, W, 3] uint8
    return torch.from_numpy(np.ascontiguousarray(data)).permute(0, 3, 1, 2).float() / 255
