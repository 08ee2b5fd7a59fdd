"""Camera files: `CameraSet` (cameras with the image size their K is in pixels of), `load_cameras`
for any camera file or folder, recognised by its content (from the format's camera records and image
headers: no pixel is decoded), and `save_cameras`.

    cams = load_cameras("cameras.json")          # this package's camera file
    cams = load_cameras("capture/transforms.json")  # nerfstudio / instant-ngp / Blender
    cams = load_cameras("capture/sparse/0")      # a COLMAP model (or its cameras.bin / images.txt ...)
    cams = load_cameras("capture/")              # any scene folder load_scene reads
    save_cameras("cameras.json", cams.cameras, cams.width, cams.height, cams.names)

What a given path is read as:
- a JSON file whose `frames` entries have `transform_matrix`: a transforms.json (its folder is the
  photos' root);
- a JSON file with `format: surfsplat-cameras`, or `width`, `height` and `frames` with `K` and `c2w`:
  this package's camera file;
- `cameras.{bin,txt}`, `images.{bin,txt}` or `points3D.{bin,txt}`: the COLMAP model of its folder;
- a folder: a COLMAP model folder (or a capture with `sparse/0` and no photos beside it), or any
  scene folder `load_scene` reads.
Anything else is one error saying what was found and what is accepted.

The camera file this package writes records, beside K and c2w, the working crop its K is in pixels
of (`crop`: the photos' size and what `rescale_and_crop` did to them) and, for a capture with a lens,
each view's source lens and the pinhole its photos were undistorted to (`lens`, `pinhole`); read
back, `CameraSet.resized` takes the cameras back to the source photos' size, and `lenses` says how
to undistort them.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.lens import Lens
from ..utils.checks import SurfSplatInputError, read_json
from .transforms import WorkingCrop

# ----------------------------------------------------------------------------------------- camera files
CAMERA_FILE_FORMAT = "surfsplat-cameras"


@dataclass
class CameraSet:
    """Cameras read from a file, with the image size their K is in pixels of."""

    cameras: Cameras
    width: int
    height: int
    names: list[str]
    near: float | None = None  # smallest near bound of the views, where the source gives one
    far: float | None = None  # largest far bound
    # the lens of each view as the source states it (None: the views are pinhole, K says it all);
    # a reader undistorts such views to the pinhole K before any stage after it sees a pixel
    lenses: list[Lens] | None = None
    # the working crop K is in pixels of (a camera file written by reconstruct): `resized` to the
    # crop's source size undoes it (None: K is in pixels of the photos themselves)
    crop: WorkingCrop | None = None
    # K, c2w and lenses describe the photos' STORED pixels (EXIF orientation not applied): a COLMAP model
    # read without its photos. Where such cameras meet photos an orientation turns (3, 6, 8), each view's
    # camera is turned with its photo (`surfsplat.reconstruction.sizes.view_cameras`); False: the cameras
    # are of the photos as read (a reader that saw the photos turned them already, or this package's file)
    stored_pixels: bool = False

    def select(self, wanted: list[str], source: str) -> CameraSet:
        """The cameras of the named images, in that order (matched by file name or stem)."""
        by_name: dict[str, int] = {}
        for i, name in enumerate(self.names):
            for key in (name, Path(name).name, Path(name).stem):
                by_name.setdefault(key, i)
        picked = []
        for name in wanted:
            for key in (name, Path(name).name, Path(name).stem):
                if key in by_name:
                    picked.append(by_name[key])
                    break
            else:
                shown = ", ".join(self.names[:8]) + (", ..." if len(self.names) > 8 else "")
                raise SurfSplatInputError(f"{source}: no camera for image {name!r} (cameras exist for: {shown})")
        return CameraSet(
            self.cameras[torch.tensor(picked)],
            self.width,
            self.height,
            [self.names[i] for i in picked],
            self.near,
            self.far,
            None if self.lenses is None else [self.lenses[i] for i in picked],
            self.crop,
            self.stored_pixels,
        )

    def fits(self, width: int, height: int) -> bool:
        """Whether `resized` takes photos of width x height: a uniform rescale of the calibrated size or,
        for cameras of a working crop, of the photos it was cut from."""
        crop = self.crop
        return is_uniform_rescale((self.width, self.height), (width, height)) or (
            crop is not None and is_uniform_rescale((crop.source_width, crop.source_height), (width, height))
        )

    def resized(self, width: int, height: int, source: str) -> Cameras:
        """K for images of width x height: the calibrated size, a uniform rescale of it (K' = diag(sx, sy, 1) K),
        or, for cameras of a working crop, the crop's source photos (the crop undone) or a uniform rescale of them."""
        if (width, height) == (self.width, self.height):
            return self.cameras
        cameras, cw, ch = self.cameras, self.width, self.height
        crop = self.crop
        if crop is not None and is_uniform_rescale((crop.source_width, crop.source_height), (width, height)):
            cameras = Cameras(cameras.c2w, crop.uncrop(cameras.K), validate=False)
            cw, ch = crop.source_width, crop.source_height
            if (width, height) == (cw, ch):
                return cameras
        if not is_uniform_rescale((cw, ch), (width, height)):
            also = f" or the {crop.source_width}x{crop.source_height} photos they were cropped from" if crop else ""
            raise SurfSplatInputError(
                f"{source}: images are {width}x{height} but the cameras are for {self.width}x{self.height}{also} "
                "(only a uniform rescale of the calibrated size is accepted)"
            )
        S = torch.tensor([width / cw, height / ch, 1.0], dtype=cameras.K.dtype)
        return Cameras(cameras.c2w, cameras.K * S[:, None], validate=False)


def pinhole_of(lens: Lens, source: str | None = None) -> Lens:
    """The pinhole a lens's photos are undistorted to: the lens itself where it is one (as PINHOLE), else
    `undistorted_pinhole` (COLMAP image_undistorter's choice). For a lens of turned photos
    (`Lens.orientation` 3, 6 or 8) it is the pinhole of the stored pixels turned for display
    (`turned_pinhole`): the photo's pinhole as it is read. `source` (the camera file and record) starts
    the error line of a lens with no valid region."""
    stored = lens.stored()
    if stored.is_pinhole:
        from .formats.common import pinhole_lens

        pinhole = pinhole_lens(stored.intrinsics(), stored.width, stored.height)
    else:
        from ..geometry.lens import undistorted_pinhole

        try:
            pinhole = undistorted_pinhole(stored)
        except SurfSplatInputError as err:
            if source is None:
                raise
            raise SurfSplatInputError(f"{source}: {err}") from None
    return pinhole if lens.orientation == 1 else turned_pinhole(pinhole, lens.orientation)


def turned_pinhole(pinhole: Lens, orientation: int) -> Lens:
    """A pinhole of stored pixels as the photo displayed with this EXIF orientation sees it
    (`surfsplat.geometry.orientation.displayed_camera`: exact for the turns 1, 3, 6, 8)."""
    from ..geometry.orientation import displayed_camera
    from .formats.common import pinhole_lens

    K, _, (width, height) = displayed_camera(
        pinhole.intrinsics(), torch.eye(4, dtype=torch.float64), pinhole.width, pinhole.height, orientation
    )
    return pinhole_lens(K, width, height)


def is_uniform_rescale(calibrated: tuple[int, int], size: tuple[int, int]) -> bool:
    """Whether size (width, height) is the calibrated (width, height) rescaled uniformly (the height within
    the half pixel of rounding)."""
    (cw, ch), (width, height) = calibrated, size
    return abs(ch * width / cw - height) <= 0.5 + 1e-9


def save_cameras(
    path: str | os.PathLike,
    cameras: Cameras,
    width: int,
    height: int,
    names: list[str] | None = None,
    near: float | None = None,
    far: float | None = None,
    *,
    crop: WorkingCrop | None = None,
    lenses: list[Lens] | None = None,
) -> Path:
    """Write cameras as JSON (the format `load_cameras` reads): OpenCV c2w, K in pixels of width x height.

    crop: the working crop of the photos K is in pixels of (`surfsplat.data.transforms.working_crop`),
        recorded so that the file is accepted back with those photos.
    lenses: each view's source lens (`CameraSet.lenses`), recorded with the pinhole its photo was
        undistorted to (`undistorted_pinhole`), so that renders can be compared with the original photos
        and the file is read back with them.
    """
    from ..utils.atomic import write_text

    names = names or [f"view_{i:03d}" for i in range(len(cameras))]
    if len(names) != len(cameras):
        raise SurfSplatInputError(f"names: expected {len(cameras)} names, got {len(names)}")
    if lenses is not None and len(lenses) != len(cameras):
        raise SurfSplatInputError(f"lenses: expected {len(cameras)} lenses (one a view), got {len(lenses)}")
    if crop is not None and (crop.width, crop.height) != (int(width), int(height)):
        raise SurfSplatInputError(f"crop: a crop of {crop.width}x{crop.height} for cameras of {width}x{height}")
    frames = []
    for i, (n, k, c) in enumerate(zip(names, cameras.K.to(torch.float64), cameras.c2w.to(torch.float64))):
        frame: dict[str, object] = {"name": n, "K": k.tolist(), "c2w": c.tolist()}
        if lenses is not None:
            frame["lens"], frame["pinhole"] = lenses[i].to_dict(), pinhole_of(lenses[i]).to_dict()
        frames.append(frame)
    document: dict[str, object] = {
        "format": CAMERA_FILE_FORMAT,
        "convention": "opencv",
        "width": int(width),
        "height": int(height),
        "frames": frames,
    }
    if crop is not None:
        document["crop"] = crop.to_dict()
    if near is not None and far is not None:
        document["near"], document["far"] = float(near), float(far)
    return write_text(path, json.dumps(document, indent=1) + "\n")


COLMAP_FILES = tuple(f"{stem}.{ext}" for stem in ("cameras", "images", "points3D") for ext in ("bin", "txt"))
ACCEPTED = (
    "a transforms.json (frames with transform_matrix), this package's camera file (format surfsplat-cameras: "
    "width, height, frames with K and c2w), a COLMAP model folder or its cameras/images .bin/.txt, or a scene folder"
)


def load_cameras(path: str | os.PathLike, images: str | None = None) -> CameraSet:
    """Cameras from a camera file or folder, recognised by its content (see the module doc).

    This package's JSON: {"format": "surfsplat-cameras", "width": W, "height": H, "convention": "opencv" |
    "opengl", "near": n, "far": f, "crop": {...}, "frames": [{"name": "a.png", "K": 3x3 pixels, "c2w": 4x4 or
    3x4, "lens": {...}, "pinhole": {...}}, ...]} (near/far, crop and lens optional).
    `images` picks the image folder of a scene folder (e.g. images_4 for DTU, images_2 for nerfstudio).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: camera file or scene folder not found")
    from .formats.colmap import find_model, model_cameras, model_root

    if path.is_file():
        if path.name in COLMAP_FILES:
            return model_cameras(path.parent)
        if path.suffix.lower() != ".json":
            raise SurfSplatInputError(f"{path}: a {path.suffix or 'suffix-less'} file; accepted: {ACCEPTED}")
        data = read_json(path)
        kind = _json_kind(data, path)
        if kind == "transforms":
            from .formats.blender import load_blender

            return load_blender(path, images=images, cameras_only=True, dtype=torch.float64)
        return _load_camera_json(path, data)
    model = find_model(path)
    if model is not None and not (model_root(model) / (images or "images")).is_dir():
        from .load import detect_format

        if detect_format(path) == "colmap":  # a model without photos beside it: its cameras alone
            return model_cameras(model)
    from .load import load_scene_cameras

    return load_scene_cameras(path, images=images)


def _json_kind(data: object, path: Path) -> str:
    """ "transforms" or "surfsplat" from a JSON camera file's content, or an error saying what it holds."""
    if not isinstance(data, dict):
        raise SurfSplatInputError(f"{path}: a JSON {type(data).__name__}, not an object; accepted: {ACCEPTED}")
    frames = data.get("frames")
    entries = [f for f in frames if isinstance(f, dict)] if isinstance(frames, list) else []
    if data.get("format") == CAMERA_FILE_FORMAT:
        return "surfsplat"
    if entries and all("transform_matrix" in f for f in entries):
        return "transforms"
    if entries and all("K" in f and "c2w" in f for f in entries) and ("width" in data or "height" in data):
        return "surfsplat"
    keys = ", ".join(sorted(map(str, data))[:12]) or "none"
    if isinstance(frames, list) and entries:
        held = ", ".join(sorted({str(k) for f in entries for k in f})[:12])
        found = f"'frames' whose entries hold {held} (no transform_matrix, nor K and c2w with a width and height)"
    elif "frames" in data:
        found = f"'frames' that is not a list of objects ({type(frames).__name__})"
    else:
        found = f"keys {keys} and no 'frames'"
    raise SurfSplatInputError(f"{path}: not a camera file this package reads: it has {found}; accepted: {ACCEPTED}")


def _load_camera_json(path: Path, data: dict) -> CameraSet:
    """This package's camera file (see load_cameras), `data` its parsed JSON object."""
    for key in ("width", "height"):
        if not isinstance(data.get(key), int) or isinstance(data.get(key), bool) or data[key] < 1:
            raise SurfSplatInputError(f"{path}: field '{key}' must be a positive integer, got {data.get(key)!r}")
    convention = data.get("convention", "opencv")
    if convention not in ("opencv", "opengl"):
        raise SurfSplatInputError(f"{path}: field 'convention' must be 'opencv' or 'opengl', got {convention!r}")
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise SurfSplatInputError(f"{path}: field 'frames' must be a non-empty list")
    Ks, c2ws, names, lenses = [], [], [], []
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise SurfSplatInputError(f"{path}: frames[{i}] must be an object with 'K' and 'c2w'")
        K = _matrix(frame.get("K"), (3, 3), f"{path}: frames[{i}].K")
        c2w = _matrix(frame.get("c2w"), None, f"{path}: frames[{i}].c2w")
        if c2w.shape == (3, 4):
            c2w = torch.cat([c2w, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)])
        if c2w.shape != (4, 4):
            raise SurfSplatInputError(f"{path}: frames[{i}].c2w must be 4x4 or 3x4, got {tuple(c2w.shape)}")
        Ks.append(K)
        c2ws.append(c2w)
        name = frame.get("name", f"view_{i:03d}")
        if not isinstance(name, str):
            raise SurfSplatInputError(f"{path}: frames[{i}].name must be a string, got {name!r}")
        names.append(name)
        if "lens" in frame:
            lenses.append(Lens.from_dict(frame["lens"], f"{path}: frames[{i}].lens"))
    if lenses and len(lenses) != len(frames):
        raise SurfSplatInputError(
            f"{path}: {len(lenses)} of {len(frames)} frames have a 'lens'; give every frame one or none"
        )
    crop = WorkingCrop.from_dict(data["crop"], f"{path}: crop") if "crop" in data else None
    if crop is not None and (crop.width, crop.height) != (data["width"], data["height"]):
        raise SurfSplatInputError(
            f"{path}: 'crop' is {crop.width}x{crop.height} but 'width' x 'height' is {data['width']}x{data['height']}"
        )
    c2w_t, K_t = torch.stack(c2ws), torch.stack(Ks)
    from ..geometry.cameras import validate_c2w, validate_intrinsics

    validate_c2w(f"{path}: frames[].c2w", c2w_t)
    validate_intrinsics(f"{path}: frames[].K", K_t)
    cameras = Cameras.from_opengl(c2w_t, K_t) if convention == "opengl" else Cameras(c2w_t, K_t)
    near, far = data.get("near"), data.get("far")
    if (near is None) != (far is None):
        raise SurfSplatInputError(f"{path}: give both 'near' and 'far' or neither")
    if near is not None:
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (near, far)) or not 0 < near < far:
            raise SurfSplatInputError(
                f"{path}: 'near' and 'far' must be numbers with 0 < near < far, got {near!r}, {far!r}"
            )
    return CameraSet(cameras, data["width"], data["height"], names, near, far, lenses or None, crop)


def _matrix(value: object, shape: tuple[int, int] | None, where: str) -> Tensor:
    try:
        t = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError):
        raise SurfSplatInputError(f"{where}: expected a matrix of numbers, got {value!r}") from None
    if t.ndim != 2 or (shape is not None and tuple(t.shape) != shape):
        raise SurfSplatInputError(f"{where}: expected shape {shape or '(rows, cols)'}, got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise SurfSplatInputError(f"{where}: contains NaN or inf")
    return t
