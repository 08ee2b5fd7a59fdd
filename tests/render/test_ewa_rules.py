"""The "ewa" mode is diff-gaussian-rasterization's function: each of its rules against a value computed
by hand (single Gaussians, both CPU backends, float64, no forced alpha blending)."""

from __future__ import annotations

import math

import pytest
import torch

from surfsplat import Cameras, Gaussians
from surfsplat.render import CpuRenderSettings, TorchRenderSettings, render

D = torch.float64


def _alpha(g: Gaussians, W: int, H: int, backend: str, **conventions) -> torch.Tensor:
    settings = (CpuRenderSettings if backend == "cpu" else TorchRenderSettings)(**conventions)
    cams = Cameras(
        torch.eye(4, dtype=D)[None], torch.tensor([[[50.0, 0, W / 2], [0, 50.0, H / 2], [0, 0, 1]]], dtype=D)
    )
    return render(g, cams, W, H, mode="ewa", backend=backend, alpha_threshold=None, settings=settings).alpha[0, 0]


def _one(mean, quat, scales, opacity) -> Gaussians:
    return Gaussians(
        means=torch.tensor([mean], dtype=D),
        quats=torch.tensor([quat], dtype=D),
        scales=torch.tensor([scales], dtype=D),
        opacities=torch.tensor([opacity], dtype=D),
        sh=torch.zeros(1, 3, 1, dtype=D),
    )


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_dilation_cap_and_threshold(backend):
    tiny = (1e-7, 1e-7)  # the 2D covariance is the 0.3 px^2 dilation alone
    g = _one([0.0, 0.0, 2.0], [1.0, 0, 0, 0], tiny, 0.5)
    # pixel (32, 32) is (0.5, 0.5) from the centre (32, 32): alpha = 0.5 exp(-0.5 * 0.5 / 0.3)
    assert float(_alpha(g, 64, 64, backend)[32, 32]) == pytest.approx(0.5 * math.exp(-0.5 * 0.5 / 0.3), rel=1e-9)
    big = _one([0.0, 0.0, 2.0], [1.0, 0, 0, 0], (0.5, 0.5), 0.999)
    assert float(_alpha(big, 64, 64, backend)[32, 32]) == pytest.approx(0.99, abs=1e-12)  # the 0.99 cap
    g_at = math.exp(-0.5 * 0.5 / 0.3)
    below = _one([0.0, 0.0, 2.0], [1.0, 0, 0, 0], tiny, 0.999 / 255 / g_at)
    above = _one([0.0, 0.0, 2.0], [1.0, 0, 0, 0], tiny, 1.001 / 255 / g_at)
    assert float(_alpha(below, 64, 64, backend)[32, 32]) == 0.0  # under 1/255: exactly nothing
    assert float(_alpha(above, 64, 64, backend)[32, 32]) == pytest.approx(1.001 / 255, rel=1e-9)


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_jacobian_clamp(backend):
    """A surfel tilted 45 degrees about y, off-screen at x/z = 1.28 (tan(fov/2) = 64 / 100 = 0.64).

    With the camera at the origin and y = 0, the 2D covariance is diagonal: a = (fx s / z)^2
    (cos t + x' sin t)^2 + 0.3 and c = (fy s / z)^2 + 0.3, x' = x/z clamped to 1.3 * 0.64 = 0.832.
    """
    s, z, t = 0.6, 2.0, math.radians(45)
    g = _one([1.28 * z, 0.0, z], [math.cos(t / 2), 0.0, math.sin(t / 2), 0.0], (s, s), 0.9)

    def expected(x):
        a = (50 * s / z) ** 2 * (math.cos(t) + x * math.sin(t)) ** 2 + 0.3
        c = (50 * s / z) ** 2 + 0.3
        dx, dy = 63.5 - (50 * 1.28 + 32), 32.5 - 32
        return 0.9 * math.exp(-0.5 * (dx * dx / a + dy * dy / c))

    assert float(_alpha(g, 64, 64, backend)[32, 63]) == pytest.approx(expected(0.832), rel=1e-9)
    unclamped = float(_alpha(g, 64, 64, backend, ewa_jacobian_clamp=None)[32, 63])
    assert unclamped == pytest.approx(expected(1.28), rel=1e-9)


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_radius_and_tile_support(backend):
    """Isotropic 2D covariance a = 100 px^2: lambda_max = 100 + sqrt(0.1), radius ceil(3 sqrt(.)) = 31.

    Centre at 47.2 in the release's pixel frame (47.7 here): tiles from floor((47.2 - 31) / 16) = 1,
    so pixel 15 is cut although its alpha 0.99 exp(-0.5 * 32.2^2 / 100) = 0.0056 exceeds 1/255.
    """
    z = 2.0
    s = z * math.sqrt(100 - 0.3) / 50
    g = _one([(47.7 - 48) / 50 * z, 0.0, z], [1.0, 0, 0, 0], (s, s), 0.99)
    release = _alpha(g, 96, 96, backend)
    exact = _alpha(g, 96, 96, backend, ewa_support="alpha")
    row = 47  # pixel centre 47.5, half a pixel above the centre row 48
    dy = 47.5 - 48.0

    def value(col):
        dx = col + 0.5 - 47.7
        return 0.99 * math.exp(-0.5 * (dx * dx + dy * dy) / 100)

    assert value(15) > 1 / 255
    assert float(release[row, 15]) == 0.0
    assert float(exact[row, 15]) == pytest.approx(value(15), rel=1e-9)
    assert float(release[row, 16]) == pytest.approx(value(16), rel=1e-9)
