"""How far estimated cameras are from reference ones, in the terms pose papers report.

Pairwise relative rotations and translation directions do not change under a similarity
transform of the world (rotation, translation, scale), so they compare an estimate with a
calibration in another frame and unit exactly as a similarity alignment would, without depending
on how the alignment is fitted.
"""

from __future__ import annotations

import numpy as np
import torch

from ..utils.checks import SurfSplatInputError


def relative_pose_errors(c2w: torch.Tensor, reference: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(rotation errors, translation direction errors) in degrees [P] over every pair i < j of
    cameras c2w [N, 4, 4] against reference [N, 4, 4] (OpenCV camera-to-world, same order)."""
    if c2w.shape != reference.shape or c2w.ndim != 3 or c2w.shape[1:] != (4, 4) or len(c2w) < 2:
        raise SurfSplatInputError(
            f"c2w, reference: expected two [N, 4, 4] tensors with N >= 2, got {tuple(c2w.shape)}, {tuple(reference.shape)}"
        )
    w2c = np.linalg.inv(c2w.detach().to(torch.float64).cpu().numpy())
    w2c_ref = np.linalg.inv(reference.detach().to(torch.float64).cpu().numpy())
    rotations, directions = [], []
    for i in range(len(w2c)):
        for j in range(i + 1, len(w2c)):
            R, t = _relative(w2c, i, j)
            R_ref, t_ref = _relative(w2c_ref, i, j)
            # atan2 of sine and cosine stays exact near 0 degrees, where arccos loses half the digits
            D = R.T @ R_ref
            sine = np.linalg.norm([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]]) / 2
            rotations.append(np.degrees(np.arctan2(sine, (np.trace(D) - 1) / 2)))
            directions.append(np.degrees(np.arctan2(np.linalg.norm(np.cross(t, t_ref)), t @ t_ref)))
    return np.array(rotations), np.array(directions)


def _relative(w2c: np.ndarray, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera j from camera i: rotation and unit translation direction."""
    R = w2c[j, :3, :3] @ w2c[i, :3, :3].T
    t = w2c[j, :3, 3] - R @ w2c[i, :3, 3]
    return R, t / max(np.linalg.norm(t), 1e-300)
