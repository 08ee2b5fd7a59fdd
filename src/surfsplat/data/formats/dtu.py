"""DTU in the IDR / NeuS packaging: `cameras_sphere.npz` (or `cameras.npz`), an image folder, `mask/`.

`world_mat_i` is a 4x4 whose top 3x4 is the projection P = K [R | t] (world -> pixels at the
1600x1200 sensor resolution); `scale_mat_i` maps the unit sphere onto the object, so that
P @ scale_mat projects the normalized world (object inside the unit sphere). P is split into
K, R, t by an RQ decomposition (Hartley & Zisserman, Sec. 6.2.4) with the signs fixed so that
K has a positive diagonal and R is a rotation.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import scipy.linalg
import torch
import torch.nn.functional as F
from torch import Tensor

from ...utils.checks import SurfSplatInputError
from ..images import list_images, read_image
from ..posed_images import PosedImages, fit_intrinsics
from .common import camera_set, image_sizes, load_image_stack, make_cameras, pick_image_folder

CAMERA_FILES = ("cameras_sphere.npz", "cameras.npz")
DTU_SENSOR_SIZE = (1600, 1200)  # (W, H) at which DTU's calibration (and IDR's world_mat) is expressed


def is_dtu(path: Path) -> bool:
    return path.is_dir() and any((path / name).is_file() for name in CAMERA_FILES)


def decompose_projection(P: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Split a 3x4 projection P ~ K [R | t] (any non-zero projective scale) into
    K [3, 3] (positive diagonal, K[2, 2] = 1), R [3, 3] (det +1) and t [3], in float64."""
    P = P.to(torch.float64)
    M = P[:, :3].numpy()
    if abs(np.linalg.det(M)) <= 1e-12 * np.abs(M).max() ** 3:
        raise SurfSplatInputError("projection matrix: its left 3x3 block is singular")
    K, R = scipy.linalg.rq(M)
    # RQ is unique up to signs: D = diag(sign(K_ii)) gives K D and D R with K's diagonal positive.
    D = np.diag(np.sign(np.diag(K)))
    K, R = K @ D, D @ R
    p4 = P[:, 3].numpy()
    if np.linalg.det(R) < 0:
        # P and -P are the same projection: -P = K [-R | -p4'] keeps K and has det(-R) = +1.
        R, p4 = -R, -p4
    scale = K[2, 2]
    t = np.linalg.solve(K, p4)
    K = K / scale
    return torch.from_numpy(K), torch.from_numpy(R), torch.from_numpy(t)


def _indexed(npz: dict[str, np.ndarray], prefix: str) -> dict[int, np.ndarray]:
    pattern = re.compile(rf"^{prefix}_(\d+)$")
    out = {}
    for key, value in npz.items():
        m = pattern.match(key)
        if m:
            out[int(m.group(1))] = value
    return out


def _read_masks(folder: Path, count: int, size: tuple[int, int]) -> Tensor:
    """Masks [N, 1, H, W] in [0, 1] resized (area average) to the image size (W, H)."""
    paths = list_images(folder)
    if len(paths) != count:
        raise SurfSplatInputError(f"{folder}: {len(paths)} masks for {count} images")
    w, h = size
    masks = []
    for p in paths:
        rgb, _ = read_image(p, background=(0.0, 0.0, 0.0))
        m = rgb[:1]
        mh, mw = m.shape[1:]
        if (mw, mh) != (w, h):
            if abs(mw / w - mh / h) > 1e-6 * max(mw / w, 1):
                raise SurfSplatInputError(f"{p}: mask is {mw}x{mh}, not a uniform scale of the {w}x{h} images")
            m = F.interpolate(m[None], size=(h, w), mode="area")[0]
        masks.append(m)
    return torch.stack(masks)


