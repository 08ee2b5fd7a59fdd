"""Rotation conventions: quaternions are (w, x, y, z), matrices act on column vectors."""

from __future__ import annotations

import torch
from torch import Tensor


def quat_to_matrix(quats: Tensor) -> Tensor:
    """Unit rotation matrices from quaternions (w, x, y, z); input need not be normalized.

    quats: [..., 4] -> [..., 3, 3]
    """
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(torch.finfo(quats.dtype).tiny)
    w, x, y, z = q.unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    )
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def matrix_to_quat(matrices: Tensor) -> Tensor:
    """Quaternions (w, x, y, z) with w >= 0 from rotation matrices, stable for every angle.

    Picks, per matrix, the largest of the four squared components to divide by
    (Shepperd's method), so no branch divides by a small number.
    matrices: [..., 3, 3] -> [..., 4]
    """
    m = matrices
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # 4 * component^2 for w, x, y, z.
    sq = torch.stack(
        (
            1 + m00 + m11 + m22,
            1 + m00 - m11 - m22,
            1 - m00 + m11 - m22,
            1 - m00 - m11 + m22,
        ),
        dim=-1,
    )
    # Candidate quaternions, each scaled by 4 * (its own largest component).
    candidates = torch.stack(
        (
            torch.stack((sq[..., 0], m21 - m12, m02 - m20, m10 - m01), dim=-1),
            torch.stack((m21 - m12, sq[..., 1], m10 + m01, m02 + m20), dim=-1),
            torch.stack((m02 - m20, m10 + m01, sq[..., 2], m12 + m21), dim=-1),
            torch.stack((m10 - m01, m20 + m02, m21 + m12, sq[..., 3]), dim=-1),
        ),
        dim=-2,
    )
    best = sq.argmax(dim=-1)
    denom = 2 * sq.gather(-1, best[..., None]).clamp_min(1e-12).sqrt()
    q = candidates.gather(-2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2) / denom
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def skew(v: Tensor) -> Tensor:
    """Cross-product matrices [v]x with [v]x @ a = v x a.  v: [..., 3] -> [..., 3, 3]"""
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack((zero, -z, y, z, zero, -x, -y, x, zero), dim=-1).reshape(*v.shape[:-1], 3, 3)
