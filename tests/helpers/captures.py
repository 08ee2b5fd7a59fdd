"""Processed captures as other tools write them, made from the fern fixture's photos and cameras: a
nerfstudio `transforms.json` (OpenGL camera-to-world, pixel intrinsics) or a COLMAP binary model in
`sparse/0` with the photos in `images/`; and zips of them, as a person would send them to the app."""

from __future__ import annotations

import json
import shutil
import zipfile
from pathlib import Path

import torch

from surfsplat.data.cameras import CameraSet
from surfsplat.data.load import load_scene_cameras

from .data import write_colmap_model

FERN = Path(__file__).resolve().parents[1] / "data" / "llff_fern"


def fern_cameras(views: int) -> CameraSet:
    """The first `views` fern cameras for its 252x189 photos (OpenCV c2w, K in pixels)."""
    cams = load_scene_cameras(FERN, images="images_16")
    return cams.select(cams.names[:views], "fern")


def write_capture(folder: Path, kind: str, views: int = 2) -> CameraSet:
    """A capture of the first `views` fern photos in `folder`: kind "transforms" (transforms.json beside
    images/) or "colmap" (sparse/0 beside images/). Returns the cameras written."""
    cams = fern_cameras(views)
    (folder / "images").mkdir(parents=True)
    for name in cams.names:
        shutil.copyfile(FERN / "images_16" / name, folder / "images" / name)
    if kind == "transforms":
        K = cams.cameras.K[0]
        c2w_gl = cams.cameras.c2w @ torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
        document = {
            "camera_model": "PINHOLE",
            "fl_x": float(K[0, 0]),
            "fl_y": float(K[1, 1]),
            "cx": float(K[0, 2]),
            "cy": float(K[1, 2]),
            "w": cams.width,
            "h": cams.height,
            "frames": [
                {"file_path": f"images/{n}", "transform_matrix": m.tolist()} for n, m in zip(cams.names, c2w_gl)
            ],
        }
        (folder / "transforms.json").write_text(json.dumps(document, indent=1))
    elif kind == "colmap":
        write_colmap_model(folder / "sparse" / "0", cams.cameras, cams.names, cams.width, cams.height, binary=True)
    else:
        raise ValueError(kind)
    return cams


def zip_folder(folder: Path, archive: Path, top: str | None = None) -> Path:
    """`archive` holding every file of `folder`, under the folder `top` when given (as zip tools write a
    zipped folder)."""
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                name = path.relative_to(folder).as_posix()
                zf.write(path, f"{top}/{name}" if top else name)
    return archive
