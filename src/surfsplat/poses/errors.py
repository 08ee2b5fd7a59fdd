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


def aligned_pose_errors(c2w: torch.Tensor, reference: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(rotation errors in degrees [N], centre errors [N] as a share of the reference's camera spread)
    of cameras c2w [N, 4, 4] against reference [N, 4, 4] (OpenCV camera-to-world, same order), each
    view on its own after aligning the estimate's world to the reference's.

    Rotations: the estimate's frame is turned by the rotation that best maps its camera rotations
    onto the reference's (scipy's chordal L2 mean of R_ref R_est^T). Centres: the similarity
    (rotation, translation, scale) that best maps the estimated centres onto the reference's, fitted
    by Umeyama's method (scikit-image's SimilarityTransform); the spread is the root mean square
    distance of the reference centres from their mean.
    """
    from scipy.spatial.transform import Rotation
    from skimage.transform import SimilarityTransform

    if c2w.shape != reference.shape or c2w.ndim != 3 or c2w.shape[1:] != (4, 4) or len(c2w) < 3:
        raise SurfSplatInputError(
            f"c2w, reference: expected two [N, 4, 4] tensors with N >= 3, got {tuple(c2w.shape)}, {tuple(reference.shape)}"
        )
    est = c2w.detach().to(torch.float64).cpu().numpy()
    ref = reference.detach().to(torch.float64).cpu().numpy()
    turn = Rotation.from_matrix(ref[:, :3, :3] @ est[:, :3, :3].transpose(0, 2, 1)).mean().as_matrix()
    D = np.einsum("nji,jk,nkl->nil", ref[:, :3, :3], turn, est[:, :3, :3])  # R_ref^T turn R_est
    sine = np.linalg.norm(
        np.stack([D[:, 2, 1] - D[:, 1, 2], D[:, 0, 2] - D[:, 2, 0], D[:, 1, 0] - D[:, 0, 1]], -1), axis=-1
    )
    rotations = np.degrees(np.arctan2(sine / 2, (np.trace(D, axis1=1, axis2=2) - 1) / 2))
    if hasattr(SimilarityTransform, "from_estimate"):  # scikit-image >= 0.26; `estimate` is deprecated there
        similarity = SimilarityTransform.from_estimate(est[:, :3, 3], ref[:, :3, 3])
        fitted = bool(similarity)
    else:
        similarity = SimilarityTransform(dimensionality=3)
        fitted = similarity.estimate(est[:, :3, 3], ref[:, :3, 3])
    if not fitted:
        raise SurfSplatInputError("c2w: the camera centres are degenerate (coincident), no similarity aligns them")
    moved = similarity(est[:, :3, 3])
    spread = np.sqrt(((ref[:, :3, 3] - ref[:, :3, 3].mean(0)) ** 2).sum(1).mean())
    return rotations, np.linalg.norm(moved - ref[:, :3, 3], axis=1) / max(spread, 1e-300)
