"""Rotating real spherical-harmonic coefficients (degree <= 3) by a rotation matrix.

A colour field f(d) = sum_k c_k Y_k(d) over unit directions d, rotated by R, is the field
g(R d) = f(d). For each degree l the basis functions of that degree span a space that rotations
map to itself, Y_l(R d) = D_l(R) Y_l(d), and for an orthonormal basis D_l is orthogonal, so the
rotated coefficients are c'_l = D_l(R) c_l (the Wigner-D matrix of R in that basis).

Two conventions are offered:

- "3dgs" (the correct one for this package): D_l in the basis of `geometry/sh.py` (3DGS order
  and signs, z the polar axis). Rotating by R, then evaluating in direction R d, gives exactly
  what the original gave in direction d.
- "e3nn" (what the released SurfSplat/DepthSplat/pixelSplat code computes): e3nn's Wigner-D
  matrices, whose real basis has y as the polar axis, applied unchanged to coefficients stored in
  the 3DGS basis. The two bases are related by a fixed rotation P (3DGS basis at d equals e3nn's
  basis at P d, up to one constant factor), so the release's matrix is D_3dgs(P^T R P): it rotates
  the colour field by the conjugated rotation P^T R P instead of R. The two agree for R = I (every
  golden case of the release) and otherwise differ only in the view-dependent degrees >= 1.

D_l is computed without Euler angles: evaluate the basis at a fixed set of directions p_s and at
the rotated directions R p_s; since Y_l(R p_s) = D_l Y_l(p_s) holds exactly, D_l is the
least-squares solution, obtained with a precomputed pseudo-inverse. This is exact up to rounding,
smooth in R (differentiable), and costs a few hundred flops per rotation.
"""

from __future__ import annotations

import functools
import math
from typing import Literal

import torch
from torch import Tensor

from ..utils.checks import SurfSplatInputError
from .sh import sh_basis, sh_degree_from_bases

SHConvention = Literal["3dgs", "e3nn"]

# e3nn's real spherical harmonics use y as the polar axis: the 3DGS basis at direction d equals
# (a constant times) e3nn's basis at P d with P d = (-d_y, d_z, -d_x). P is a proper rotation.
_E3NN_FROM_3DGS = ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0), (-1.0, 0.0, 0.0))  # numbers, not a module-level tensor

# Sample directions for the least-squares fit; 32 points of a Fibonacci spiral make every degree
# up to 3 (7 basis functions) well conditioned.
_NUM_SAMPLES = 32


@functools.cache
@torch.inference_mode(False)
def _fit_operators(degree: int) -> tuple[Tensor, Tensor]:
    """Sample directions [S, 3] and, per degree l <= `degree`, pinv(Y_l(samples)) stacked block-wise.

    Returns (samples [S, 3], pinv [K, S]) in float64 on the CPU, K = (degree + 1)^2, where rows
    l^2 .. (l+1)^2 of `pinv` hold the pseudo-inverse of degree l's basis matrix. Made outside
    inference mode whatever the first caller runs under: the cache serves autograd later.
    """
    i = torch.arange(_NUM_SAMPLES, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / _NUM_SAMPLES
    r = (1.0 - z * z).sqrt()
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    samples = torch.stack((r * phi.cos(), r * phi.sin(), z), dim=-1)
    basis = sh_basis(samples, degree)  # [S, K]
    blocks = [torch.linalg.pinv(basis[:, l * l : (l + 1) ** 2]) for l in range(degree + 1)]
    return samples, torch.cat(blocks, dim=0)


def sh_rotation_matrix(rotations: Tensor, degree: int, convention: SHConvention = "3dgs") -> Tensor:
    """Block-diagonal matrices M with c' = M c rotating SH coefficients of degree <= `degree`.

    rotations: [..., 3, 3] proper rotations -> [..., K, K], K = (degree + 1)^2, same dtype.
    Computed in float64 (the matrices are few: one per camera) and cast back.
    """
    if not 0 <= degree <= 3:
        raise SurfSplatInputError(f"degree: expected an SH degree in 0..3, got {degree}")
    if rotations.ndim < 2 or rotations.shape[-2:] != (3, 3):
        raise SurfSplatInputError(f"rotations: expected shape [..., 3, 3], got {tuple(rotations.shape)}")
    if convention not in ("3dgs", "e3nn"):
        raise SurfSplatInputError(f"convention: expected '3dgs' or 'e3nn', got {convention!r}")
    samples, pinv = (t.to(rotations.device) for t in _fit_operators(degree))
    R = rotations.to(torch.float64)
    if convention == "e3nn":
        P = R.new_tensor(_E3NN_FROM_3DGS)
        R = P.T @ R @ P
    # Y(R p_s) for every sample: rows are R p_s = p_s R^T.  [..., S, K]
    rotated = sh_basis(samples @ R.transpose(-1, -2), degree)
    K = (degree + 1) ** 2
    out = R.new_zeros(*R.shape[:-2], K, K)
    for l in range(degree + 1):
        sl = slice(l * l, (l + 1) ** 2)
        # Y_l(R p_s) = D Y_l(p_s) for all s, i.e. rotated_l = basis_l D^T, so D = (pinv_l rotated_l)^T.
        out[..., sl, sl] = (pinv[sl] @ rotated[..., sl]).transpose(-1, -2)
    return out.to(rotations.dtype)


def rotate_sh(sh: Tensor, rotations: Tensor, convention: SHConvention = "3dgs") -> Tensor:
    """Rotate SH coefficients: `sh` [..., K] (K = (d+1)^2, e.g. [..., 3, 9] for RGB), `rotations`
    [..., 3, 3] broadcastable against sh.shape[:-1].  -> [..., K]

    With convention "3dgs", eval_sh(rotate_sh(sh, R), R d) == eval_sh(sh, d).
    """
    if sh.ndim < 1:
        raise SurfSplatInputError("sh: expected a tensor with a coefficient axis last")
    try:
        degree = sh_degree_from_bases(sh.shape[-1])
    except ValueError as err:
        raise SurfSplatInputError(str(err)) from None
    M = sh_rotation_matrix(rotations, degree, convention)
    return torch.einsum("...ij,...j->...i", M.to(sh.dtype), sh)
