"""A capture through a lens, written as the tools people process captures with write it.

    views = [PinholeView(name, image, pinhole, c2w, source), ...]   # photos with known pinhole cameras
    write_lens_capture(folder, views, lens, points=xyz, colmap_text=True, instant_ngp=True)

Pinhole photos with known cameras (a DTU scan's) are resampled to what a camera with `lens` (any COLMAP
model, `surfsplat.geometry.lens.Lens`) would have taken from the same poses, by
`surfsplat.data.undistort.distort` (bicubic by default), and written beside the camera files a user
arrives with, so that a reader's undistortion can be checked against the photos it started from:
- `images/NAME`: the photos through the lens, 8-bit RGB PNGs (Pillow, `optimize=False`: the same bytes
  on every run);
- `sparse/0/`: a COLMAP model written by pycolmap (`Reconstruction.write`, binary: cameras, images,
  points3D, rigs, frames; COLMAP >= 3.12's layout, a trivial rig and frame per image), one camera
  (`lens`, camera id 1), the views' poses, and the 3D points given (each observed in the views where
  the lens projects it inside the photo), or none; `sparse/text/` the same model by `write_text`;
- `transforms.json`: nerfstudio's dialect (`camera_model` OPENCV or OPENCV_FISHEYE, fl_x, fl_y, cx, cy,
  w, h and the coefficients at the top level; frames' `transform_matrix` camera-to-world with OpenGL axes);
- `instant_ngp/transforms.json`: instant-ngp's (no camera_model; k1, k2, p1, p2 at the top level; w and h
  floats; fl_x without fl_y; camera_angle_x; paths relative to its folder), for an OPENCV lens;
- `truth.json`: the lens, the resampling, and per view the source photo, its pinhole and camera-to-world
  (OpenCV axes).
Used by `tests/data/make_distorted.py` (the repository's fixture `tests/data/distorted/`) and
`benchmarks/undistort.py` (DTU scan 24 at 400x300, end to end).

The file layouts are pycolmap's own writer and the two tools' JSON keys (nerfstudio's
`nerfstudio/data/dataparsers/nerfstudio_dataparser.py`, instant-ngp's `scripts/colmap2nerf.py`), written
with `json`; nothing here parses them (the readers under `surfsplat.data.formats` do).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from ..data.undistort import distort
from ..geometry.lens import Lens, project

NERFSTUDIO_MODELS = {"OPENCV": ("k1", "k2", "p1", "p2"), "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4")}


@dataclass(frozen=True)
class PinholeView:
    """One photo of a pinhole camera: what a lens's view of the same pose is made from."""

    name: str  # its file name under images/ in the capture written
    image: Tensor  # [3, H, W] in [0, 1]
    pinhole: Lens  # its calibration (PINHOLE, at the image's size)
    c2w: np.ndarray  # [4, 4] camera-to-world, OpenCV axes
    source: str  # where the photo came from (recorded in truth.json)


