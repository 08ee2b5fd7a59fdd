"""COLMAP sparse models (text and binary) for custom captures.

Layout: `<root>/images/` and `<root>/sparse/0/{cameras,images,points3D}.{bin,txt}` (a model folder
can also be passed directly). Image poses are world-to-camera (R(q) X + t, q = (w, x, y, z)) with
OpenCV axes; COLMAP puts the centre of the top-left pixel at (0.5, 0.5), our convention, so K is
used as is. Every camera model COLMAP writes (ids 0-10, `surfsplat.geometry.lens.CAMERA_MODELS`)
becomes a `Lens`: PINHOLE and SIMPLE_PINHOLE cameras, and any model whose distortion parameters are
all zero, are read as their K; any other lens is undistorted at load to the pinhole COLMAP's
`image_undistorter` would choose (`undistorted_pinhole`), photos and masks alike, and the scene's K
and size are that pinhole's. A registered image whose photo file is missing is left out with one
warning (`common.present_views`).

The binary and text layouts are read here rather than through pycolmap's `Reconstruction.read`
so that a truncated or malformed file is reported as one line naming its path, line and field, and
so that a model's cameras and poses are read without its points (`load_cameras`); the tests check
this reader against models written by pycolmap (text and binary, every camera model).
Per-view near/far come from the depths of the view's own triangulated points (0.1 and 99.9
percentiles, as LLFF's imgs2poses does) when points3D is present and every view sees at least
one point in front of it (a view whose points all share one depth gets far = 1.01 near);
otherwise the scene has no near/far.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ...geometry.cameras import rigid_inverse
from ...geometry.lens import CAMERA_MODELS, MODEL_IDS, Lens
from ...geometry.rotations import quat_to_matrix
from ...utils.checks import SurfSplatInputError
from ..images import image_orientation
from ..posed_images import PosedImages, downscale_from_folder
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

SUPPORTED = ", ".join(f"{i} {name}" for i, (name, _) in CAMERA_MODELS.items())


@dataclass
class ColmapImage:
    qvec: list[float]  # (w, x, y, z), world-to-camera
    tvec: list[float]
    camera_id: int
    name: str
    point_ids: np.ndarray  # [P] int64, -1 where a 2D point has no 3D point


def find_model(path: Path) -> Path | None:
    """The folder holding cameras.{bin,txt}: the path itself, sparse/0, or sparse."""
    for folder in (path, path / "sparse" / "0", path / "sparse"):
        if folder.is_dir() and any((folder / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return folder
    return None


def is_colmap(path: Path) -> bool:
    return find_model(path) is not None


# ---------------------------------------------------------------------------------------- binary
class _Reader:
    """Little-endian reader that names the file and offset when the data runs out."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def read(self, fmt: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise SurfSplatInputError(
                f"{self.path}: truncated file (needed {size} bytes at offset {self.pos}, have {len(self.data) - self.pos})"
            )
        out = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return out

    def read_string(self) -> str:
        end = self.data.find(b"\x00", self.pos)
        if end < 0:
            raise SurfSplatInputError(f"{self.path}: truncated file (unterminated image name at offset {self.pos})")
        out = self.data[self.pos : end].decode("utf-8")
        self.pos = end + 1
        return out

    def read_array(self, dtype: np.dtype, count: int) -> np.ndarray:
        size = np.dtype(dtype).itemsize * count
        if self.pos + size > len(self.data):
            raise SurfSplatInputError(f"{self.path}: truncated file (needed {size} bytes at offset {self.pos})")
        out = np.frombuffer(self.data, dtype=dtype, count=count, offset=self.pos)
        self.pos += size
        return out


def _lens(model: str, width: int, height: int, params: list[float], where: str) -> Lens:
    """The Lens of one camera record, its errors prefixed with the file and camera."""
    try:
        return Lens(model, int(width), int(height), tuple(float(v) for v in params))
    except SurfSplatInputError as err:
        raise SurfSplatInputError(f"{where}: {err}") from None


