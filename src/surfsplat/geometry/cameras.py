"""Pinhole cameras in one convention, with converters at the boundary.

Convention (pinned by tests/geometry/test_conventions.py):
- `c2w` is camera-to-world with OpenCV axes: x right, y down, z forward.
- `K` is in pixels for a stated image size; pixel (row i, column j) has its centre at
  (j + 0.5, i + 0.5), so rendering at s times the resolution uses K' = diag(s, s, 1) K exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..utils.checks import SurfSplatInputError, check_tensor

# OpenGL / Blender camera axes (x right, y up, z backward) <-> OpenCV (x right, y down, z forward).
# Constants as numbers, made tensors where used: a module-level tensor made while the module is first
# imported under torch.inference_mode() would be an inference tensor, which autograd refuses to save.
_FLIP_YZ = (1.0, -1.0, -1.0, 1.0)  # OpenGL <-> OpenCV camera axes: diag(_FLIP_YZ)
# LLFF stores camera-to-world columns as (down, right, back); OpenCV columns are (right, down, forward).
_LLFF_TO_OPENCV = ((0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, -1.0))  # c2w_cv[:, :3] = c2w_llff[:, :3] @ it


@dataclass
class Cameras:
    """A batch of C pinhole cameras.

    c2w: [C, 4, 4] camera-to-world, OpenCV axes.
    K:   [C, 3, 3] intrinsics in pixels.
    """

    c2w: Tensor  # [C, 4, 4]
    K: Tensor  # [C, 3, 3]
    validate: bool = True  # set False only for tensors already validated (internal use)

    def __post_init__(self) -> None:
        if not self.validate:
            return
        c2w = check_tensor("cameras.c2w", self.c2w, ("C", 4, 4))
        K = check_tensor("cameras.K", self.K, (c2w.shape[0], 3, 3))
        validate_c2w("cameras.c2w", c2w)
        validate_intrinsics("cameras.K", K)

    # ------------------------------------------------------------------ basic accessors
    def __len__(self) -> int:
        return self.c2w.shape[0]

    def __getitem__(self, index: int | slice | Tensor) -> Cameras:
        if isinstance(index, int):
            index = slice(index, index + 1 if index != -1 else None)
        return Cameras(self.c2w[index], self.K[index], validate=False)

    def to(self, *args, **kwargs) -> Cameras:
        return Cameras(self.c2w.to(*args, **kwargs), self.K.to(*args, **kwargs), validate=False)

    @property
    def device(self) -> torch.device:
        return self.c2w.device

    @property
    def w2c(self) -> Tensor:
        """[C, 4, 4] world-to-camera, computed as the exact rigid inverse."""
        R = self.c2w[:, :3, :3]
        t = self.c2w[:, :3, 3:]
        out = torch.zeros_like(self.c2w)
        out[:, :3, :3] = R.transpose(1, 2)
        out[:, :3, 3:] = -R.transpose(1, 2) @ t
        out[:, 3, 3] = 1
        return out

    @property
    def centers(self) -> Tensor:
        """[C, 3] camera centres in world coordinates."""
        return self.c2w[:, :3, 3]

    def scaled(self, s: float) -> Cameras:
        """The same cameras for images s times wider and taller: K' = diag(s, s, 1) K."""
        if not s > 0:
            raise SurfSplatInputError(f"scale: expected a positive factor, got {s}")
        # diag(s, s, 1) filled where K is: built from a Python list it would be a copy to the device
        S = torch.full((3,), s, dtype=self.K.dtype, device=self.K.device)
        S[2] = 1.0
        return Cameras(self.c2w, self.K * S[:, None], validate=False)

    # ------------------------------------------------------------------ converters
    @staticmethod
    def from_normalized(c2w: Tensor, K_normalized: Tensor, width: int, height: int) -> Cameras:
        """From intrinsics normalized by image size (fx/W, fy/H, cx/W, cy/H), as RealEstate10K stores them."""
        K = K_normalized.clone()
        K[:, 0, :] = K[:, 0, :] * width
        K[:, 1, :] = K[:, 1, :] * height
        return Cameras(c2w, K)

    def normalized_intrinsics(self, width: int, height: int) -> Tensor:
        """[C, 3, 3] intrinsics divided by image size (the inverse of `from_normalized`)."""
        K = self.K.clone()
        K[:, 0, :] = K[:, 0, :] / width
        K[:, 1, :] = K[:, 1, :] / height
        return K

    @staticmethod
    def from_opengl(c2w_opengl: Tensor, K: Tensor) -> Cameras:
        """From OpenGL/Blender camera-to-world matrices (x right, y up, z backward)."""
        flip = c2w_opengl.new_tensor(_FLIP_YZ).diag()
        return Cameras(c2w_opengl @ flip, K)

    def to_opengl(self) -> Tensor:
        """[C, 4, 4] camera-to-world with OpenGL/Blender axes."""
        return self.c2w @ self.c2w.new_tensor(_FLIP_YZ).diag()

    @staticmethod
    def from_llff(poses: Tensor, downscale: float = 1.0) -> Cameras:
        """From LLFF poses [N, 3, 5]: columns 0-3 camera-to-world with axes (down, right, back),
        column 4 = (H, W, focal) of the full-resolution images; `downscale` = 8 for images_8."""
        check_tensor("poses", poses, ("N", 3, 5))
        n = poses.shape[0]
        c2w = torch.zeros(n, 4, 4, dtype=poses.dtype, device=poses.device)
        c2w[:, :3, :3] = poses[:, :, :3] @ poses.new_tensor(_LLFF_TO_OPENCV)
        c2w[:, :3, 3] = poses[:, :, 3]
        c2w[:, 3, 3] = 1
        h, w, f = (poses[:, i, 4] / downscale for i in range(3))
        K = torch.zeros(n, 3, 3, dtype=poses.dtype, device=poses.device)
        K[:, 0, 0] = f
        K[:, 1, 1] = f
        K[:, 0, 2] = w / 2
        K[:, 1, 2] = h / 2
        K[:, 2, 2] = 1
        return Cameras(c2w, K)

    def to_llff(self, width: int, height: int, downscale: float = 1.0) -> Tensor:
        """[C, 3, 5] LLFF poses (inverse of `from_llff`; needs fx == fy and a centred principal point)."""
        out = torch.zeros(len(self), 3, 5, dtype=self.c2w.dtype, device=self.c2w.device)
        out[:, :, :3] = self.c2w[:, :3, :3] @ self.c2w.new_tensor(_LLFF_TO_OPENCV).T
        out[:, :, 3] = self.c2w[:, :3, 3]
        out[:, 0, 4] = height * downscale
        out[:, 1, 4] = width * downscale
        out[:, 2, 4] = self.K[:, 0, 0] * downscale
        return out

    @staticmethod
    def from_re10k(rows: Tensor, width: int, height: int) -> Cameras:
        """From RealEstate10K 18-float rows [N, 18]: fx, fy, cx, cy normalized by image size,
        two zeros, then the row-major 3x4 world-to-camera matrix (OpenCV axes)."""
        check_tensor("cameras", rows, ("N", 18))
        n = rows.shape[0]
        fx, fy, cx, cy = rows[:, :4].unbind(-1)
        K = torch.zeros(n, 3, 3, dtype=rows.dtype, device=rows.device)
        K[:, 0, 0] = fx * width
        K[:, 1, 1] = fy * height
        K[:, 0, 2] = cx * width
        K[:, 1, 2] = cy * height
        K[:, 2, 2] = 1
        w2c = torch.eye(4, dtype=rows.dtype, device=rows.device).repeat(n, 1, 1)
        w2c[:, :3, :] = rows[:, 6:].reshape(n, 3, 4)
        validate_c2w("cameras (world-to-camera rows)", w2c)
        return Cameras(rigid_inverse(w2c), K)

    def to_re10k(self, width: int, height: int) -> Tensor:
        """[C, 18] RealEstate10K rows (inverse of `from_re10k`)."""
        out = torch.zeros(len(self), 18, dtype=self.c2w.dtype, device=self.c2w.device)
        out[:, 0] = self.K[:, 0, 0] / width
        out[:, 1] = self.K[:, 1, 1] / height
        out[:, 2] = self.K[:, 0, 2] / width
        out[:, 3] = self.K[:, 1, 2] / height
        out[:, 6:] = self.w2c[:, :3, :].reshape(-1, 12)
        return out