def save_png(image: Tensor, path: Path) -> None:
    """[3, H, W] in [0, 1] as an 8-bit RGB PNG (rounded to the nearest level)."""
    array = (image.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
    Image.fromarray(array).save(path, optimize=False)


def opengl_c2w(c2w: np.ndarray) -> list[list[float]]:
    """OpenCV camera axes (x right, y down, z forward) -> OpenGL's (x right, y up, z back), as JSON rows."""
    out = c2w.copy()
    out[:3, 1:3] *= -1
    return [[round(float(v), 12) for v in row] for row in out]


def lens_photo(view: PinholeView, lens: Lens, mode: str = "bicubic") -> Tensor:
    """The photo `lens` takes from `view`'s pose: [3, h, w] at the lens's size (0 where it sees beyond
    the pinhole photo)."""
    return distort(view.image.to(torch.float32), view.pinhole, lens, mode)


def blank_pixels(view: PinholeView, lens: Lens) -> int:
    """How many pixels of `lens`'s photo see beyond `view`'s pinhole photo (and are blank)."""
    cover = distort(torch.ones(1, view.pinhole.height, view.pinhole.width), view.pinhole, lens)
    return int((cover != 1).sum())


def write_photos(folder: Path, views: list[PinholeView], lens: Lens, mode: str, full_cover: bool) -> list[dict]:
    """Each view's photo as `lens` sees it in folder/images; the views' truth entries. With `full_cover`
    a lens that sees beyond a pinhole photo is an error (the fixture's lenses are chosen so it does not)."""
    (folder / "images").mkdir(parents=True)
    truth = []
    for view in views:
        if full_cover and blank_pixels(view, lens):
            raise ValueError(f"{view.source}: the lens sees beyond the pinhole photo")
        save_png(lens_photo(view, lens, mode), folder / "images" / view.name)
        truth.append(
            {
                "image": f"images/{view.name}",
                "source": view.source,
                "pinhole": view.pinhole.to_dict(),
                "c2w": [[float(v) for v in row] for row in view.c2w],
            }
        )
    return truth


def write_colmap(
    model_dir: Path, views: list[PinholeView], lens: Lens, points: np.ndarray | None, text_dir: Path | None
) -> None:
    """The capture as a COLMAP model by pycolmap: one camera (`lens`), the views' poses, and `points`
    ([P, 3] world, or None for a model without 3D points), each observed where `lens` projects it inside
    the photo (those pixels are the images' keypoints)."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(model=lens.model, width=lens.width, height=lens.height, params=list(lens.params), camera_id=1)
    )
    xyz = np.zeros((0, 3)) if points is None else points
    observations: dict[int, list[tuple[int, int]]] = {}
    for image_id, view in enumerate(views, start=1):
        w2c = np.linalg.inv(view.c2w)
        cam = xyz @ w2c[:3, :3].T + w2c[:3, 3]
        px = project(lens, torch.from_numpy(cam)).numpy()
        w, h = lens.width, lens.height
        seen = np.isfinite(px).all(1) & (px[:, 0] > 0) & (px[:, 0] < w) & (px[:, 1] > 0) & (px[:, 1] < h)
        image = pycolmap.Image(name=view.name, keypoints=px[seen], camera_id=1, image_id=image_id)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c[:3, :4]))
        for idx, point in enumerate(np.nonzero(seen)[0]):
            observations.setdefault(int(point), []).append((image_id, idx))
    for point in sorted(observations):
        track = pycolmap.Track()
        for image_id, idx in observations[point]:
            track.add_element(image_id, idx)
        rec.add_point3D(xyz[point], track, np.array([128, 128, 128], dtype=np.uint8))
    model_dir.mkdir(parents=True)
    rec.write(str(model_dir))
    if text_dir is not None:
        text_dir.mkdir(parents=True)
        rec.write_text(str(text_dir))


def nerfstudio_transforms(lens: Lens, views: list[PinholeView], prefix: str = "") -> dict:
    """nerfstudio's transforms.json for `lens` (OPENCV or OPENCV_FISHEYE), frames at prefix + images/NAME."""
    if lens.model not in NERFSTUDIO_MODELS:
        raise ValueError(f"nerfstudio's transforms.json has no camera_model {lens.model}")
    fx, fy, cx, cy = lens.focal_and_centre
    return {
        "camera_model": lens.model,
        **{"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": lens.width, "h": lens.height},
        **dict(zip(NERFSTUDIO_MODELS[lens.model], lens.extra_params)),
        "frames": [{"file_path": f"{prefix}images/{v.name}", "transform_matrix": opengl_c2w(v.c2w)} for v in views],
    }


def instant_ngp_transforms(lens: Lens, views: list[PinholeView], prefix: str = "../") -> dict:
    """instant-ngp's transforms.json (colmap2nerf's keys) for an OPENCV lens whose fy is its fx."""
    if lens.model != "OPENCV":
        raise ValueError(f"instant-ngp's implicit lens is OPENCV, not {lens.model}")
    fx, _, cx, cy = lens.focal_and_centre
    k1, k2, p1, p2 = lens.extra_params
    return {
        "camera_angle_x": 2 * math.atan(lens.width / (2 * fx)),
        **{"fl_x": fx, "k1": k1, "k2": k2, "p1": p1, "p2": p2, "cx": cx, "cy": cy},
        **{"w": float(lens.width), "h": float(lens.height), "aabb_scale": 4},
        "frames": [
            {"file_path": f"{prefix}images/{v.name}", "transform_matrix": opengl_c2w(v.c2w), "sharpness": 100.0}
            for v in views
        ],
    }


def write_json(path: Path, document: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(document, indent=2) + "\n")


def write_lens_capture(
    folder: Path,
    views: list[PinholeView],
    lens: Lens,
    *,
    mode: str = "bicubic",
    colmap: bool = True,
    colmap_text: bool = False,
    points: np.ndarray | None = None,
    nerfstudio: bool = True,
    instant_ngp: bool = False,
    full_cover: bool = True,
) -> None:
    """Write the capture `lens` takes of `views` into `folder` (which must not exist): the photos, the
    camera files asked for, and truth.json (see the module doc)."""
    if folder.exists():
        raise FileExistsError(f"{folder}: exists; the capture is written into a new folder")
    truth_views = write_photos(folder, views, lens, mode, full_cover)
    if colmap:
        write_colmap(folder / "sparse" / "0", views, lens, points, folder / "sparse" / "text" if colmap_text else None)
    if nerfstudio:
        write_json(folder / "transforms.json", nerfstudio_transforms(lens, views))
    if instant_ngp:
        write_json(folder / "instant_ngp" / "transforms.json", instant_ngp_transforms(lens, views))
    resampling = f"surfsplat.data.undistort.distort, {mode}"
    write_json(folder / "truth.json", {"lens": lens.to_dict(), "resampling": resampling, "views": truth_views})
