"""Blender (NeRF synthetic), nerfstudio and instant-ngp `transforms.json` captures.

Each frame has `file_path` (relative to the JSON file; Blender omits the `.png` suffix) and
`transform_matrix`, a camera-to-world matrix with OpenGL/Blender axes (x right, y up, z back).
Intrinsics, at the top level or per frame (a frame's own keys override the top level's):
- Blender: `camera_angle_x` (horizontal field of view in radians; `camera_angle_y` optional),
  principal point at the image centre;
- nerfstudio / instant-ngp: `fl_x` (`fl_y` defaults to it), `cx`, `cy` (default the centre), `w`, `h`
  (the calibrated size; instant-ngp writes them as floats);
- the lens: nerfstudio's `camera_model` (`PINHOLE`, `SIMPLE_PINHOLE`, `SIMPLE_RADIAL`, `RADIAL`,
  `OPENCV`: one perspective model with k1, k2, k3, p1, p2; `OPENCV_FISHEYE`: k1..k4), or, without
  `camera_model`, instant-ngp's: any non-zero k1, k2, k3, p1, p2 is its OpenCV model, and
  `is_fisheye: true` makes k1..k4 the OpenCV fisheye model's.
As COLMAP models (`surfsplat.geometry.lens`): a perspective lens is OPENCV (fx, fy, cx, cy, k1, k2,
p1, p2), or FULL_OPENCV (k3 its r^6 term) when k3 is non-zero: nerfstudio's radial factor is
1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8 (`camera_utils.radial_and_tangential_distort`), OpenCV's and
FULL_OPENCV's numerator the same up to r^6, so k3 carries over; nerfstudio's k4 (an r^8 term) has no
COLMAP model and is an error where non-zero (nerfstudio itself refuses it when undistorting). A
fisheye lens is OPENCV_FISHEYE (k1..k4 of theta, as both tools and COLMAP define it); tangential terms
there are an error. instant-ngp stores k3/k4 and p1/p2 in the same two slots and so drops k3 when
p1/p2 are present; its own colmap2nerf never writes a non-zero k3 for a perspective camera, so a
non-zero k3 is read with nerfstudio's (and OpenCV's) meaning. nerfstudio's `applied_transform` and
`applied_scale` are informational (the poses are used as the file gives them).
Lenses are undistorted at load to a pinhole (see `common.lens_view`); frames whose photo is missing
are left out with one warning (`common.present_views`).
RGBA images are composited on a background colour and their alpha becomes the scene's masks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from ...geometry.cameras import Cameras
from ...geometry.lens import Lens
from ...geometry.orientation import stored_size
from ...utils.checks import SurfSplatInputError, read_json
from ..images import image_orientation
from ..posed_images import PosedImages, check_finite_rows, downscale_from_folder
from .common import (
    camera_set,
    image_sizes,
    lens_view,
    load_image_stack,
    make_cameras,
    present_views,
    undistort_views,
    view_lenses,
)

DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
# nerfstudio's camera_model values of perspective cameras (its CAMERA_MODEL_TO_TYPE): one model whose
# distortion is whatever k1..k4, p1, p2 the file gives
PERSPECTIVE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
FISHEYE_MODELS = ("OPENCV_FISHEYE",)


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


def _size(entry: dict[str, Any], key: str, source: str) -> int:
    """A calibrated size in pixels: an integer, or a float holding one (instant-ngp writes 800.0)."""
    value = _number(entry, key, source)
    if value != round(value) or value < 1:
        raise SurfSplatInputError(f"{source}: field '{key}' must be a positive whole number of pixels, got {value!r}")
    return int(round(value))


def frame_lens(
    entry: dict[str, Any],
    image_size: tuple[int, int],
    source: str,
    frame_keys=None,
    top_source: str | None = None,
) -> Lens:
    """The lens of one frame (its keys over the top level's) at its calibrated size, as a COLMAP model.

    image_size: the stored pixels' (width, height), the default of a missing w / h. An error about a key
    names the frame (`source`) where the frame holds it (`frame_keys`), else the file's top level
    (`top_source`)."""
    if frame_keys is not None and top_source is not None:
        keys = set(frame_keys)
        frame_source = source

        def at(key: str) -> str:
            return frame_source if key in keys else top_source
    else:

        def at(key: str) -> str:
            return source

    w, h = image_size
    if "fl_x" in entry:
        fx = _number(entry, "fl_x", at("fl_x"))
        fy = _number(entry, "fl_y", at("fl_y")) if "fl_y" in entry else fx
        cw = _size(entry, "w", at("w")) if "w" in entry else w
        ch = _size(entry, "h", at("h")) if "h" in entry else h
        cx = _number(entry, "cx", at("cx")) if "cx" in entry else cw / 2
        cy = _number(entry, "cy", at("cy")) if "cy" in entry else ch / 2
    elif "camera_angle_x" in entry:
        cw = _size(entry, "w", at("w")) if "w" in entry else w
        ch = _size(entry, "h", at("h")) if "h" in entry else h
        fx = 0.5 * cw / math.tan(0.5 * _number(entry, "camera_angle_x", at("camera_angle_x")))
        angle_y = "camera_angle_y" in entry
        fy = 0.5 * ch / math.tan(0.5 * _number(entry, "camera_angle_y", at("camera_angle_y"))) if angle_y else fx
        cx, cy = cw / 2, ch / 2
    else:
        raise SurfSplatInputError(f"{source}: no intrinsics (expected 'fl_x' or 'camera_angle_x')")
    for key, value in (("fl_x", fx), ("fl_y", fy)):
        if not value > 0:
            raise SurfSplatInputError(f"{at(key)}: field '{key}' must be a positive focal length, got {value!r}")
    k = {key: _number(entry, key, at(key)) for key in DISTORTION_KEYS if key in entry}
    k1, k2, k3, k4, p1, p2 = (k.get(key, 0.0) for key in DISTORTION_KEYS)
    model = entry.get("camera_model")
    if model is None:  # instant-ngp: the keys present decide
        fisheye = entry.get("is_fisheye", False)
        if not isinstance(fisheye, bool):
            raise SurfSplatInputError(f"{at('is_fisheye')}: field 'is_fisheye' must be true or false, got {fisheye!r}")
        model = "OPENCV_FISHEYE" if fisheye else "OPENCV"
    elif model not in PERSPECTIVE_MODELS + FISHEYE_MODELS:
        supported = ", ".join(PERSPECTIVE_MODELS + FISHEYE_MODELS)
        raise SurfSplatInputError(
            f"{at('camera_model')}: field 'camera_model' is {model!r}, which is not supported ({supported})"
        )
    if model in FISHEYE_MODELS:
        for key in ("p1", "p2"):
            if k.get(key, 0.0) != 0:
                raise SurfSplatInputError(
                    f"{at(key)}: field '{key}' is {k[key]!r}, but the OpenCV fisheye model has no tangential terms"
                )
        return Lens("OPENCV_FISHEYE", cw, ch, (fx, fy, cx, cy, k1, k2, k3, k4))
    if k4 != 0:
        raise SurfSplatInputError(
            f"{at('k4')}: field 'k4' is {k4!r}: a perspective lens's r^8 term has no COLMAP camera model "
            "(k1, k2, k3, p1, p2 are read); undistort these photos first"
        )
    if k3 != 0:
        return Lens("FULL_OPENCV", cw, ch, (fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0))
    if (k1, k2, p1, p2) == (0.0, 0.0, 0.0, 0.0):
        return Lens("PINHOLE", cw, ch, (fx, fy, cx, cy))
    return Lens("OPENCV", cw, ch, (fx, fy, cx, cy, k1, k2, p1, p2))


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
    frames: list[dict[str, Any]]  # the JSON frame entries with a photo, in file order
    lenses: list[Lens] | None = None  # each view's lens (None: all pinhole), undistorted to `cameras` at load
    sizes: list[tuple[int, int]] | None = None  # (width, height) of each view once read (after undistortion)


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
    keep = present_views(paths, str(json_path))  # frames whose photo the publisher left out are dropped
    frames = [frames[i] for i in keep]
    paths = [paths[i] for i in keep]
    c2w_gl_t = c2w_gl_t[keep]

    sizes = image_sizes(paths)
    # OpenGL -> OpenCV flips the camera's y and z axes (the same matrix as Cameras.from_opengl,
    # applied here so that validation errors name the JSON file).
    c2w_cv = c2w_gl_t @ torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
    views = []
    for j, (i, frame, path, size) in enumerate(zip(keep, frames, paths, sizes)):
        entry = {**meta, **frame}  # per-frame intrinsics override the shared ones
        # the file's camera is of the STORED pixels: nerfstudio and instant-ngp copy COLMAP's camera
        # (w, h and the intrinsics of the image COLMAP read, which ignores the EXIF tag)
        orientation = image_orientation(path)
        stored = stored_size(orientation, *size)
        where = f"{json_path}: frame {i}"
        lens = frame_lens(entry, stored, where, frame.keys(), str(json_path))
        views.append(
            lens_view(lens, size, str(path), downscale_from_folder(path.parent), where, orientation, c2w_cv[j])
        )
    Ks, lenses, view_sizes = view_lenses(views)
    c2w_cv = torch.stack([view[3] for view in views])
    cameras = make_cameras(c2w_cv, Ks, str(json_path), dtype)
    return TransformsCameras(json_path, paths, cameras, frames, lenses, view_sizes)


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
        return camera_set(parsed.cameras, parsed.paths, parsed.sizes, names, lenses=parsed.lenses)
    rgb, alpha = load_image_stack(parsed.paths, background=background)
    rgb, alpha = undistort_views(rgb, alpha, parsed.lenses, parsed.paths)
    return PosedImages(
        images=rgb,
        cameras=parsed.cameras,
        names=[p.name for p in parsed.paths],
        masks=alpha,
        source=str(parsed.json_path),
        extras={} if parsed.lenses is None else {"lenses": parsed.lenses},  # each view's lens before undistortion
    )
