"""The antialiasing filter (`render(..., antialiased=True)`, `surfsplat.render.antialias`) against closed forms
and gsplat's antialiased mode.

- The surfel compensation's area I (the integral of the larger of two concentric Gaussians) against
  numerical quadrature, in its three cases.
- A fronto-parallel surfel (its homography is affine, so the closed form is exact up to pixel sampling)
  keeps its integrated alpha at x1, x1/2 and x1/4: sum of alpha = I (o c - 1/255) exactly, and within a few
  percent of its true integrated opacity o 2 pi s_u s_v where the 1/255 cut is small; without the filter
  it covers the low-pass's 2 pi (1/2) px^2 at full opacity whatever its size.
- Surfels at least as large as the filter render bit for bit as without it.
- "ewa": gsplat 1.5.3's `rasterize_mode="antialiased"` (its pure-PyTorch reference), forward to 1e-4
  (float32) / 1e-10 (float64) and float64 gradients, on the torch and compiled CPU backends.
- "surfel": gsplat's 2DGS given the compensated opacities, forward and gradients, on both backends; the
  gsplat backend (gsplat's references standing in for its CUDA kernels) against the torch backend.
- float64 gradcheck of both compensations.
"""

from __future__ import annotations

import math

import pytest
import torch

from surfsplat import Cameras, Gaussians
from surfsplat.render import CpuRenderSettings, TorchRenderSettings, render
from surfsplat.render.antialias import (
    SURFEL_FILTER_VARIANCE,
    compensations,
    ewa_compensation,
    max_of_gaussians_area,
    surfel_compensation,
)
from surfsplat.render.types import ALPHA_MIN

D = torch.float64
S = SURFEL_FILTER_VARIANCE
BACKENDS = ["torch", "cpu"]


@pytest.mark.parametrize(
    ("l1", "l2"),
    [(0.1, 0.05), (0.3, 0.3), (2.0, 0.1), (0.8, 0.3), (0.6, 0.49), (3.0, 1.0), (40.0, 0.01)],
)
def test_area_of_the_larger_of_two_gaussians_is_the_integral(l1, l2):
    """I = integral of exp(-0.5 min(x^2 / l1 + y^2 / l2, (x^2 + y^2) / s)) over the plane, by quadrature."""
    x = torch.linspace(-40, 40, 4001, dtype=D)
    X, Y = torch.meshgrid(x, x, indexing="ij")
    q = torch.minimum(X**2 / l1 + Y**2 / l2, (X**2 + Y**2) / S)
    numeric = float(torch.exp(-0.5 * q).sum() * (x[1] - x[0]) ** 2)
    l1t, l2t = torch.tensor(l1, dtype=D), torch.tensor(l2, dtype=D)
    closed = float(max_of_gaussians_area(l1t, l2t, (l1t * l2t).sqrt(), S))
    assert closed == pytest.approx(numeric, rel=2e-5)


COPIES = 10  # per axis: copies of the surfel at stratified sub-pixel offsets, so the pixel sums average to the integral
SPACING = 32.4  # px at x1 between copies: 0.1 px more than a multiple of 4 at x1/4 (offsets i / 10 there)


def surfel_copies(sigma_u: float, sigma_v: float, opacity: float, f: float = 100.0):
    """COPIES^2 fronto-parallel surfels of screen sigmas (sigma_u, sigma_v) px at x1, 2 units ahead of a camera of
    focal f, far apart (no overlap) and at stratified sub-pixel offsets at every scale used here."""
    z, n = 2.0, COPIES * COPIES
    grid = torch.stack(torch.meshgrid(torch.arange(COPIES), torch.arange(COPIES), indexing="ij"), -1).reshape(-1, 2)
    width = round(COPIES * SPACING + 16)
    pixels = 16 + SPACING * grid.to(D)  # [n, 2] x1 pixel positions of the centres
    xy = (pixels - width / 2) * z / f
    g = Gaussians(
        means=torch.cat((xy, torch.full((n, 1), z, dtype=D)), -1),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=D).expand(n, 4),
        scales=torch.tensor([[sigma_u * z / f, sigma_v * z / f]], dtype=D).expand(n, 2),
        opacities=torch.full((n,), opacity, dtype=D),
        sh=torch.zeros(n, 3, 1, dtype=D),
    )
    K = torch.tensor([[[f, 0, width / 2], [0, f, width / 2], [0, 0, 1]]], dtype=D)
    return g, Cameras(torch.eye(4, dtype=D)[None], K), width


