"""The absolute screen gradient (`render(..., absgrad=True)`, AbsGS): the torch reference against a
per-pixel autograd computation, the compiled CPU kernels against the reference, and one pixel's
closed form (the plain gradient's norm)."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from surfsplat import Cameras, Gaussians
from surfsplat.render import CpuRenderSettings, TorchRenderSettings, render
from surfsplat.utils.checks import SurfSplatInputError
from tests.render.test_cpu import camera, scene

PARAMS = ("means", "quats", "scales", "opacities", "sh")


def _two_cameras(width: int, height: int) -> Cameras:
    a = camera(0.8 * width, width, height)
    b = camera(0.9 * width, width, height, offset=(-0.1, 0.05, 0.0))
    return Cameras(torch.cat((a.c2w, b.c2w)), torch.cat((a.K, b.K)))


def _weights(cams: Cameras, width: int, height: int) -> dict[str, Tensor]:
    """Random weights of a loss that reads every map a fit's loss reads."""
    g = torch.Generator().manual_seed(5)
    c = len(cams)
    return {
        k: torch.randn(c, ch, height, width, generator=g, dtype=torch.float64)
        for k, ch in (("color", 3), ("alpha", 1), ("depth", 1), ("normal", 3))
    }


def _loss_maps(out, weights: dict[str, Tensor]) -> Tensor:
    """[C, H, W] each pixel's own share L_p of the loss."""
    return sum((getattr(out, k) * w).sum(1) for k, w in weights.items())


def _per_pixel_reference(g: Gaussians, cams: Cameras, width: int, height: int, settings) -> tuple[Tensor, Tensor]:
    """Per camera and surfel, sum over pixels of |dL_p/dc| and the signed sum dL/dc, by one autograd pass
    per pixel: dL_p/dmu (world) turned into the projected centre's pixel gradient at fixed depth,
    z (R_cw dL_p/dmu)_xy / f (SH degree 0, so the means enter the render through the geometry alone)."""
    means = g.means.detach().clone().requires_grad_(True)
    gs = Gaussians(means, g.quats, g.scales, g.opacities, g.sh)
    out = render(gs, cams, width, height, backend="torch", alpha_threshold=0.001, settings=settings)
    maps = _loss_maps(out, _weights(cams, width, height))
    R_cw = cams.w2c[:, :3, :3]
    z = (g.means @ R_cw.mT + cams.w2c[:, None, :3, 3])[..., 2]  # [C, N]
    f = torch.stack((cams.K[:, 0, 0], cams.K[:, 1, 1]), -1)  # [C, 2]
    absolute = torch.zeros(len(cams), len(means), 2, dtype=torch.float64)
    signed = torch.zeros_like(absolute)
    for c in range(len(cams)):
        for i in range(height):
            for j in range(width):
                (grad,) = torch.autograd.grad(maps[c, i, j], means, retain_graph=True)
                centre = (grad @ R_cw[c].T)[:, :2] * z[c, :, None] / f[c]
                absolute[c] += centre.abs()
                signed[c] += centre
    return absolute, signed


def _absgrad(g: Gaussians, cams: Cameras, width: int, height: int, backend: str, settings) -> Tensor:
    leaves = {k: getattr(g, k).detach().clone().requires_grad_(True) for k in PARAMS}
    out = render(
        Gaussians(**leaves),
        cams,
        width,
        height,
        backend=backend,
        alpha_threshold=0.001,
        settings=settings,
        absgrad=True,
    )
    assert out.absgrad is not None and out.absgrad.shape == (len(cams), len(g), 2)
    _loss_maps(out, _weights(cams, width, height)).sum().backward()
    return out.absgrad.grad