def rigid_inverse(T: Tensor) -> Tensor:
    """Inverse of rigid 4x4 transforms [..., 4, 4] without a general matrix inverse."""
    R = T[..., :3, :3]
    t = T[..., :3, 3:]
    out = torch.zeros_like(T)
    out[..., :3, :3] = R.transpose(-1, -2)
    out[..., :3, 3:] = -R.transpose(-1, -2) @ t
    out[..., 3, 3] = 1
    return out


def validate_c2w(name: str, c2w: Tensor, tol: float = 1e-3) -> None:
    """Raise unless every [4, 4] matrix is a rigid transform (rotation, translation, [0 0 0 1])."""
    check_tensor(name, c2w, (None, 4, 4))
    if c2w.shape[0] == 0:
        return
    # Every constant is made on the matrices' device (a CPU one stops a CUDA run here) and none is
    # copied from Python data (a blocking upload that waits for the device).
    R = c2w[:, :3, :3].to(torch.float64)
    eye = torch.eye(3, dtype=torch.float64, device=c2w.device)
    orth_err = (R.transpose(1, 2) @ R - eye).abs().amax(dim=(1, 2))
    det = torch.linalg.det(R)
    bottom = c2w[:, 3, :].to(torch.float64)  # expected (0, 0, 0, 1)
    bottom_err = torch.cat((bottom[:, :3], bottom[:, 3:] - 1), dim=1).abs().amax(1)
    bad = (orth_err > tol) | ((det - 1).abs() > tol) | (bottom_err > tol)
    if bool(bad.any()):
        i = int(bad.nonzero()[0])
        raise SurfSplatInputError(
            f"{name}[{i}]: not a rigid camera transform (|R^T R - I| = {orth_err[i]:.3g}, "
            f"det R = {det[i]:.4g}, bottom row {c2w[i, 3].tolist()})"
        )