def integrated_alpha(g, cams, width, scale, backend, antialiased):
    """The sum of alpha over the pixels per surfel (pixels of that scale)."""
    size = round(width * scale)
    out = render(g, cams.scaled(scale), size, size, backend=backend, alpha_threshold=None, antialiased=antialiased)
    return float(out.alpha.sum()) / len(g)


def predicted(sigma_u: float, sigma_v: float, opacity: float) -> float:
    """The closed form: the compensated peak P = o c, the cut at 1/255 removing t / P of each radial profile."""
    l1, l2 = torch.tensor(max(sigma_u, sigma_v) ** 2, dtype=D), torch.tensor(min(sigma_u, sigma_v) ** 2, dtype=D)
    area = float(max_of_gaussians_area(l1, l2, (l1 * l2).sqrt(), S))
    c = 2 * math.pi * sigma_u * sigma_v / area
    return max(0.0, area * (opacity * c - ALPHA_MIN))


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("sigma", [(1.2, 1.2), (0.2, 0.3), (1.4, 2.4)], ids=["round", "sub-pixel", "ellipse"])
def test_a_fronto_parallel_surfel_keeps_its_integrated_alpha_at_every_scale(backend, sigma):
    o = 0.95
    g, cams, width = surfel_copies(*sigma, o)
    for scale in (1.0, 0.5, 0.25):
        su, sv = sigma[0] * scale, sigma[1] * scale
        got = integrated_alpha(g, cams, width, scale, backend, True)
        assert got == pytest.approx(predicted(su, sv, o), rel=1e-2), scale  # the closed form, cut included
        truth = o * 2 * math.pi * su * sv
        if o * su * sv / max(su * sv, S) > 10 * ALPHA_MIN / 0.25:  # the cut removes under 2.5 %
            assert got == pytest.approx(truth, rel=3e-2), scale
        plain = integrated_alpha(g, cams, width, scale, backend, False)
        if max(su, sv) ** 2 < S:  # without the filter: the low-pass's area at full opacity
            assert plain == pytest.approx(2 * math.pi * S * (o - ALPHA_MIN), rel=1e-2)
            assert plain > 1.3 * truth


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_surfel_far_smaller_than_a_pixel_keeps_its_integrated_opacity(backend):
    """sigma 0.25 px at x1 (0.0625 px at x1/4): the sum of alpha is the closed form I (o c - 1/255), which
    is within a few percent of o 2 pi sigma^2 while the compensated peak is well above the cut."""
    o = 0.98
    g, cams, width = surfel_copies(0.25, 0.25, o)
    for scale in (1.0, 0.5, 0.25):
        s = 0.25 * scale
        got = integrated_alpha(g, cams, width, scale, backend, True)
        assert got == pytest.approx(predicted(s, s, o), rel=1e-2, abs=1e-4), scale
        if o * s * s / S > 10 * ALPHA_MIN / 0.25:
            assert got == pytest.approx(o * 2 * math.pi * s * s, rel=3e-2), scale


