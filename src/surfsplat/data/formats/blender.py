"""Blender (NeRF synthetic) and nerfstudio `transforms.json` captures.

Each frame has `file_path` (relative to the JSON file; Blender omits the `.png` suffix) and
`transform_matrix`, a camera-to-world matrix with OpenGL/Blender axes (x right, y up, z back).
Intrinsics: Blender gives `camera_angle_x` (horizontal field of view, principal point at the
image centre); nerfstudio gives `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h` at the top level or per frame.
RGBA images are composited on a background colour and their alpha becomes the scene's masks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from ...geometry.cameras import Cameras
from ...utils.checks import SurfSplatInputError, read_json
from ..posed_images import PosedImages, check_finite_rows, downscale_from_folder, fit_intrinsics
from .common import camera_set, image_sizes, load_image_stack, make_cameras

DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


def find_transforms(path: Path, split: str) -> Path | None:
    if path.is_file() and path.suffix == ".json":
        return path
    if path.is_dir():
        for name in ("transforms.json", f"transforms_{split}.json"):
            if (path / name).is_file():
                return path / name
    return None


def is_blender(path: Path) -> bool:
    return find_transforms(path, "train") is not None


def _number(entry: dict[str, Any], key: str, source: str) -> float:
    value = entry[key]
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
        raise SurfSplatInputError(f"{source}: field '{key}' must be a finite number, got {value!r}")
    return float(value)


def _resolve_image(json_dir: Path, file_path: str, images: str | None) -> Path:
    rel = Path(file_path)
    if images is not None and rel.parts and rel.parts[0].startswith("images"):
        # nerfstudio keeps downscaled copies in sibling folders images_2, images_4, ...
        rel = Path(images, *rel.parts[1:])
    candidate = json_dir / rel
    if candidate.suffix == "" and not candidate.is_file():
        candidate = candidate.with_suffix(".png")  # Blender synthetic omits the suffix
    return candidate


@dataclass
class TransformsCameras:
    """Cameras of a transforms.json and the image files they belong to (pixels not decoded)."""

    json_path: Path
    paths: list[Path]
    cameras: Cameras
    frames: list[dict[str, Any]]  # the JSON frame entries, in file order


def read_transforms(
    path: Path,
    split: str = "train",
    images: str | None = None,
    dtype: torch.dtype = torch.float32,
) -> TransformsCameras:
    """Parse and validate a transforms.json (see load_blender); images are only opened for their size."""
    json_path = find_transforms(path, split)
    if json_path is None:
        raise FileNotFoundError(f"{path}: no transforms.json or transforms_{split}.json")
    meta = read_json(json_path)
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise SurfSplatInputError(f"{json_path}: missing key 'frames' (a list of frames)")
    frames = meta["frames"]
    if not frames:
        raise SurfSplatInputError(f"{json_path}: 'frames' is empty")

    paths: list[Path] = []
    c2w_gl = []
    for i, frame in enumerate(frames):
        where = f"{json_path}: frame {i}"
        if not isinstance(frame, dict):
            raise SurfSplatInputError(f"{where}: expected an object, got {type(frame).__name__}")
        for key in ("file_path", "transform_matrix"):
            if key not in frame:
                raise SurfSplatInputError(f"{where}: missing key '{key}'")
        try:
            matrix = torch.tensor(frame["transform_matrix"], dtype=torch.float64)
        except (TypeError, ValueError, RuntimeError) as err:
            raise SurfSplatInputError(f"{where}: transform_matrix is not a numeric matrix ({err})") from None
        if matrix.shape == (3, 4):
            matrix = torch.cat([matrix, torch.tensor([[0, 0, 0, 1.0]], dtype=torch.float64)])
        if matrix.shape != (4, 4):
            raise SurfSplatInputError(f"{where}: transform_matrix has shape {list(matrix.shape)}, expected [4, 4]")
        c2w_gl.append(matrix)
        paths.append(_resolve_image(json_path.parent, str(frame["file_path"]), images))
    c2w_gl_t = torch.stack(c2w_gl)
    check_finite_rows(c2w_gl_t, str(json_path), "frame")
    for p in paths:
        if not p.is_file():
            raise FileNotFoundError(f"{p}: image file not found (listed in {json_path})")

    sizes = image_sizes(paths)
    Ks = []
    for i, (frame, size) in enumerate(zip(frames, sizes)):
        entry = {**meta, **frame}  # per-frame intrinsics override the shared ones
        where = f"{json_path}: frame {i}"
        model = entry.get("camera_model", "PINHOLE")
        distortion = {k: float(entry[k]) for k in DISTORTION_KEYS if k in entry}
        if any(v != 0 for v in distortion.values()):
            raise SurfSplatInputError(
                f"{where}: camera_model {model} has non-zero distortion {distortion}; "
                "undistort the images first (e.g. ns-process-data or COLMAP's image_undistorter)"
            )
        w, h = size
        if "fl_x" in entry:
            fx = _number(entry, "fl_x", where)
            fy = _number(entry, "fl_y", where) if "fl_y" in entry else fx
            cw = int(_number(entry, "w", where)) if "w" in entry else w
            ch = int(_number(entry, "h", where)) if "h" in entry else h
            cx = _number(entry, "cx", where) if "cx" in entry else cw / 2
            cy = _number(entry, "cy", where) if "cy" in entry else ch / 2
        elif "camera_angle_x" in entry:
            cw, ch = w, h
            fx = 0.5 * w / math.tan(0.5 * _number(entry, "camera_angle_x", where))
            fy = 0.5 * h / math.tan(0.5 * _number(entry, "camera_angle_y", where)) if "camera_angle_y" in entry else fx
            cx, cy = w / 2, h / 2
        else:
            raise SurfSplatInputError(f"{where}: no intrinsics (expected 'fl_x' or 'camera_angle_x')")
        K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
        Ks.append(
            fit_intrinsics(K, (cw, ch), size, str(paths[i]), allow_downscale=downscale_from_folder(paths[i].parent))
        )

    # OpenGL -> OpenCV flips the camera's y and z axes (the same matrix as Cameras.from_opengl,
    # applied here so that validation errors name the JSON file).
    c2w_cv = c2w_gl_t @ torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
    cameras = make_cameras(c2w_cv, torch.stack(Ks), str(json_path), dtype)
    return TransformsCameras(json_path, paths, cameras, frames)


def load_blender(
    path: Path,
    split: str = "train",
    images: str | None = None,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    dtype: torch.dtype = torch.float32,
    cameras_only: bool = False,
) -> PosedImages:
    """Read a transforms.json capture; `split` picks transforms_{split}.json when there is no
    transforms.json, `images` substitutes a downscaled image folder (nerfstudio `images_4`),
    `background` is the colour RGBA images are composited on."""
    parsed = read_transforms(path, split=split, images=images, dtype=dtype)
    if cameras_only:
        names = [p.name for p in parsed.paths]
        return camera_set(parsed.cameras, parsed.paths, image_sizes(parsed.paths), names)
    rgb, alpha = load_image_stack(parsed.paths, background=background)
    return PosedImages(
        images=rgb,
        cameras=parsed.cameras,
        names=[p.name for p in parsed.paths],
        masks=alpha,
        source=str(parsed.json_path),
    )