def validate_intrinsics(name: str, K: Tensor) -> None:
    """Raise unless every K has positive focal lengths and the pinhole layout."""
    check_tensor(name, K, (None, 3, 3))
    if K.shape[0] == 0:
        return
    focal_bad = (K[:, 0, 0] <= 0) | (K[:, 1, 1] <= 0)
    if bool(focal_bad.any()):
        i = int(focal_bad.nonzero()[0])
        raise SurfSplatInputError(
            f"{name}[{i}]: focal lengths must be positive, got fx={float(K[i, 0, 0]):.6g}, fy={float(K[i, 1, 1]):.6g}"
        )
    last = torch.cat((K[:, 2, :2], K[:, 2, 2:] - 1), dim=1)  # expected (0, 0, 1)
    layout_bad = (last.abs().amax(1) > 1e-6) | (K[:, 1, 0].abs() > 1e-6)
    if bool(layout_bad.any()):
        i = int(layout_bad.nonzero()[0])
        raise SurfSplatInputError(f"{name}[{i}]: expected a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")


def look_at(eyes: Tensor, targets: Tensor, down: tuple[float, float, float] = (0.0, 1.0, 0.0)) -> Tensor:
    """OpenCV camera-to-world [..., 4, 4] at eyes [..., 3] looking at targets [..., 3], without
    roll: the image's y axis as close to the world direction `down` as it can be.

    z (forward) = normalize(target - eye); x (right) = normalize(down x z); y = z x x, so that x, y,
    z is right-handed. A world with z up passes down = (0, 0, -1).
    """
    z = torch.nn.functional.normalize(targets - eyes, dim=-1)
    d = torch.tensor(down, dtype=z.dtype, device=z.device).expand_as(z)
    x = torch.nn.functional.normalize(torch.linalg.cross(d, z, dim=-1), dim=-1)
    y = torch.linalg.cross(z, x, dim=-1)
    c2w = torch.zeros(*z.shape[:-1], 4, 4, dtype=z.dtype, device=z.device)
    c2w[..., :3, 0], c2w[..., :3, 1], c2w[..., :3, 2] = x, y, z
    c2w[..., :3, 3] = eyes.expand_as(z)
    c2w[..., 3, 3] = 1
    return c2w
