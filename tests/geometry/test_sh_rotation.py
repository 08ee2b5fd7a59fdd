"""Rotation of real SH coefficients: the 3DGS-basis rotation and the release's e3nn-ordered one."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.spatial.transform import Rotation

from surfsplat.geometry.rotations import skew
from surfsplat.geometry.sh import SH_C1, eval_sh, sh_basis
from surfsplat.geometry.sh_rotation import rotate_sh, sh_rotation_matrix
from surfsplat.utils.checks import SurfSplatInputError


def random_rotations(n: int, seed: int) -> torch.Tensor:
    return torch.from_numpy(Rotation.random(n, random_state=seed).as_matrix())  # float64 [n, 3, 3]


def random_directions(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)


# ------------------------------------------------------------------ the e3nn construction, written out
# e3nn (0.5.x, the release's version) builds D^l(R) from Euler angles: R = Ry(a) Rx(b) Ry(c), and
# D^l = exp(a X_y) exp(b X_x) exp(c X_y) with X the so(3) generators of the complex |l, m> basis
# changed to its real basis (y is the polar axis). This slow twin follows that construction.
def _su2_generators(l: int) -> torch.Tensor:
    m = torch.arange(-l, l + 1, dtype=torch.float64)
    up = torch.zeros(2 * l + 1, 2 * l + 1, dtype=torch.complex128)
    down = torch.zeros_like(up)
    for i in range(2 * l):  # <m+1| J+ |m> = -sqrt(l(l+1) - m(m+1)) (e3nn's sign), <m-1| J- |m> = +sqrt(...)
        mi = float(m[i])
        up[i + 1, i] = -math.sqrt(l * (l + 1) - mi * (mi + 1))
        mj = float(m[i + 1])
        down[i, i + 1] = math.sqrt(l * (l + 1) - mj * (mj - 1))
    return torch.stack((0.5 * (up + down), torch.diag(1j * m.to(torch.complex128)), -0.5j * (up - down)))


def _real_from_complex(l: int) -> torch.Tensor:
    q = torch.zeros(2 * l + 1, 2 * l + 1, dtype=torch.complex128)
    s = 2**-0.5
    for m in range(-l, 0):
        q[l + m, l - m] = s
        q[l + m, l + m] = -1j * s
    q[l, l] = 1
    for m in range(1, l + 1):
        q[l + m, l + m] = (-1) ** m * s
        q[l + m, l - m] = 1j * (-1) ** m * s
    return (-1j) ** l * q


def _axis_rotation(axis: int, angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    if axis == 0:
        return torch.tensor([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=torch.float64)
    return torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)


def wigner_d_e3nn(l: int, R: torch.Tensor) -> torch.Tensor:
    """e3nn's wigner_D(l, *matrix_to_angles(R)) for one rotation R [3, 3] (float64)."""
    y = R[:, 1]  # R e_y
    b = math.acos(max(-1.0, min(1.0, float(y[1]))))
    a = math.atan2(float(y[0]), float(y[2]))
    rest = (_axis_rotation(1, a) @ _axis_rotation(0, b)).T @ R
    c = math.atan2(float(rest[0, 2]), float(rest[0, 0]))
    q = _real_from_complex(l)
    X = (q.conj().T @ _su2_generators(l) @ q).real
    return torch.matrix_exp(a * X[1]) @ torch.matrix_exp(b * X[0]) @ torch.matrix_exp(c * X[1])


# ------------------------------------------------------------------ the correct (3DGS-basis) rotation
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_rotated_coefficients_evaluated_in_rotated_direction_equal_original(degree: int) -> None:
    torch.manual_seed(0)
    R = random_rotations(6, seed=1)[:, None]  # [6, 1, 3, 3]
    sh = torch.randn(6, 3, (degree + 1) ** 2, dtype=torch.float64)
    d = random_directions(6, seed=2)
    rotated = rotate_sh(sh, R)
    Rd = (R[:, 0] @ d[..., None]).squeeze(-1)
    torch.testing.assert_close(eval_sh(rotated, Rd), eval_sh(sh, d), atol=1e-12, rtol=0)


def test_degree_one_closed_form() -> None:
    # Degree 1 of a 3DGS field is C1 * a . d with a = (-c2, -c0, c1); rotating the field rotates a.
    R = random_rotations(1, seed=3)[0]
    c = torch.tensor([0.3, -1.2, 0.7], dtype=torch.float64)
    a = torch.stack((-c[2], -c[0], c[1]))
    a_rot = R @ a
    expected = torch.stack((-a_rot[1], a_rot[2], -a_rot[0]))
    sh = torch.cat((torch.zeros(1, dtype=torch.float64), c))
    torch.testing.assert_close(rotate_sh(sh, R)[1:], expected, atol=1e-13, rtol=0)
    # and the basis itself is what the closed form assumes
    d = random_directions(4, seed=4)
    torch.testing.assert_close(sh_basis(d, 1)[:, 1:] @ c, SH_C1 * (d @ a), atol=1e-14, rtol=0)


def test_identity_leaves_coefficients_unchanged() -> None:
    torch.manual_seed(0)
    sh = torch.randn(10, 3, 16)
    for convention in ("3dgs", "e3nn"):
        torch.testing.assert_close(rotate_sh(sh, torch.eye(3), convention), sh, atol=2e-6, rtol=0)