def load_dtu(
    root: Path,
    images: str | None = None,
    apply_scale_mat: bool = True,
    calibrated_size: tuple[int, int] = DTU_SENSOR_SIZE,
    dtype: torch.dtype = torch.float32,
    cameras_only: bool = False,
) -> PosedImages:
    """Read a DTU scan in IDR packaging (see module doc).

    apply_scale_mat: express the world in IDR's normalized frame (object inside the unit sphere);
        False keeps DTU's original world (millimetres).
    calibrated_size: (W, H) at which world_mat's K is expressed; images in a folder at a uniform
        downscale of it (`images_4`) get K scaled accordingly.
    near/far: camera-z range of the bounding sphere (the unit sphere, or scale_mat's sphere in the
        original world) per view, with near clamped to at least 1% of far.
    """
    cam_path = next(root / name for name in CAMERA_FILES if (root / name).is_file())
    try:
        with np.load(cam_path, allow_pickle=False) as data:
            npz = {k: np.asarray(data[k]) for k in data.files}
    except (OSError, ValueError, EOFError) as err:
        raise SurfSplatInputError(f"{cam_path}: cannot read ({type(err).__name__}: {err})") from None
    world = _indexed(npz, "world_mat")
    scale = _indexed(npz, "scale_mat")
    if not world:
        raise SurfSplatInputError(f"{cam_path}: no world_mat_i entries")
    n = max(world) + 1
    missing = [i for i in range(n) if i not in world]
    if missing:
        raise SurfSplatInputError(f"{cam_path}: missing key world_mat_{missing[0]} ({n} views expected)")

    folder = pick_image_folder(root, images, ("image", "images"), "")
    paths = list_images(folder)
    if len(paths) != n:
        raise SurfSplatInputError(f"{cam_path}: {n} cameras but {len(paths)} images in {folder}")
    sizes = image_sizes(paths)

    c2w = torch.zeros(n, 4, 4, dtype=torch.float64)
    Ks = []
    near = torch.zeros(n, dtype=torch.float64)
    far = torch.zeros(n, dtype=torch.float64)
    has_sphere = apply_scale_mat or bool(scale)
    for i in range(n):
        W = torch.from_numpy(world[i].astype(np.float64))
        if W.shape != (4, 4) and W.shape != (3, 4):
            raise SurfSplatInputError(f"{cam_path}: world_mat_{i} has shape {list(W.shape)}, expected [4, 4]")
        if not bool(torch.isfinite(W).all()):
            raise SurfSplatInputError(f"{cam_path}: world_mat_{i} contains NaN or inf")
        S = torch.eye(4, dtype=torch.float64)
        if has_sphere:
            if i not in scale:
                raise SurfSplatInputError(f"{cam_path}: missing key scale_mat_{i} (needed for the bounding sphere)")
            S = torch.from_numpy(scale[i].astype(np.float64))
            if S.shape != (4, 4) or not bool(torch.isfinite(S).all()):
                raise SurfSplatInputError(f"{cam_path}: scale_mat_{i} must be a finite 4x4 matrix")
        P = W[:3, :4] @ S if apply_scale_mat else W[:3, :4]
        try:
            K, R, t = decompose_projection(P)
        except SurfSplatInputError as err:
            raise SurfSplatInputError(f"{cam_path}: world_mat_{i}: {err}") from None
        c2w[i, :3, :3] = R.T
        c2w[i, :3, 3] = -R.T @ t
        c2w[i, 3, 3] = 1
        Ks.append(fit_intrinsics(K, calibrated_size, sizes[i], str(paths[i]), allow_downscale=True))
        if has_sphere:
            # Bounding sphere: the unit sphere in the normalized frame, scale_mat's sphere otherwise.
            centre = torch.zeros(3, dtype=torch.float64) if apply_scale_mat else S[:3, 3]
            radius = 1.0 if apply_scale_mat else float(S[:3, :3].diagonal().abs().mean())
            z = float(R[2] @ centre + t[2])
            far[i] = z + radius
            near[i] = max(z - radius, 0.01 * (z + radius))
    cameras = make_cameras(c2w, torch.stack(Ks), str(cam_path), dtype)

    if cameras_only:
        bounds = (near.to(dtype), far.to(dtype)) if has_sphere else (None, None)
        return camera_set(cameras, paths, sizes, [p.name for p in paths], *bounds)
    rgb, _ = load_image_stack(paths, background=None)
    masks = None
    if (root / "mask").is_dir():
        masks = _read_masks(root / "mask", n, sizes[0]).to(rgb.dtype)
    extras: dict[str, object] = {
        "world_mats": torch.stack([torch.from_numpy(world[i].astype(np.float64)) for i in range(n)])
    }
    if scale:
        extras["scale_mats"] = torch.stack([torch.from_numpy(scale[i].astype(np.float64)) for i in sorted(scale)])
    return PosedImages(
        images=rgb,
        cameras=cameras,
        names=[p.name for p in paths],
        near=near.to(dtype) if has_sphere else None,
        far=far.to(dtype) if has_sphere else None,
        masks=masks,
        source=str(root),
        extras=extras,
    )