@pytest.mark.parametrize("backend", BACKENDS)
def test_surfels_larger_than_the_filter_render_bit_for_bit_as_without_it(backend):
    gen = torch.Generator().manual_seed(3)
    n = 40
    means = torch.cat((torch.rand(n, 2, generator=gen, dtype=D) - 0.5, torch.full((n, 1), 3.0, dtype=D)), -1)
    angle = torch.rand(n, generator=gen, dtype=D) * math.pi
    quats = torch.stack((torch.cos(angle / 2), 0 * angle, 0 * angle, torch.sin(angle / 2)), -1)  # fronto-parallel
    scales = 0.03 + 0.05 * torch.rand(n, 2, generator=gen, dtype=D)  # at least 1 px (f = 100 at z = 3)
    g = Gaussians(
        means=means,
        quats=quats,
        scales=scales,
        opacities=torch.full((n,), 0.7, dtype=D),
        sh=torch.zeros(n, 3, 1, dtype=D),
    )
    cams = Cameras(torch.eye(4, dtype=D)[None], torch.tensor([[[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]]], dtype=D))
    assert bool((compensations(g, cams, 64, 64, "surfel", None) == 1).all())
    on = render(g, cams, 64, 64, backend=backend, antialiased=True)
    off = render(g, cams, 64, 64, backend=backend)
    assert float(off.alpha.max()) > 0.5
    for name in ("color", "alpha", "depth", "normal"):
        assert torch.equal(getattr(on, name), getattr(off, name)), name
    # the same surfels four times smaller on screen (x1/4): now the filter acts
    small = render(g, cams.scaled(0.25), 16, 16, backend=backend, antialiased=True)
    small_off = render(g, cams.scaled(0.25), 16, 16, backend=backend)
    assert float((small.alpha - small_off.alpha).abs().max()) > 0.05


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_sparse_scene_of_small_surfels_keeps_its_mean_alpha_when_rendered_smaller(backend):
    """Integrated alpha kept per surfel: the mean alpha at x1/4 is the x1 mean alpha (no overlaps)."""
    gen = torch.Generator().manual_seed(5)
    n = 30
    grid = torch.stack(torch.meshgrid(torch.arange(6), torch.arange(5), indexing="ij"), -1).reshape(-1, 2)
    xy = (grid.to(D) - torch.tensor([2.5, 2.0], dtype=D)) * 0.3 + 0.02 * torch.rand(n, 2, generator=gen, dtype=D)
    means = torch.cat((xy, torch.full((n, 1), 3.0, dtype=D)), -1)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=D).expand(n, 4)
    scales = (0.8 + 0.8 * torch.rand(n, 2, generator=gen, dtype=D)) * 3.0 / 200.0  # 0.8-1.6 px at x1
    g = Gaussians(
        means=means,
        quats=quats,
        scales=scales,
        opacities=torch.full((n,), 0.9, dtype=D),
        sh=torch.zeros(n, 3, 1, dtype=D),
    )
    cams = Cameras(torch.eye(4, dtype=D)[None], torch.tensor([[[200.0, 0, 128], [0, 200.0, 128], [0, 0, 1]]], dtype=D))
    x1 = float(render(g, cams, 256, 256, backend=backend, alpha_threshold=None).alpha.mean())
    quarter = cams.scaled(0.25)
    aa = float(render(g, quarter, 64, 64, backend=backend, alpha_threshold=None, antialiased=True).alpha.mean())
    plain = float(render(g, quarter, 64, 64, backend=backend, alpha_threshold=None).alpha.mean())
    assert aa == pytest.approx(x1, rel=0.05)
    assert plain > 1.5 * x1


# --- gsplat's antialiased mode ---------------------------------------------------------------------------


@pytest.fixture
def gsplat_reference():
    pytest.importorskip("gsplat", reason="gsplat is part of the test extra: pip install -e '.[test]'")
    from surfsplat.testing import gsplat_reference as ref

    return ref


def ours(g, cams, width, height, mode, backend, aligned):
    settings = (CpuRenderSettings if backend == "cpu" else TorchRenderSettings)(**aligned)
    return render(
        g, cams, width, height, mode=mode, backend=backend, alpha_threshold=None, settings=settings, antialiased=True
    )