def read_cameras_binary(path: Path) -> dict[int, Lens]:
    r = _Reader(path)
    (count,) = r.read("Q")
    cameras = {}
    for _ in range(count):
        camera_id, model_id, width, height = r.read("iiQQ")
        if model_id not in CAMERA_MODELS:
            raise SurfSplatInputError(
                f"{path}: camera {camera_id} has camera model id {model_id}, which is not supported (supported: {SUPPORTED})"
            )
        name, names = CAMERA_MODELS[model_id]
        params = list(r.read("d" * len(names)))
        cameras[camera_id] = _lens(name, width, height, params, f"{path}: camera {camera_id}")
    return cameras


def read_images_binary(path: Path) -> dict[int, ColmapImage]:
    r = _Reader(path)
    (count,) = r.read("Q")
    images = {}
    for _ in range(count):
        image_id, qw, qx, qy, qz, tx, ty, tz, camera_id = r.read("idddddddi")
        name = r.read_string()
        (num_points,) = r.read("Q")
        # Each 2D point: x, y (double) and its 3D point id (int64).
        pts = r.read_array(np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")]), num_points)
        images[image_id] = ColmapImage([qw, qx, qy, qz], [tx, ty, tz], camera_id, name, pts["id"].astype(np.int64))
    return images


def read_points_binary(path: Path) -> dict[int, np.ndarray]:
    r = _Reader(path)
    (count,) = r.read("Q")
    points = {}
    for _ in range(count):
        point_id, x, y, z, _, _, _, _ = r.read("QdddBBBd")
        (track_length,) = r.read("Q")
        r.read_array(np.dtype("<i4"), 2 * track_length)
        points[point_id] = np.array([x, y, z])
    return points


# ------------------------------------------------------------------------------------------ text
def _data_lines(path: Path) -> list[tuple[int, str]]:
    return [(i + 1, line.strip()) for i, line in enumerate(path.read_text().splitlines()) if not line.startswith("#")]


def _parse(tokens: list[str], types: list[type], path: Path, line_no: int) -> list:
    if len(tokens) < len(types):
        raise SurfSplatInputError(f"{path}:{line_no}: expected at least {len(types)} fields, got {len(tokens)}")
    try:
        return [t(tok) for t, tok in zip(types, tokens)]
    except ValueError as err:
        raise SurfSplatInputError(f"{path}:{line_no}: {err}") from None


def read_cameras_text(path: Path) -> dict[int, Lens]:
    cameras = {}
    for line_no, line in _data_lines(path):
        if not line:
            continue
        tokens = line.split()
        camera_id, model, width, height = _parse(tokens, [int, str, int, int], path, line_no)
        if model not in MODEL_IDS:
            raise SurfSplatInputError(
                f"{path}:{line_no}: camera {camera_id} has camera model {model}, which is not supported (supported: {SUPPORTED})"
            )
        names = CAMERA_MODELS[MODEL_IDS[model]][1]
        if len(tokens) - 4 != len(names):
            raise SurfSplatInputError(
                f"{path}:{line_no}: camera {camera_id} ({model}) has {len(tokens) - 4} parameters, "
                f"expected {len(names)} ({', '.join(names)})"
            )
        params = _parse(tokens[4:], [float] * len(names), path, line_no)
        cameras[camera_id] = _lens(model, width, height, params, f"{path}:{line_no}: camera {camera_id}")
    return cameras


def read_images_text(path: Path) -> dict[int, ColmapImage]:
    images = {}
    lines = _data_lines(path)
    i = 0
    while i < len(lines):
        line_no, line = lines[i]
        if not line:  # blank lines may separate records; a header line is never blank
            i += 1
            continue
        tokens = line.split(maxsplit=9)
        fields = _parse(tokens, [int, float, float, float, float, float, float, float, int, str], path, line_no)
        points_line = lines[i + 1][1] if i + 1 < len(lines) else ""
        values = points_line.split()
        if len(values) % 3:
            raise SurfSplatInputError(f"{path}:{line_no + 1}: POINTS2D line must hold (X, Y, POINT3D_ID) triples")
        point_ids = np.array([int(v) for v in values[2::3]], dtype=np.int64)
        images[fields[0]] = ColmapImage(fields[1:5], fields[5:8], fields[8], fields[9], point_ids)
        i += 2
    return images


def read_points_text(path: Path) -> dict[int, np.ndarray]:
    points = {}
    for line_no, line in _data_lines(path):
        if not line:
            continue
        point_id, x, y, z = _parse(line.split(), [int, float, float, float], path, line_no)
        points[point_id] = np.array([x, y, z])
    return points


def read_model(model_dir: Path) -> tuple[dict[int, Lens], dict[int, ColmapImage], dict[int, np.ndarray] | None]:
    """(cameras, images, points or None) from a model folder, binary preferred over text."""
    ext = "bin" if (model_dir / "cameras.bin").is_file() else "txt"
    readers = {
        "bin": (read_cameras_binary, read_images_binary, read_points_binary),
        "txt": (read_cameras_text, read_images_text, read_points_text),
    }[ext]
    images_path = model_dir / f"images.{ext}"
    if not images_path.is_file():
        raise FileNotFoundError(f"{images_path}: COLMAP images file not found")
    cameras = readers[0](model_dir / f"cameras.{ext}")
    images = readers[1](images_path)
    points_path = model_dir / f"points3D.{ext}"
    points = readers[2](points_path) if points_path.is_file() else None
    return cameras, images, points


def cameras_file(model_dir: Path) -> Path:
    """The cameras file `read_model` reads in a model folder (binary preferred over text)."""
    return model_dir / ("cameras.bin" if (model_dir / "cameras.bin").is_file() else "cameras.txt")


def model_root(model_dir: Path) -> Path:
    """The capture folder of a model folder: <root>/sparse/0, <root>/sparse, or the model folder itself."""
    if model_dir.parent.name == "sparse":  # <root>/sparse/0
        return model_dir.parent.parent
    if model_dir.name == "sparse":  # <root>/sparse
        return model_dir.parent
    return model_dir


def _poses(ordered: list[ColmapImage], src: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(c2w [N, 4, 4], R [N, 3, 3], t [N, 3]) of the registered images, each pose checked."""
    q = torch.tensor([r.qvec for r in ordered], dtype=torch.float64)
    t = torch.tensor([r.tvec for r in ordered], dtype=torch.float64)
    bad = ~torch.isfinite(torch.cat([q, t], 1)).all(1)
    if bool(bad.any()):
        i = int(bad.nonzero()[0])
        raise SurfSplatInputError(f"{src}: image '{ordered[i].name}' has a NaN or inf pose")
    norms = q.norm(dim=1)
    off = (norms - 1).abs() > 1e-3
    if bool(off.any()):
        i = int(off.nonzero()[0])
        raise SurfSplatInputError(
            f"{src}: image '{ordered[i].name}' quaternion has norm {float(norms[i]):.6g}, expected a unit quaternion"
        )
    R = quat_to_matrix(q)
    w2c = torch.eye(4, dtype=torch.float64).repeat(len(ordered), 1, 1)
    w2c[:, :3, :3] = R
    w2c[:, :3, 3] = t
    return rigid_inverse(w2c), R, t


def _camera_of(cameras: dict[int, Lens], record: ColmapImage, src: str) -> Lens:
    if record.camera_id not in cameras:
        raise SurfSplatInputError(f"{src}: image '{record.name}' refers to missing camera {record.camera_id}")
    return cameras[record.camera_id]


def model_cameras(model_dir: Path, dtype: torch.dtype = torch.float64):
    """The CameraSet of a bare model folder (no photos read): each camera's K at its calibrated size,
    or, for a lens, the pinhole its photos are undistorted to, with `lenses` set."""
    cameras, records, _ = read_model(model_dir)
    if not records:
        raise SurfSplatInputError(f"{model_dir}: the model has no registered images")
    ordered = sorted(records.values(), key=lambda r: r.name)
    src = f"{model_dir}/images"
    c2w, _, _ = _poses(ordered, src)
    views = []
    where = cameras_file(model_dir)
    for r in ordered:
        lens = _camera_of(cameras, r, src)
        views.append(lens_view(lens, (lens.width, lens.height), f"{where}: camera {r.camera_id}", False))
    Ks, lenses, sizes = view_lenses(views)
    sizes_set = sorted(set(sizes))
    if len(sizes_set) != 1:
        raise SurfSplatInputError(
            f"{model_dir}/cameras: cameras of different image sizes {sizes_set} (after undistortion); "
            "give a JSON camera file instead"
        )
    from ..cameras import CameraSet

    cams = make_cameras(c2w, Ks, src, dtype)
    (width, height) = sizes_set[0]
    # no photo was read: the cameras are of the stored pixels, turned where the photos meet them
    return CameraSet(cams, width, height, [r.name for r in ordered], lenses=lenses, stored_pixels=True)


def load_colmap(
    path: Path,
    images: str | None = None,
    dtype: torch.dtype = torch.float32,
    cameras_only: bool = False,
) -> PosedImages:
    """Read a COLMAP capture (see module doc); `images` names the image folder under the root
    (default `images`; `images_N` folders are accepted as uniform downscales)."""
    model_dir = find_model(path)
    if model_dir is None:
        raise FileNotFoundError(f"{path}: no COLMAP model (cameras.bin or cameras.txt) in it, sparse/0 or sparse")
    root = model_root(model_dir)
    folder = root / (images or "images")
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: image folder not found (pass images=... to choose another)")

    cameras, records, points = read_model(model_dir)
    if not records:
        raise SurfSplatInputError(f"{model_dir}: the model has no registered images")
    ordered = sorted(records.values(), key=lambda r: r.name)
    keep = present_views([folder / r.name for r in ordered], f"{model_dir} (registered images)")
    ordered = [ordered[i] for i in keep]
    paths = [folder / r.name for r in ordered]

    src = f"{model_dir}/images"
    c2w, R, t = _poses(ordered, src)
    sizes = image_sizes(paths)
    views = []
    where = cameras_file(model_dir)
    for i, (r, p, size) in enumerate(zip(ordered, paths, sizes)):
        lens = _camera_of(cameras, r, src)
        # COLMAP calibrates the stored pixels (its Bitmap::Read sets oiio:reorient 0): a photo its EXIF
        # orientation turns gets its camera turned with it
        orientation = image_orientation(p)
        views.append(
            lens_view(
                lens, size, str(p), downscale_from_folder(folder), f"{where}: camera {r.camera_id}", orientation, c2w[i]
            )
        )
    Ks, lenses, view_sizes = view_lenses(views)
    c2w = torch.stack([view[3] for view in views])
    cams = make_cameras(c2w, Ks, src, dtype)

    near = far = None
    if points is not None:
        bounds = []
        for i, r in enumerate(ordered):
            ids = [int(pid) for pid in r.point_ids if pid >= 0 and int(pid) in points]
            if not ids:
                bounds = []
                break
            xyz = torch.from_numpy(np.stack([points[pid] for pid in ids]))
            z = (xyz @ R[i].T + t[i])[:, 2]
            z = z[z > 0]
            if z.numel() == 0:
                bounds = []
                break
            bounds.append((float(torch.quantile(z, 0.001)), float(torch.quantile(z, 0.999))))
        if bounds:
            near = torch.tensor([b[0] for b in bounds], dtype=dtype)
            far = torch.tensor([b[1] for b in bounds], dtype=dtype)
            far = torch.where(far > near, far, near * 1.01)

    names = [r.name for r in ordered]
    if cameras_only:
        return camera_set(cams, paths, view_sizes, names, near, far, lenses)
    rgb, alpha = load_image_stack(paths, background=(0.0, 0.0, 0.0))
    rgb, alpha = undistort_views(rgb, alpha, lenses, paths)
    extras = {} if lenses is None else {"lenses": lenses}  # the source lens of each view, before undistortion
    return PosedImages(
        images=rgb, cameras=cams, names=names, near=near, far=far, masks=alpha, source=str(root), extras=extras
    )
