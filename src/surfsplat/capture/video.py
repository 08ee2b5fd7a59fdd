"""Frames of a video worth reconstructing from: decoded through imageio-ffmpeg, chosen by motion and sharpness.

    video = select_video_frames("capture.mp4", FrameConfig())
    video.frames      # the chosen frames, uint8 [H, W, 3] at the matching size
    video.names       # frame_000012, ... (the frame numbers they had in the video)
    video.records     # every decoded frame: kept or why not

Two decoding passes, each scaled by ffmpeg itself so no full-size frame is ever held:
1. analysis at `analysis_size` (long side): the sharpness of every frame, the variance of the
   Laplacian of its grey image (a blurred frame has little high-frequency energy), and a 64-pixel
   grey thumbnail for motion.
2. the chosen frames at `max_size` (long side), the size pose estimation matches at.
Selection, in this order:
- blur: a frame is dropped when its sharpness is below `blur_ratio` times the median sharpness of
  the frames around it (`blur_window` each side). Relative to its neighbours, since absolute
  sharpness depends on what is filmed (a white wall is never "sharp").
- motion: walking the sharp frames in order, a frame is kept when its thumbnail differs from the
  last kept one's by `min_motion` (mean absolute grey difference in [0, 1]) or more; the others
  are near-duplicates of it (a still camera, a repeated frame). The first sharp frame is kept.
- budget: above `max_frames` kept frames, an evenly spaced subset of them stays.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..utils.checks import SurfSplatInputError

VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm", ".mpg", ".mpeg")
THUMBNAIL_SIZE = 64  # long side of the grey thumbnails motion is measured on


def is_video_file(path: str | os.PathLike) -> bool:
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


def frame_name(index: int) -> str:
    """The name a video frame's camera carries: its frame number in the video."""
    return f"frame_{index:06d}"


@dataclass(frozen=True)
class FrameConfig:
    """How frames are chosen from a video (sizes are long sides in pixels)."""

    max_size: int = 960  # frames are kept at this size for pose estimation (never upscaled)
    analysis_size: int = 640  # sharpness and motion are measured at this size (never upscaled)
    min_motion: float = 0.02  # mean absolute grey difference in [0, 1] from the last kept frame
    blur_ratio: float = 0.5  # blurred: sharpness below this share of the local median
    blur_window: int = 7  # frames each side of the local median
    max_frames: int | None = None  # at most this many frames (evenly spaced among the chosen), None: all

    def __post_init__(self) -> None:
        if self.max_size < 64 or self.analysis_size < 64:
            raise SurfSplatInputError(
                f"max_size and analysis_size: expected at least 64 pixels, got {self.max_size}, {self.analysis_size}"
            )
        if not (math.isfinite(self.min_motion) and self.min_motion >= 0):
            raise SurfSplatInputError(f"min_motion: expected a value >= 0, got {self.min_motion}")
        if not 0 <= self.blur_ratio < 1:
            raise SurfSplatInputError(f"blur_ratio: expected a value in [0, 1), got {self.blur_ratio}")
        if self.blur_window < 1:
            raise SurfSplatInputError(f"blur_window: expected at least 1 frame, got {self.blur_window}")
        if self.max_frames is not None and self.max_frames < 2:
            raise SurfSplatInputError(f"max_frames: expected at least 2 frames, got {self.max_frames}")


@dataclass
class FrameRecord:
    """One decoded frame and what selection made of it."""

    index: int  # frame number in the video (0-based)
    kept: bool
    reason: str  # "kept", or why it was dropped
    sharpness: float  # variance of the Laplacian of the grey frame at the analysis size
    motion: float | None  # mean absolute grey difference from the last kept frame (None: the first)


@dataclass
class VideoFrames:
    """The frames chosen from a video, with the record of every decoded frame."""

    path: Path
    fps: float
    width: int  # of the video
    height: int
    frames: list[np.ndarray]  # chosen frames, uint8 [h, w, 3] at the matching size
    indices: list[int]  # their frame numbers
    records: list[FrameRecord] = field(default_factory=list)
    config: FrameConfig = field(default_factory=FrameConfig)

    @property
    def names(self) -> list[str]:
        return [frame_name(i) for i in self.indices]

    def dropped(self) -> dict[str, int]:
        """How many frames were dropped for each reason (the reason's first word)."""
        counts: dict[str, int] = {}
        for r in self.records:
            if not r.kept:
                key = r.reason.split(" ")[0]
                counts[key] = counts.get(key, 0) + 1
        return counts

    def to_dict(self) -> dict:
        return {
            "video": str(self.path),
            "fps": self.fps,
            "size": [self.width, self.height],
            "decoded": len(self.records),
            "used": self.names,
            "dropped": self.dropped(),
            "config": vars(self.config),
            "frames": [vars(r) for r in self.records],
        }

    def lines(self) -> list[str]:
        dropped = ", ".join(f"{n} {why}" for why, n in self.dropped().items()) or "none"
        return [
            f"{self.path.name}: {len(self.records)} frames of {self.width}x{self.height} at {self.fps:g} fps; "
            f"using {len(self.indices)} (dropped: {dropped})"
        ]