def leaves(g: Gaussians) -> dict:
    return {
        k: getattr(g, k).detach().clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "sh")
    }


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_ewa_antialiased_is_gsplats_antialiased_mode(gsplat_reference, backend, dtype):
    ref = gsplat_reference
    W, H = 64, 48
    g, cams = ref.reference_scene(1200, 21, dtype, 2)
    cams = ref.with_intrinsics(cams, W, H)
    out = ours(g, cams, W, H, "ewa", backend, ref.ALIGNED)
    facing = ref.facing_normals(g, cams.centers[0])
    color, alpha, depth, normal = ref.render_3dgs(
        g, cams.w2c[0], cams.K[0], cams.centers[0], W, H, extra=facing, antialiased=True
    )
    plain = ref.render_3dgs(g, cams.w2c[0], cams.K[0], cams.centers[0], W, H, extra=facing)[1]
    assert float((alpha - plain).abs().max()) > 0.05  # the compensation matters in this scene
    tol = 1e-10 if dtype == torch.float64 else 1e-4
    for name, a, b in (("colour", out.color, color), ("alpha", out.alpha, alpha), ("depth", out.depth, depth)):
        assert (a - b).abs().max() < tol * max(1.0, float(b.abs().max())), name
    assert (out.normal - normal).abs().max() < tol


@pytest.mark.parametrize("mode", ["ewa", "surfel"])
@pytest.mark.parametrize("backend", BACKENDS)
def test_antialiased_gradients_match_gsplats_reference(gsplat_reference, backend, mode):
    """float64 gradients of a fixed random loss with respect to every attribute; in "surfel" mode gsplat's
    2DGS is handed the compensated opacities (computed by autograd through `surfel_compensation`)."""
    ref = gsplat_reference
    W, H = 48, 36
    g, cams = ref.reference_scene(150, 7, D, 2)
    cams = ref.with_intrinsics(cams, W, H)
    gen = torch.Generator().manual_seed(0)
    weights = [torch.rand(1, c, H, W, generator=gen, dtype=D) for c in (3, 1)]
    grads = []
    for which in ("ours", "reference"):
        free = leaves(g)
        gs = Gaussians(**free)
        if which == "ours":
            out = ours(gs, cams, W, H, mode, backend, ref.ALIGNED)
            color, alpha = out.color, out.alpha
        elif mode == "ewa":
            color, alpha, _, _ = ref.render_3dgs(gs, cams.w2c[0], cams.K[0], cams.centers[0], W, H, antialiased=True)
        else:
            factors = compensations(gs, cams, W, H, "surfel", None)[0]
            color, alpha, _, _ = ref.render_2dgs(
                gs, cams.w2c[0], cams.K[0], cams.centers[0], W, H, opacities=gs.opacities * factors
            )
        ((color * weights[0]).sum() + (alpha * weights[1]).sum()).backward()
        grads.append({k: v.grad for k, v in free.items()})
    for k in grads[0]:
        assert (grads[0][k] - grads[1][k]).norm() <= 1e-8 * grads[1][k].norm() + 1e-12, k


@pytest.mark.parametrize("backend", BACKENDS)
def test_surfel_antialiased_is_gsplats_2dgs_with_the_compensated_opacities(gsplat_reference, backend):
    ref = gsplat_reference
    W, H = 64, 48
    g, cams = ref.reference_scene(1500, 22, torch.float32, 1)
    cams = ref.with_intrinsics(cams, W, H)
    out = ours(g, cams, W, H, "surfel", backend, ref.ALIGNED)
    factors = compensations(g, cams, W, H, "surfel", None)[0].float()
    assert float((factors < 0.9).float().mean()) > 0.1  # sub-pixel surfels are in the scene
    color, alpha, _, normal = ref.render_2dgs(
        g, cams.w2c[0], cams.K[0], cams.centers[0], W, H, opacities=g.opacities * factors
    )
    assert (out.color - color).abs().max() < 1e-4
    assert (out.alpha - alpha).abs().max() < 1e-4
    assert (out.normal - normal).abs().max() < 1e-4


