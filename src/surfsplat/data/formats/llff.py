"""LLFF captures: `poses_bounds.npy` plus an image folder (`images`, `images_4`, `images_8`, ...).

poses_bounds.npy is [N, 17]: [:, :15] reshapes to [N, 3, 5] whose columns 0-3 are camera-to-world
with axes (down, right, back) and column 4 is (H, W, focal) of the full-resolution photos;
[:, 15:17] are near/far depth bounds. The axis change to OpenCV is `Cameras.from_llff`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ...geometry.cameras import Cameras, validate_c2w
from ...utils.checks import SurfSplatInputError
from ..images import list_images
from ..posed_images import PosedImages, check_finite_rows, fit_intrinsics
from .common import camera_set, image_sizes, load_image_stack, make_cameras, pick_image_folder

POSES_FILE = "poses_bounds.npy"


def is_llff(path: Path) -> bool:
    return path.is_dir() and (path / POSES_FILE).is_file()


def read_poses_bounds(path: Path) -> tuple[torch.Tensor, torch.Tensor]:
    """(poses [N, 3, 5], bounds [N, 2]) in float64, checked for shape and finite values."""
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as err:
        raise SurfSplatInputError(f"{path}: cannot read ({type(err).__name__}: {err})") from None
    if array.ndim != 2 or array.shape[1] != 17:
        raise SurfSplatInputError(f"{path}: expected an array [N, 17], got shape {list(array.shape)}")
    if array.shape[0] == 0:
        raise SurfSplatInputError(f"{path}: no cameras")
    data = torch.from_numpy(array.astype(np.float64))
    check_finite_rows(data, str(path), "row")
    return data[:, :15].reshape(-1, 3, 5), data[:, 15:17]


def load_llff(
    root: Path,
    images: str | None = None,
    dtype: torch.dtype = torch.float32,
    cameras_only: bool = False,
) -> PosedImages:
    """Read an LLFF capture (see module doc); `images` picks the image folder by name."""
    poses_path = root / POSES_FILE
    poses, bounds = read_poses_bounds(poses_path)
    folder = pick_image_folder(root, images, ("images",), f" beside {POSES_FILE}")
    paths = list_images(folder)
    if len(paths) != poses.shape[0]:
        raise SurfSplatInputError(f"{poses_path}: {poses.shape[0]} camera rows but {len(paths)} images in {folder}")
    for i, (h, w, f) in enumerate(poses[:, :, 4].tolist()):
        if not (h >= 1 and w >= 1):
            raise SurfSplatInputError(f"{poses_path}: row {i} has image size H={h:g}, W={w:g}; expected positive")
        if not f > 0:
            raise SurfSplatInputError(f"{poses_path}: row {i}: focal length must be positive, got {f:g}")

    # LLFF's (down, right, back) frame is itself right-handed, so its 3x4 block must already be
    # rigid; checking it here lets the error name this file and row.
    raw = torch.eye(4, dtype=torch.float64).repeat(poses.shape[0], 1, 1)
    raw[:, :3, :] = poses[:, :, :4]
    validate_c2w(f"{poses_path}: camera", raw)
    # Conversion at full resolution (downscale 1); the image folder decides the factor below.
    full = Cameras.from_llff(poses)
    c2w, K = full.c2w, full.K

    sizes = image_sizes(paths)
    Ks = []
    for i, (p, size) in enumerate(zip(paths, sizes)):
        calibrated = (round(float(poses[i, 1, 4])), round(float(poses[i, 0, 4])))
        Ks.append(fit_intrinsics(K[i], calibrated, size, str(p), allow_downscale=True))
    cameras = make_cameras(c2w, torch.stack(Ks), str(poses_path), dtype)

    near, far = bounds[:, 0].to(dtype), bounds[:, 1].to(dtype)
    if cameras_only:
        return camera_set(cameras, paths, sizes, [p.name for p in paths], near, far)
    rgb, _ = load_image_stack(paths, background=None)
    near, far = bounds[:, 0].to(dtype), bounds[:, 1].to(dtype)
    if bool((near <= 0).any()) or bool((far <= near).any()):
        raise SurfSplatInputError(f"{poses_path}: depth bounds must satisfy 0 < near < far in every row")
    return PosedImages(
        images=rgb,
        cameras=cameras,
        names=[p.name for p in paths],
        near=near,
        far=far,
        source=str(root),
    )
