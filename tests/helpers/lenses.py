"""Lens test helpers: COLMAP models written by pycolmap itself, photos distorted by pycolmap's own
projection, and pycolmap-backed references of `undistorted_pinhole` and `undistort`.

The references are COLMAP's own functions (`pycolmap.undistort_camera`, `pycolmap.undistort_image`).
The `lens_math` fixture of the reader tests installs them only where the package's own functions are
absent, so the readers can be tested on their own; where the package has them, the package's run and
the references check them.
"""

from __future__ import annotations

import sys
import types
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from surfsplat import Cameras
from surfsplat.geometry.cameras import rigid_inverse
from surfsplat.geometry.lens import Lens

# Realistic parameters of every COLMAP model 0-10 for a 100x75 photo (focal about 90 px), in COLMAP's order.
MODEL_PARAMS: dict[str, list[float]] = {
    "SIMPLE_PINHOLE": [90.0, 50.0, 37.5],
    "PINHOLE": [90.0, 88.0, 50.5, 37.0],
    "SIMPLE_RADIAL": [90.0, 50.0, 37.5, -0.08],
    "RADIAL": [90.0, 50.0, 37.5, -0.08, 0.02],
    "OPENCV": [90.0, 88.0, 50.5, 37.0, -0.1, 0.05, 0.001, -0.001],
    "OPENCV_FISHEYE": [90.0, 88.0, 50.5, 37.0, 0.05, -0.01, 0.002, 0.0],
    "FULL_OPENCV": [90.0, 88.0, 50.5, 37.0, -0.1, 0.05, 0.001, -0.001, 0.01, 0.002, 0.001, 0.0005],
    "FOV": [90.0, 88.0, 50.5, 37.0, 0.3],
    "SIMPLE_RADIAL_FISHEYE": [90.0, 50.0, 37.5, 0.04],
    "RADIAL_FISHEYE": [90.0, 50.0, 37.5, 0.04, -0.005],
    "THIN_PRISM_FISHEYE": [90.0, 88.0, 50.5, 37.0, 0.04, -0.005, 0.001, -0.001, 0.001, 0.0, 0.0005, -0.0005],
}


def colmap_camera(lens: Lens):
    import pycolmap

    return pycolmap.Camera(model=lens.model, width=lens.width, height=lens.height, params=list(lens.params))


def reference_pinhole(lens: Lens) -> Lens:
    """COLMAP image_undistorter's pinhole of a lens (default options)."""
    import pycolmap

    camera = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), colmap_camera(lens))
    return Lens("PINHOLE", int(camera.width), int(camera.height), tuple(float(v) for v in camera.params))


def reference_undistort(image: torch.Tensor, lens: Lens, pinhole: Lens, mode: str = "bilinear") -> torch.Tensor:
    """[C, H, W] in [0, 1] undistorted by pycolmap.undistort_image (8-bit, bilinear) to `pinhole`'s size."""
    import pycolmap

    arr = (image.permute(1, 2, 0).numpy() * 255).round().clip(0, 255).astype(np.uint8)
    channels = arr.shape[2]
    planes = [arr[..., c] for c in range(channels)] if channels != 3 else [arr]
    out = []
    for plane in planes:
        bitmap, camera = pycolmap.undistort_image(
            pycolmap.UndistortCameraOptions(),
            pycolmap.Bitmap.from_array(np.ascontiguousarray(plane)),
            colmap_camera(lens),
        )
        assert (camera.width, camera.height) == (pinhole.width, pinhole.height)
        result = np.asarray(bitmap.to_array())
        out.append(result if result.ndim == 3 else result[..., None])
    return torch.from_numpy(np.concatenate(out, -1).astype(np.float32) / 255).permute(2, 0, 1)


def install_lens_references(monkeypatch) -> None:
    """The references in place of `undistorted_pinhole` and `surfsplat.data.undistort.undistort`, where the
    package does not have them."""
    import surfsplat.geometry.lens as lens_module

    if not hasattr(lens_module, "undistorted_pinhole"):
        monkeypatch.setattr(lens_module, "undistorted_pinhole", reference_pinhole, raising=False)
    try:
        import surfsplat.data.undistort  # noqa: F401
    except ImportError:
        module = types.ModuleType("surfsplat.data.undistort")
        module.undistort = reference_undistort
        monkeypatch.setitem(sys.modules, "surfsplat.data.undistort", module)


def has_lens_functions() -> bool:
    import surfsplat.geometry.lens as lens_module

    try:
        import surfsplat.data.undistort  # noqa: F401
    except ImportError:
        return False
    return hasattr(lens_module, "undistorted_pinhole")


def distort_photo(image: torch.Tensor, K: torch.Tensor, lens: Lens) -> torch.Tensor:
    """A photo [3, H, W] of a pinhole camera K as the lens would have taken it ([3, lens.height, lens.width]):
    each distorted pixel centre is unprojected by pycolmap's cam_from_img and sampled in the pinhole photo."""
    camera = colmap_camera(lens)
    j, i = np.meshgrid(np.arange(lens.width) + 0.5, np.arange(lens.height) + 0.5)
    xy = camera.cam_from_img(np.stack([j.ravel(), i.ravel()], -1))  # normalized image-plane coordinates
    u = K[0, 0].item() * xy[:, 0] + K[0, 2].item()
    v = K[1, 1].item() * xy[:, 1] + K[1, 2].item()
    H, W = image.shape[1:]
    grid = torch.from_numpy(np.stack([u / W * 2 - 1, v / H * 2 - 1], -1)).float().reshape(1, lens.height, lens.width, 2)
    return F.grid_sample(image[None], grid, align_corners=False, padding_mode="border")[0]


def write_pycolmap_model(
    folder: Path, cams: Cameras, names: list[str], lens: Lens, binary: bool, points: torch.Tensor | None = None
) -> None:
    """A COLMAP model written by pycolmap (`Reconstruction.write` binary, `write_text` text) with one camera."""
    import pycolmap

    folder.mkdir(parents=True, exist_ok=True)
    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(
        pycolmap.Camera(model=lens.model, width=lens.width, height=lens.height, params=list(lens.params), camera_id=1)
    )
    w2c = rigid_inverse(cams.c2w.double())
    for i, name in enumerate(names):
        R = w2c[i, :3, :3].numpy()
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R), w2c[i, :3, 3].numpy())
        reconstruction.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=1, image_id=i + 1), pose)
    if points is not None:
        for xyz in points.tolist():
            reconstruction.add_point3D(np.array(xyz), pycolmap.Track(), np.zeros(3, np.uint8))
    (reconstruction.write if binary else reconstruction.write_text)(str(folder))


def write_photos(folder: Path, names: list[str], images: torch.Tensor) -> None:
    """[N, 3, H, W] in [0, 1] as 8-bit PNGs."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, image in zip(names, images):
        arr = (image.permute(1, 2, 0).numpy() * 255).round().clip(0, 255).astype(np.uint8)
        Image.fromarray(arr).save(folder / name)