@pytest.mark.parametrize("mode", ["surfel", "ewa"])
def test_the_gsplat_backend_renders_the_filter_as_the_torch_backend(gsplat_reference, mode):
    from surfsplat.render.gsplat_backend import render_gsplat

    ref = gsplat_reference
    W, H = 64, 48
    g, cams = ref.reference_scene(600, 4, torch.float32, 2)
    cams = ref.with_intrinsics(cams, W, H)
    settings = TorchRenderSettings()
    gen = torch.Generator().manual_seed(1)
    weights = [torch.rand(1, c, H, W, generator=gen) for c in (3, 1)]
    results = []
    with ref.cpu_kernels():
        for backend in ("gsplat", "torch"):
            free = leaves(g)
            gs = Gaussians(**free)
            if backend == "gsplat":
                factors = compensations(gs, cams, W, H, mode, settings.ewa_jacobian_clamp).float()
                color, alpha = render_gsplat(gs, cams, W, H, mode, settings, factors=factors)[:2]
            else:
                out = render(gs, cams, W, H, mode=mode, backend="torch", alpha_threshold=None, antialiased=True)
                color, alpha = out.color, out.alpha
            ((color * weights[0]).sum() + (alpha * weights[1]).sum()).backward()
            results.append(((color, alpha), {k: v.grad for k, v in free.items()}))
    (maps_a, grads_a), (maps_b, grads_b) = results
    for a, b in zip(maps_a, maps_b):
        assert (a - b).abs().max() < 1e-4
    for k in grads_a:
        assert (grads_a[k] - grads_b[k]).norm() <= 1e-3 * grads_b[k].norm() + 1e-6, k


# --- the compensations themselves ----------------------------------------------------------------------------


def test_surfel_compensation_gradcheck_in_every_case():
    """T of surfels larger than the filter, smaller, mixed (a needle), isotropic and edge-on-ish."""
    f = 100.0
    K = torch.tensor([[f, 0, 32], [0, f, 24], [0, 0, 1]], dtype=D)
    rows = []
    for su, sv, tilt in (
        (0.03, 0.02, 0.3),
        (0.002, 0.003, 0.2),
        (0.05, 0.002, 0.5),
        (0.004, 0.004, 0.0),
        (0.02, 0.01, 1.45),
    ):
        c, s = math.cos(tilt), math.sin(tilt)
        tu = torch.tensor([su, 0, 0], dtype=D)
        tv = torch.tensor([0, sv * c, sv * s], dtype=D)
        mu = torch.tensor([0.1, -0.05, 2.0], dtype=D)
        rows.append(K @ torch.stack((tu, tv, mu), -1))
    T = torch.stack(rows).requires_grad_(True)
    values = surfel_compensation(T).detach()
    assert float(values[0]) == 1.0 and 0 < float(values[1]) < 0.1 and 0 < float(values[2]) < 1
    assert torch.autograd.gradcheck(surfel_compensation, (T,), eps=1e-7, atol=1e-6)


def test_ewa_compensation_is_gsplats_formula_and_gradcheck():
    gen = torch.Generator().manual_seed(2)
    A = torch.randn(20, 2, 2, generator=gen, dtype=D) * torch.linspace(0.05, 3, 20, dtype=D)[:, None, None]
    cov = A @ A.mT + 0.3 * torch.eye(2, dtype=D)
    a, b, c = (cov[:, 0, 0].clone().requires_grad_(True), cov[:, 0, 1].clone().requires_grad_(True),
               cov[:, 1, 1].clone().requires_grad_(True))  # fmt: skip
    det_orig = torch.linalg.det(A @ A.mT)
    expected = torch.sqrt(torch.clamp(det_orig / torch.linalg.det(cov).clamp(min=1e-10), min=0.0))
    assert torch.allclose(ewa_compensation(a, b, c), expected, atol=1e-12)
    assert torch.autograd.gradcheck(ewa_compensation, (a, b, c))


def test_antialiased_must_be_a_bool():
    from surfsplat.utils.checks import SurfSplatInputError

    g, cams, width = surfel_copies(1.0, 1.0, 0.5)
    with pytest.raises(SurfSplatInputError, match="antialiased"):
        render(g, cams, width, width, antialiased="yes")
