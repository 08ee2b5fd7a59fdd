"""Conventions pinned: camera axes, pixel centres, K scaling, quaternion order, format converters."""

from __future__ import annotations

import math

import pytest
import torch

from surfsplat import Cameras
from surfsplat.geometry.rotations import matrix_to_quat, quat_to_matrix
from surfsplat.utils.checks import SurfSplatInputError


def random_c2w(n: int, seed: int = 0, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g, dtype=dtype)
    c2w = torch.eye(4, dtype=dtype).repeat(n, 1, 1)
    c2w[:, :3, :3] = quat_to_matrix(q)
    c2w[:, :3, 3] = torch.randn(n, 3, generator=g, dtype=dtype)
    return c2w


def project(cam: Cameras, points: torch.Tensor) -> torch.Tensor:
    """World points [P, 3] -> pixel coordinates [C, P, 2]."""
    pc = points @ cam.w2c[:, :3, :3].transpose(1, 2) + cam.w2c[:, None, :3, 3]
    uvw = pc @ cam.K.transpose(1, 2)
    return uvw[..., :2] / uvw[..., 2:]


def test_convention_opencv_axes_and_pixel_centres():
    # A point on the optical axis lands on the principal point; +x world -> right, +y world -> down.
    K = torch.tensor([[[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]]], dtype=torch.float64)
    cam = Cameras(torch.eye(4, dtype=torch.float64)[None], K)
    p = project(cam, torch.tensor([[0.0, 0, 2], [0.2, 0, 2], [0, 0.2, 2]], dtype=torch.float64))[0]
    assert torch.allclose(p[0], torch.tensor([32.0, 24.0], dtype=torch.float64))
    assert p[1, 0] > 32 and p[1, 1] == 24  # right
    assert p[2, 1] > 24 and p[2, 0] == 32  # down
    # Pixel (row i, column j) has its centre at (j + 0.5, i + 0.5): with cx = W / 2 the principal
    # point is the corner shared by the four central pixels of an even-sized image.
    assert float(K[0, 0, 2]) == 64 / 2


@pytest.mark.parametrize("s", [0.5, 2.0, 4.0, 3.0])
def test_convention_k_scaling_keeps_pixel_centres_aligned(s):
    # Under K' = diag(s, s, 1) K a point projecting to the continuous position x lands on s * x,
    # so the centre of low-res pixel j, (j + 0.5), maps to s (j + 0.5): the centre of the block of
    # s x s high-res pixels that covers it.
    cam = Cameras(
        random_c2w(3),
        torch.tensor([[80.0, 0, 30], [0, 90.0, 20], [0, 0, 1]], dtype=torch.float64).expand(3, 3, 3).clone(),
    )
    pts = torch.randn(50, 3, dtype=torch.float64) * 0.1
    pts = pts @ cam.c2w[0, :3, :3].T + cam.c2w[0, :3, 3] + 2 * cam.c2w[0, :3, 2]  # in front of camera 0
    a = project(cam[0], pts)
    b = project(cam[0].scaled(s), pts)
    assert torch.allclose(b, s * a, rtol=1e-12, atol=1e-9)
    assert torch.equal(cam.scaled(s).K[:, 2], cam.K[:, 2])
    assert torch.equal(cam.scaled(s).c2w, cam.c2w)


def test_convention_quaternion_order_is_wxyz():
    # 90 degrees about z: q = (cos 45, 0, 0, sin 45) takes x to y.
    q = torch.tensor([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)], dtype=torch.float64)
    R = quat_to_matrix(q)
    assert torch.allclose(
        R @ torch.tensor([1.0, 0, 0], dtype=torch.float64), torch.tensor([0.0, 1, 0], dtype=torch.float64)
    )
    qs = torch.randn(500, 4, dtype=torch.float64)
    qs = qs / qs.norm(dim=-1, keepdim=True)
    qs = torch.where(qs[:, :1] < 0, -qs, qs)
    assert torch.allclose(matrix_to_quat(quat_to_matrix(qs)), qs, atol=1e-12)
    # Near-180-degree rotations (w ~ 0) are the hard case for naive conversions.
    flips = torch.tensor([[1e-9, 1.0, 0, 0], [0, 0.6, 0.8, 0], [1e-7, 0, 0.6, -0.8]], dtype=torch.float64)
    flips = flips / flips.norm(dim=-1, keepdim=True)
    assert torch.allclose(quat_to_matrix(matrix_to_quat(quat_to_matrix(flips))), quat_to_matrix(flips), atol=1e-9)


def test_w2c_is_the_inverse_of_c2w():
    cam = Cameras(random_c2w(4), torch.eye(3, dtype=torch.float64).expand(4, 3, 3).clone())
    assert torch.allclose(cam.w2c @ cam.c2w, torch.eye(4, dtype=torch.float64).expand(4, 4, 4), atol=1e-12)
    assert torch.allclose(cam.centers, cam.c2w[:, :3, 3])