def select_video_frames(path: str | os.PathLike, config: FrameConfig | None = None) -> VideoFrames:
    """The frames of a video to reconstruct from (see the module docstring). Raises
    SurfSplatInputError naming the file when it cannot be decoded or holds fewer than two usable
    frames (a still camera, or every other frame blurred)."""
    cfg = config or FrameConfig()
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: video file not found")
    width, height, fps = _probe(path)
    analysis = _fit(width, height, cfg.analysis_size)
    sharpness, thumbs = [], []
    for frame in _decode(path, analysis):
        grey = frame.astype(np.float32) @ np.array([0.299, 0.587, 0.114], dtype=np.float32) / 255.0
        sharpness.append(_laplacian_variance(grey))
        thumbs.append(_thumbnail(grey))
    if not sharpness:
        raise SurfSplatInputError(f"{path}: the video has no frames")
    records = choose_frames(np.array(sharpness), np.stack(thumbs), cfg)
    kept = [r.index for r in records if r.kept]
    if len(kept) < 2:
        raise SurfSplatInputError(
            f"{path}: only {len(kept)} usable frame among {len(records)} (the others are near-duplicates of it "
            "or blurred): the camera did not move; film while moving around the scene"
        )
    wanted = set(kept)
    frames = [f.copy() for i, f in enumerate(_decode(path, _fit(width, height, cfg.max_size))) if i in wanted]
    if len(frames) != len(kept):
        raise SurfSplatInputError(f"{path}: the second decoding gave {len(frames)} of the {len(kept)} chosen frames")
    return VideoFrames(path, fps, width, height, frames, kept, records, cfg)


def choose_frames(sharpness: np.ndarray, thumbnails: np.ndarray, config: FrameConfig) -> list[FrameRecord]:
    """The selection on measured frames: sharpness [T], grey thumbnails [T, h, w] in [0, 1]."""
    n = len(sharpness)
    records = [FrameRecord(i, False, "", float(sharpness[i]), None) for i in range(n)]
    sharp = np.ones(n, dtype=bool)
    for i in range(n):
        lo, hi = max(0, i - config.blur_window), min(n, i + config.blur_window + 1)
        local = float(np.median(sharpness[lo:hi]))
        if sharpness[i] < config.blur_ratio * local:
            sharp[i] = False
            records[
                i
            ].reason = f"blurred (sharpness {sharpness[i]:.3g} < {config.blur_ratio:g} x the local median {local:.3g})"
    last = None
    for i in np.flatnonzero(sharp):
        if last is None:
            records[i].kept, records[i].reason = True, "kept"
            last = i
            continue
        motion = float(np.abs(thumbnails[i] - thumbnails[last]).mean())
        records[i].motion = motion
        if motion >= config.min_motion:
            records[i].kept, records[i].reason = True, "kept"
            last = i
        else:
            records[
                i
            ].reason = f"near-duplicate of {frame_name(int(last))} (motion {motion:.4f} < {config.min_motion:g})"
    kept = [r.index for r in records if r.kept]
    if config.max_frames is not None and len(kept) > config.max_frames:
        chosen = {kept[round(k)] for k in np.linspace(0, len(kept) - 1, config.max_frames)}
        for i in kept:
            if i not in chosen:
                records[i].kept, records[i].reason = False, f"budget (more than max_frames={config.max_frames})"
    return records


def _fit(width: int, height: int, long_side: int) -> tuple[int, int]:
    """(w, h) with the long side at most `long_side`, even (what yuv video filters like), aspect kept."""
    s = min(1.0, long_side / max(width, height))
    return max(2, round(width * s / 2) * 2), max(2, round(height * s / 2) * 2)


def _probe(path: Path) -> tuple[int, int, float]:
    import imageio_ffmpeg

    try:
        reader = imageio_ffmpeg.read_frames(str(path))
        meta = next(reader)
        reader.close()
    except (RuntimeError, OSError, StopIteration, ValueError) as err:
        reason = str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__
        raise SurfSplatInputError(f"{path}: cannot read the video ({reason})") from None
    size = meta.get("size") or (0, 0)
    if not (size[0] > 0 and size[1] > 0):
        raise SurfSplatInputError(f"{path}: cannot read the video (no video stream)")
    return int(size[0]), int(size[1]), float(meta.get("fps") or 0.0)


def _decode(path: Path, size: tuple[int, int]):
    """Frames as uint8 [h, w, 3], scaled by ffmpeg to `size` = (w, h)."""
    import imageio_ffmpeg

    w, h = size
    reader = imageio_ffmpeg.read_frames(str(path), output_params=["-vf", f"scale={w}:{h}:flags=area"])
    try:
        next(reader)  # the metadata
        for data in reader:
            yield np.frombuffer(data, dtype=np.uint8).reshape(h, w, 3)
    except (RuntimeError, OSError) as err:
        raise SurfSplatInputError(f"{path}: decoding failed ({str(err).strip().splitlines()[-1]})") from None
    finally:
        reader.close()


def _laplacian_variance(grey: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian over the interior pixels."""
    lap = grey[1:-1, :-2] + grey[1:-1, 2:] + grey[:-2, 1:-1] + grey[2:, 1:-1] - 4 * grey[1:-1, 1:-1]
    return float(lap.var())


def _thumbnail(grey: np.ndarray) -> np.ndarray:
    """Area-averaged grey thumbnail with its long side at most THUMBNAIL_SIZE."""
    h, w = grey.shape
    f = max(1, math.ceil(max(h, w) / THUMBNAIL_SIZE))
    h2, w2 = h // f, w // f
    return grey[: h2 * f, : w2 * f].reshape(h2, f, w2, f).mean(axis=(1, 3))
