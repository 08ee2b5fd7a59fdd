"""Real spherical harmonics up to degree 3 with the constants and sign convention of 3DGS.

Colour = sum_k sh_k Y_k(d) + 0.5, clamped at 0, with d the unit direction from the camera
centre to the Gaussian. Basis order within a degree follows 3DGS (m = -l .. l).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

SH_C0 = 0.28209479177387814  # 1 / (2 sqrt(pi))
SH_C1 = 0.4886025119029199  # sqrt(3 / (4 pi))
SH_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def sh_degree_from_bases(n: int) -> int:
    degree = math.isqrt(n) - 1
    if (degree + 1) ** 2 != n or not 0 <= degree <= 3:
        raise ValueError(f"sh: {n} coefficients per channel is not (d+1)^2 for a degree d in 0..3")
    return degree


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """Real SH basis values Y_k(d) for unit directions. dirs: [..., 3] -> [..., (degree+1)^2]"""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(sh: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate SH colour for unit directions (without the +0.5 offset).

    sh: [..., 3, (d+1)^2], dirs: [..., 3] -> [..., 3]
    """
    degree = sh_degree_from_bases(sh.shape[-1])
    basis = sh_basis(dirs, degree)  # [..., B]
    return (sh * basis[..., None, :]).sum(-1)


def sh_to_color(sh: Tensor, dirs: Tensor) -> Tensor:
    """RGB from SH as 3DGS renders it: SH(d) + 0.5, clamped at 0.  -> [..., 3]"""
    return (eval_sh(sh, dirs) + 0.5).clamp_min(0.0)


def rgb_to_sh_dc(rgb: Tensor) -> Tensor:
    """The DC coefficient that makes a constant colour `rgb` (the adapter's colour initialisation)."""
    return (rgb - 0.5) / SH_C0