def test_normalized_intrinsics_round_trip():
    Kn = torch.tensor([[[0.9, 0, 0.5], [0, 1.2, 0.45], [0, 0, 1]]], dtype=torch.float64)
    cam = Cameras.from_normalized(random_c2w(1), Kn, width=320, height=240)
    assert cam.K[0, 0, 0] == 0.9 * 320 and cam.K[0, 1, 1] == 1.2 * 240 and cam.K[0, 1, 2] == 0.45 * 240
    assert torch.allclose(cam.normalized_intrinsics(320, 240), Kn)


def test_opengl_converter_round_trips_and_flips_y_z():
    c2w_gl = random_c2w(3, seed=1)
    K = torch.tensor([[50.0, 0, 20], [0, 50.0, 20], [0, 0, 1]], dtype=torch.float64).expand(3, 3, 3).clone()
    cam = Cameras.from_opengl(c2w_gl, K)
    assert torch.allclose(cam.to_opengl(), c2w_gl)
    # OpenGL looks down its -z: the OpenCV forward axis is minus the OpenGL z column.
    assert torch.allclose(cam.c2w[:, :3, 2], -c2w_gl[:, :3, 2])
    assert torch.allclose(cam.c2w[:, :3, 1], -c2w_gl[:, :3, 1])
    assert torch.allclose(cam.c2w[:, :3, 0], c2w_gl[:, :3, 0])


def test_llff_converter_round_trips_and_maps_axes():
    c2w = random_c2w(2, seed=2)
    K = torch.tensor([[400.0, 0, 252], [0, 400.0, 189], [0, 0, 1]], dtype=torch.float64).expand(2, 3, 3).clone()
    cam = Cameras(c2w, K)
    poses = cam.to_llff(width=504, height=378, downscale=8)
    # LLFF columns are (down, right, back) = (y, x, -z) of OpenCV.
    assert torch.allclose(poses[:, :, 0], c2w[:, :3, 1])
    assert torch.allclose(poses[:, :, 1], c2w[:, :3, 0])
    assert torch.allclose(poses[:, :, 2], -c2w[:, :3, 2])
    assert torch.allclose(poses[:, :, 4], torch.tensor([378 * 8, 504 * 8, 3200.0], dtype=torch.float64))
    back = Cameras.from_llff(poses, downscale=8)
    assert torch.allclose(back.c2w, c2w) and torch.allclose(back.K, K)


def test_re10k_row_round_trips():
    c2w = random_c2w(5, seed=3)
    Kn = torch.tensor([[0.85, 0, 0.5], [0, 0.85 * 16 / 9, 0.5], [0, 0, 1]], dtype=torch.float64)
    cam = Cameras.from_normalized(c2w, Kn.expand(5, 3, 3).clone(), 640, 360)
    rows = cam.to_re10k(640, 360)
    assert torch.equal(rows[:, 4:6], torch.zeros(5, 2, dtype=torch.float64))
    # The 3x4 block is world-to-camera, row-major.
    assert torch.allclose(rows[:, 6:].reshape(5, 3, 4), cam.w2c[:, :3])
    back = Cameras.from_re10k(rows, 640, 360)
    assert torch.allclose(back.c2w, c2w) and torch.allclose(back.K, cam.K)


def test_bad_cameras_get_one_clear_error():
    K = torch.eye(3)[None]
    with pytest.raises(SurfSplatInputError, match=r"cameras.c2w: expected shape \[C, 4, 4\]"):
        Cameras(torch.eye(3)[None], K)
    bad = torch.eye(4)[None].clone()
    bad[0, 0, 0] = 2.0
    with pytest.raises(SurfSplatInputError, match=r"cameras.c2w\[0\]: not a rigid"):
        Cameras(bad, K)
    mirror = torch.diag(torch.tensor([1.0, 1.0, -1.0, 1.0]))[None]
    with pytest.raises(SurfSplatInputError, match="det R"):
        Cameras(mirror, K)
    nan = torch.eye(4)[None].clone()
    nan[0, 1, 3] = float("inf")
    with pytest.raises(SurfSplatInputError, match="NaN or inf"):
        Cameras(nan, K)
    with pytest.raises(SurfSplatInputError, match="focal lengths must be positive"):
        Cameras(torch.eye(4)[None], torch.diag(torch.tensor([0.0, 1.0, 1.0]))[None])
    with pytest.raises(SurfSplatInputError, match=r"cameras.K: expected shape \[2, 3, 3\]"):
        Cameras(torch.eye(4).repeat(2, 1, 1), K)
    with pytest.raises(SurfSplatInputError, match="scale"):
        Cameras(torch.eye(4)[None], K).scaled(0)
