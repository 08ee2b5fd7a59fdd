"""A processed capture given as `images`: one folder holding photos and the camera file another tool made
(a nerfstudio / instant-ngp `transforms.json`, or a COLMAP model in `sparse/0`, `sparse` or the folder itself).

    scene = reconstruct("capture/")                 # its transforms.json or sparse/0: its photos, its cameras
    scene = reconstruct("capture/", cameras=None)   # the same photos, cameras estimated from them

What wins, decided here before anything heavy runs:
- `cameras="auto"` (reconstruct's default): a folder that `load_scene`'s detection reads as a transforms.json
  or COLMAP capture is a processed capture: its views are the photos its camera file lists, where the file
  points (a transforms.json's `file_path`s relative to it; COLMAP's `images/` beside `sparse/`), and its
  cameras are used. An info line says so. Any other folder (plain photos, or a layout such as LLFF's whose
  photos are not at the top) keeps its meaning: photos whose cameras are estimated.
- `cameras=None`: the cameras are estimated; a processed capture's views are still the photos it lists.
- a camera file, folder, CameraSet or Cameras: those cameras; the views as above.

Only the photo list is made here (from the camera file's names, no pixel or header read); the cameras are the
readers' (`surfsplat.data.cameras.load_cameras`), and where they leave a listed frame out (its photo missing),
so does the photo list.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

from ..utils.checks import SurfSplatInputError, read_json

logger = logging.getLogger(__name__)

AUTO = "auto"  # reconstruct's default `cameras`: a processed capture's own, else estimated


@dataclass(frozen=True)
class ProcessedCapture:
    """A folder of photos and the camera file that lists them."""

    root: Path  # the folder given
    kind: str  # "transforms.json" or "COLMAP model"
    camera_file: Path  # the transforms.json, or the COLMAP model folder
    photos: list[Path]  # every photo the camera file lists, in its order (present or not)


def find_processed_capture(folder: str | os.PathLike, images_folder: str | None = None) -> ProcessedCapture | None:
    """The processed capture of `folder` (see the module docstring), or None when it is not one.
    `images_folder` substitutes a downscaled photo folder (nerfstudio's images_4), as the readers do."""
    from ..data.formats.blender import _resolve_image, find_transforms
    from ..data.formats.colmap import find_model, read_images_binary, read_images_text
    from ..data.load import DETECTORS

    root = Path(folder)
    if not root.is_dir():
        return None
    kind = next((name for name, detect in DETECTORS.items() if detect(root)), None)
    if kind == "blender":
        json_path = find_transforms(root, "train")
        meta = read_json(json_path)
        frames = meta.get("frames") if isinstance(meta, dict) else None
        if not isinstance(frames, list) or not frames:
            raise SurfSplatInputError(f"{json_path}: field 'frames' must be a non-empty list of frames")
        photos = []
        for i, frame in enumerate(frames):
            if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
                raise SurfSplatInputError(f"{json_path}: frame {i}: missing key 'file_path' (a string)")
            photos.append(_resolve_image(json_path.parent, frame["file_path"], images_folder))
        return ProcessedCapture(root, "transforms.json", json_path, photos)
    if kind == "colmap":
        model = find_model(root)
        ext = "bin" if (model / "cameras.bin").is_file() else "txt"
        listing = model / f"images.{ext}"
        if not listing.is_file():
            raise FileNotFoundError(f"{listing}: COLMAP images file not found")
        records = (read_images_binary if ext == "bin" else read_images_text)(listing)
        names = sorted(r.name for r in records.values())  # the reader's order
        beside = root / (images_folder or "images")
        photos_dir = beside if beside.is_dir() or model != root else root  # a bare model: photos beside it
        return ProcessedCapture(root, "COLMAP model", model, [photos_dir / n for n in names])
    return None


def capture_views(images, cameras, images_folder: str | None):
    """(images, cameras, cameras' source or None) as reconstruct reads them: a processed capture given
    as `images` becomes the list of its photos, and with `cameras="auto"` (or its own camera file) its
    cameras as a CameraSet; "auto" for anything else means None (estimated)."""
    from ..data.cameras import load_cameras

    capture = None
    if isinstance(images, (str, os.PathLike)) and Path(images).is_dir():
        capture = find_processed_capture(images, images_folder)
    if capture is None:
        return images, (None if _is_auto(cameras) else cameras), None
    own = _is_auto(cameras) or (
        isinstance(cameras, (str, os.PathLike))
        and Path(cameras).resolve() in {capture.root.resolve(), capture.camera_file.resolve()}
    )
    if own:
        found = load_cameras(capture.root, images=images_folder)
        keys = {k for n in found.names for k in (n, Path(n).name, Path(n).stem)}
        photos = [p for p in capture.photos if p.name in keys or p.stem in keys]
        logger.info(
            f"{capture.root}: a processed capture ({capture.kind}): its {len(photos)} listed photos and their "
            "cameras are used (cameras=None estimates the cameras instead)"
        )
        return photos, found, f"{capture.camera_file} ({capture.kind} of the capture folder)"
    photos = [p for p in capture.photos if p.is_file()]
    missing = [p for p in capture.photos if not p.is_file()]
    if missing:
        shown = ", ".join(p.name for p in missing[:3]) + (", ..." if len(missing) > 3 else "")
        logger.warning(
            f"{len(missing)} of {len(capture.photos)} photos listed in {capture.camera_file} are missing ({shown}); "
            "they are left out"
        )
    what = "estimated" if cameras is None else "given"
    logger.info(
        f"{capture.root}: a processed capture ({capture.kind}): its {len(photos)} listed photos, cameras {what}"
    )
    return photos, cameras, None


def _is_auto(cameras) -> bool:
    return isinstance(cameras, str) and cameras == AUTO