def test_matrices_are_an_orthogonal_representation() -> None:
    R1, R2 = random_rotations(2, seed=5)
    for convention in ("3dgs", "e3nn"):
        M1, M2 = sh_rotation_matrix(R1, 3, convention), sh_rotation_matrix(R2, 3, convention)
        M12 = sh_rotation_matrix(R1 @ R2, 3, convention)
        torch.testing.assert_close(M12, M1 @ M2, atol=1e-12, rtol=0)
        torch.testing.assert_close(M1.T @ M1, torch.eye(16, dtype=torch.float64), atol=1e-12, rtol=0)


def test_float32_inputs_keep_float32_accuracy() -> None:
    torch.manual_seed(0)
    R = random_rotations(4, seed=6)
    sh = torch.randn(4, 3, 9, dtype=torch.float64)
    ref = rotate_sh(sh, R[:, None])
    out = rotate_sh(sh.float(), R[:, None].float())
    assert out.dtype == torch.float32
    torch.testing.assert_close(out.double(), ref, atol=2e-6, rtol=0)


def test_gradcheck_wrt_coefficients_and_rotation() -> None:
    torch.manual_seed(0)
    sh = torch.randn(2, 3, 9, dtype=torch.float64, requires_grad=True)
    # Parametrize the rotation by a rotation vector so the perturbed input stays a rotation.
    rotvec = torch.tensor([[0.3, -0.5, 0.9], [1.1, 0.2, -0.4]], dtype=torch.float64, requires_grad=True)

    def fn(sh: torch.Tensor, rotvec: torch.Tensor) -> torch.Tensor:
        angle = rotvec.norm(dim=-1)[:, None, None]
        k = skew(rotvec / angle[..., 0])
        R = torch.eye(3, dtype=torch.float64) + angle.sin() * k + (1 - angle.cos()) * (k @ k)
        return rotate_sh(sh, R[:, None])

    assert torch.autograd.gradcheck(fn, (sh, rotvec))


def test_operators_cached_under_inference_mode_still_serve_autograd() -> None:
    # The forward passes run under inference_mode; the first SH rotation of a process may happen
    # there (the release adapter), and its cached fit operators must not become inference tensors.
    from surfsplat.geometry import sh_rotation

    sh_rotation._fit_operators.cache_clear()
    R = torch.linalg.qr(torch.randn(4, 3, 3, dtype=torch.float64))[0]
    R = R * torch.linalg.det(R)[:, None, None]  # proper rotations
    with torch.inference_mode():
        rotate_sh(torch.randn(4, 3, 9, dtype=torch.float64), R[:, None])
    sh = torch.randn(4, 3, 9, dtype=torch.float64, requires_grad=True)
    R.requires_grad_(True)
    rotate_sh(sh, R[:, None]).square().sum().backward()
    assert sh.grad is not None and R.grad is not None and bool(torch.isfinite(R.grad).all())


# ------------------------------------------------------------------ the release's e3nn convention
@pytest.mark.parametrize("l", [1, 2, 3])
def test_e3nn_convention_matches_e3nn_wigner_d(l: int) -> None:
    for R in random_rotations(4, seed=7):
        M = sh_rotation_matrix(R, 3, "e3nn")[l * l : (l + 1) ** 2, l * l : (l + 1) ** 2]
        torch.testing.assert_close(M, wigner_d_e3nn(l, R), atol=1e-10, rtol=0)


def test_e3nn_wigner_d_degree_one_is_the_rotation_itself() -> None:
    # A fact about e3nn's convention that the construction above must reproduce: D^1(R) = R.
    R = random_rotations(1, seed=8)[0]
    torch.testing.assert_close(wigner_d_e3nn(1, R), R, atol=1e-12, rtol=0)
    torch.testing.assert_close(sh_rotation_matrix(R, 1, "e3nn")[1:, 1:], R, atol=1e-12, rtol=0)


def test_quirk_release_sh_rotation_rotates_by_a_conjugated_rotation() -> None:
    """The release applies e3nn's matrices to 3DGS-ordered coefficients: the colour field turns by
    P^T R P (P d = (-d_y, d_z, -d_x)), not by R. Degree 0 (the DC colour) is unaffected."""
    torch.manual_seed(0)
    R = random_rotations(1, seed=9)[0]
    sh = torch.randn(3, 9, dtype=torch.float64)
    d = random_directions(64, seed=10)
    release = rotate_sh(sh, R, "e3nn")
    wrong = (eval_sh(release[None], d @ R.T) - eval_sh(sh[None], d)).abs().max()
    assert wrong > 1e-2, "e3nn-ordered rotation unexpectedly equivariant in the 3DGS basis"
    P = torch.tensor([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]], dtype=torch.float64)
    torch.testing.assert_close(release, rotate_sh(sh, P.T @ R @ P), atol=1e-12, rtol=0)
    torch.testing.assert_close(release[:, 0], sh[:, 0], atol=1e-13, rtol=0)


def test_bad_inputs_raise_named_errors() -> None:
    with pytest.raises(SurfSplatInputError, match="rotations"):
        rotate_sh(torch.zeros(3, 9), torch.eye(4))
    with pytest.raises(SurfSplatInputError, match="sh"):
        rotate_sh(torch.zeros(3, 25), torch.eye(3))
    with pytest.raises(SurfSplatInputError, match="convention"):
        rotate_sh(torch.zeros(3, 9), torch.eye(3), "wigner")  # type: ignore[arg-type]
