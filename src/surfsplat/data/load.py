"""`load_scene`: one entry point for every single-scene format, with format auto-detection;
`load_scene_cameras`: the same scene's cameras alone, from camera records and image headers."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Literal

import torch

from ..utils.checks import SurfSplatInputError
from .cameras import CameraSet
from .formats.blender import is_blender, load_blender
from .formats.colmap import is_colmap, load_colmap
from .formats.dtu import is_dtu, load_dtu
from .formats.llff import is_llff, load_llff
from .formats.re10k_raw import is_re10k_raw, load_re10k_raw
from .posed_images import PosedImages

SceneFormat = Literal["llff", "dtu", "blender", "colmap", "re10k"]

# Detection order matters where layouts overlap: LLFF and nerfstudio folders often also hold the
# COLMAP model they were made from, and their own camera file is the one to trust.
DETECTORS: dict[str, Callable[[Path], bool]] = {
    "re10k": is_re10k_raw,
    "llff": is_llff,
    "dtu": is_dtu,
    "blender": is_blender,
    "colmap": is_colmap,
}

EXPECTED_FILES = {
    "re10k": "<key>.txt with a frames folder",
    "llff": "poses_bounds.npy",
    "dtu": "cameras_sphere.npz",
    "blender": "transforms.json",
    "colmap": "sparse/0/cameras.bin or .txt",
}


def detect_format(path: str | Path) -> str:
    """The format of a scene folder (or file), or a FileNotFoundError listing what was looked for."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: not found")
    for name, detector in DETECTORS.items():
        if detector(path):
            return name
    wanted = "; ".join(f"{k}: {v}" for k, v in EXPECTED_FILES.items())
    raise FileNotFoundError(f"{path}: no known scene layout ({wanted})")


def load_scene(
    path: str | Path,
    format: SceneFormat | None = None,
    *,
    images: str | None = None,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    split: str = "train",
    apply_scale_mat: bool = True,
    frames: str | Path | None = None,
    dtype: torch.dtype = torch.float32,
) -> PosedImages:
    """Read one captured scene into a `PosedImages` (images [N, 3, H, W] in [0, 1], OpenCV c2w, pixel K).

    format: "llff" | "dtu" | "blender" | "colmap" | "re10k" (raw camera .txt), or None to detect.
    images: image folder name under the scene (`images_8` for LLFF, `images_4` for DTU, a
        downscaled nerfstudio/COLMAP folder); K is scaled to the images' size.
    background: colour RGBA images are composited on (Blender/nerfstudio; white as in NeRF).
    split: Blender's transforms_{split}.json when there is no transforms.json.
    apply_scale_mat: DTU: express the world in IDR's normalized frame (object in the unit sphere).
    frames: RealEstate10K: the folder of extracted frames, when not beside the .txt.
    dtype: dtype of the cameras (float64 keeps the source precision).
    """
    options = dict(images=images, split=split, apply_scale_mat=apply_scale_mat, frames=frames, dtype=dtype)
    return _read(path, format, background=background, cameras_only=False, **options)


def load_scene_cameras(
    path: str | Path,
    format: SceneFormat | None = None,
    *,
    images: str | None = None,
    split: str = "train",
    apply_scale_mat: bool = True,
    frames: str | Path | None = None,
    dtype: torch.dtype = torch.float64,
) -> CameraSet:
    """The cameras of a scene folder `load_scene` reads, as a `CameraSet`: from the format's camera
    records and the images' headers, without decoding a pixel. Options as for `load_scene`."""
    options = dict(images=images, split=split, apply_scale_mat=apply_scale_mat, frames=frames, dtype=dtype)
    return _read(path, format, background=None, cameras_only=True, **options)


def _read(path, format, *, images, background, split, apply_scale_mat, frames, dtype, cameras_only):
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: not found")
    fmt = format or detect_format(path)
    only = {"dtype": dtype, "cameras_only": cameras_only}
    if fmt == "llff":
        return load_llff(path, images=images, **only)
    if fmt == "dtu":
        return load_dtu(path, images=images, apply_scale_mat=apply_scale_mat, **only)
    if fmt == "blender":
        return load_blender(path, split=split, images=images, background=background or (1.0, 1.0, 1.0), **only)
    if fmt == "colmap":
        return load_colmap(path, images=images, **only)
    if fmt == "re10k":
        return load_re10k_raw(path, frames=Path(frames) if frames is not None else None, **only)
    raise SurfSplatInputError(f"format: expected one of {sorted(DETECTORS)}, got {format!r}")
