"""Camera files: `CameraSet` (cameras with the image size their K is in pixels of), `load_cameras`
for a JSON camera file, a bare COLMAP model or any scene folder `load_scene` reads (from the
format's camera records and image headers: no pixel is decoded), and `save_cameras`.

    cams = load_cameras("cameras.json")          # or a COLMAP model folder, or a scene folder
    save_cameras("cameras.json", cams.cameras, cams.width, cams.height, cams.names)
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
from ..geometry.rotations import quat_to_matrix
from ..utils.checks import SurfSplatInputError, read_json

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
        )

    def resized(self, width: int, height: int, source: str) -> Cameras:
        """K for images of width x height: a uniform rescale of the calibrated size (K' = diag(sx, sy, 1) K)."""
        if (width, height) == (self.width, self.height):
            return self.cameras
        sx, sy = width / self.width, height / self.height
        if abs(self.height * sx - height) > 0.5 + 1e-9:
            raise SurfSplatInputError(
                f"{source}: images are {width}x{height} but the cameras are for {self.width}x{self.height} "
                "(only a uniform rescale of the calibrated size is accepted)"
            )
        S = torch.tensor([sx, sy, 1.0], dtype=self.cameras.K.dtype)
        return Cameras(self.cameras.c2w, self.cameras.K * S[:, None], validate=False)


def save_cameras(
    path: str | os.PathLike,
    cameras: Cameras,
    width: int,
    height: int,
    names: list[str] | None = None,
    near: float | None = None,
    far: float | None = None,
    *,
    lenses: list[tuple[Lens, Lens]] | None = None,
) -> Path:
    """Write cameras as JSON (the format `load_cameras` reads): OpenCV c2w, K in pixels of width x height.

    lenses: each view's (source lens, pinhole it was undistorted to), recorded per frame as "lens" and
        "pinhole" (`Lens.to_dict`), so that renders can be compared with the original photos.
    """
    from ..utils.atomic import write_text

    names = names or [f"view_{i:03d}" for i in range(len(cameras))]
    if len(names) != len(cameras):
        raise SurfSplatInputError(f"names: expected {len(cameras)} names, got {len(names)}")
    if lenses is not None and len(lenses) != len(cameras):
        raise SurfSplatInputError(f"lenses: expected {len(cameras)} (lens, pinhole) pairs, got {len(lenses)}")
    document: dict[str, object] = {
        "format": CAMERA_FILE_FORMAT,
        "convention": "opencv",
        "width": int(width),
        "height": int(height),
        "frames": [
            {"name": n, "K": k.tolist(), "c2w": c.tolist()}
            for n, k, c in zip(names, cameras.K.to(torch.float64), cameras.c2w.to(torch.float64))
        ],
    }
    if lenses is not None:
        for frame, (lens, pinhole) in zip(document["frames"], lenses):
            frame["lens"], frame["pinhole"] = lens.to_dict(), pinhole.to_dict()
    if near is not None and far is not None:
        document["near"], document["far"] = float(near), float(far)
    return write_text(path, json.dumps(document, indent=1) + "\n")


def load_cameras(path: str | os.PathLike, images: str | None = None) -> CameraSet:
    """Cameras from a JSON camera file, a COLMAP model folder, or any scene folder `load_scene` reads.

    JSON: {"width": W, "height": H, "convention": "opencv" | "opengl", "near": n, "far": f,
    "frames": [{"name": "a.png", "K": 3x3 pixels, "c2w": 4x4 or 3x4}, ...]} (near/far optional).
    `images` picks the image folder of a scene folder (e.g. images_4 for DTU).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: camera file or scene folder not found")
    if path.is_file():
        if path.suffix.lower() != ".json":
            raise SurfSplatInputError(f"{path}: expected a .json camera file, a COLMAP model folder or a scene folder")
        return _load_camera_json(path)
    from .formats.colmap import find_model

    model = find_model(path)
    if model is not None and model == path and not (path / "images").is_dir():
        return _load_colmap_model(path)
    from .load import load_scene_cameras

    return load_scene_cameras(path, images=images)


def _load_camera_json(path: Path) -> CameraSet:
    data = read_json(path)
    if not isinstance(data, dict):
        raise SurfSplatInputError(f"{path}: expected a JSON object with 'width', 'height' and 'frames'")
    for key in ("width", "height"):
        if not isinstance(data.get(key), int) or isinstance(data.get(key), bool) or data[key] < 1:
            raise SurfSplatInputError(f"{path}: field '{key}' must be a positive integer, got {data.get(key)!r}")
    convention = data.get("convention", "opencv")
    if convention not in ("opencv", "opengl"):
        raise SurfSplatInputError(f"{path}: field 'convention' must be 'opencv' or 'opengl', got {convention!r}")
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise SurfSplatInputError(f"{path}: field 'frames' must be a non-empty list")
    Ks, c2ws, names = [], [], []
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
    return CameraSet(cameras, data["width"], data["height"], names, near, far)


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


def _load_colmap_model(model_dir: Path) -> CameraSet:
    """Cameras of a bare COLMAP model folder (cameras/images .bin or .txt, no image folder)."""
    from ..geometry.cameras import rigid_inverse
    from .formats.colmap import pinhole_matrix, read_model

    cameras, records, _ = read_model(model_dir)
    if not records:
        raise SurfSplatInputError(f"{model_dir}: the model has no registered images")
    ordered = sorted(records.values(), key=lambda r: r.name)
    sizes = set()
    Ks, w2c = [], torch.eye(4, dtype=torch.float64).repeat(len(ordered), 1, 1)
    for i, r in enumerate(ordered):
        if r.camera_id not in cameras:
            raise SurfSplatInputError(f"{model_dir}: image '{r.name}' refers to missing camera {r.camera_id}")
        cam = cameras[r.camera_id]
        sizes.add((cam.width, cam.height))
        Ks.append(pinhole_matrix(cam, f"{model_dir}/cameras: camera {r.camera_id}").to(torch.float64))
        w2c[i, :3, :3] = quat_to_matrix(torch.tensor(r.qvec, dtype=torch.float64))
        w2c[i, :3, 3] = torch.tensor(r.tvec, dtype=torch.float64)
    if len(sizes) != 1:
        raise SurfSplatInputError(
            f"{model_dir}: cameras of different image sizes {sorted(sizes)}; give a JSON camera file instead"
        )
    ((width, height),) = sizes
    return CameraSet(Cameras(rigid_inverse(w2c), torch.stack(Ks)), width, height, [r.name for r in ordered])