@pytest.mark.parametrize("sigma", [None, 1.0])
def test_torch_absgrad_is_the_sum_of_each_pixels_own_centre_gradient(sigma):
    """Against a brute-force per-pixel autograd computation, with both low-pass centres (the box centre
    of the sigma ellipse, or the projected centre); the surfels are small enough that both the ray-splat
    and the filter branch carry weight."""
    W, H = 12, 10
    g = scene(7, 3, 0)
    cams = _two_cameras(W, H)
    settings = TorchRenderSettings(lowpass_center_sigma=sigma)
    ours = _absgrad(g, cams, W, H, "torch", settings)
    absolute, signed = _per_pixel_reference(g, cams, W, H, settings)
    assert float(absolute.max()) > 1e-2  # the scene is seen
    assert (ours - absolute).abs().max() < 1e-9 * (1 + float(absolute.max()))
    # shares of opposite sign cancel in the plain gradient: the absolute sums are larger somewhere
    assert bool((absolute >= signed.abs() - 1e-12).all())
    assert float((absolute - signed.abs()).max()) > 0.1 * float(absolute.max())


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_cpu_absgrad_equals_the_torch_reference(precision):
    W, H = 23, 17  # tiles cut at the border, several rows of pixels a surfel
    g = scene(24, 8, 1)
    cams = _two_cameras(W, H)
    torch_settings = TorchRenderSettings()
    reference = _absgrad(g, cams, W, H, "torch", torch_settings)
    cpu_settings = CpuRenderSettings(precision=precision)
    ours = _absgrad(g, cams, W, H, "cpu", cpu_settings)
    assert float(reference.max()) > 1e-2
    tolerance = 1e-9 if precision == "float64" else 1e-4
    assert (ours - reference).abs().max() < tolerance * (1 + float(reference.max()))


def test_with_one_surfel_and_one_pixel_it_is_the_plain_gradients_norm():
    """One pixel has one share: the absolute sums are |dL/dc| of the plain gradient, read from the means
    as the densification reads it (z (R_cw dL/dmu)_xy / f)."""
    cams = camera(1.0, 1, 1)
    g = Gaussians(
        means=torch.tensor([[0.1, -0.05, 0.6]], dtype=torch.float64),
        quats=torch.tensor([[0.9, 0.2, -0.3, 0.1]], dtype=torch.float64),
        scales=torch.tensor([[0.3, 0.2]], dtype=torch.float64),
        opacities=torch.tensor([0.7], dtype=torch.float64),
        sh=torch.tensor([[[0.3], [-0.2], [0.5]]], dtype=torch.float64),
    )
    for backend, settings in (("torch", TorchRenderSettings()), ("cpu", CpuRenderSettings(precision="float64"))):
        means = g.means.clone().requires_grad_(True)
        out = render(
            Gaussians(means, g.quats, g.scales, g.opacities, g.sh),
            cams,
            1,
            1,
            backend=backend,
            settings=settings,
            alpha_threshold=None,
            absgrad=True,
        )
        (out.color * torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)[None, :, None, None]).sum().backward()
        R_cw = cams.w2c[0, :3, :3]
        z = float((g.means[0] @ R_cw.T + cams.w2c[0, :3, 3])[2])
        plain = (means.grad[0] @ R_cw.T)[:2] * z / cams.K[0, [0, 1], [0, 1]]
        assert float(plain.abs().min()) > 1e-4, backend
        assert torch.allclose(out.absgrad.grad[0, 0], plain.abs(), rtol=1e-10, atol=0), backend


def test_absgrad_is_refused_where_it_is_not_computed():
    g = scene(3, 0, 0)
    cams = camera(10.0, 8, 8)
    with pytest.raises(SurfSplatInputError, match="surfel"):
        render(g, cams, 8, 8, mode="ewa", backend="torch", absgrad=True)
    with pytest.raises(SurfSplatInputError, match="distortion"):
        render(g, cams, 8, 8, backend="torch", absgrad=True, distortion=True)
    with pytest.raises(SurfSplatInputError, match="absgrad"):
        render(g, cams, 8, 8, backend="torch", absgrad="yes")
    assert render(g, cams, 8, 8, backend="cpu").absgrad is None
