"""Both CPU backends against gsplat's own pure-PyTorch reference of 2DGS and 3DGS (`_gsplat_reference`).

Seeded random scenes: 200-2,000 surfels in front of posed cameras, footprints from a fraction of
a pixel to tens of pixels, opacities 0.05-0.99, SH degrees 0 and 3, 64x48 and 128x96, forced
alpha blending off (the reference has none). Conventions aligned through public options:
`lowpass_center_sigma=1` (gsplat centres the surfel low-pass term on its 1-sigma box) and
`ewa_support="alpha"` (no truncation of footprints; the reference lists every Gaussian in every
tile); the cameras' principal points are centred, where gsplat's asymmetric Jacobian limits equal
3DGS's 1.3 tan(fov/2). Opacities stay at most 0.99, so gsplat's alpha cap (0.999) and ours (0.99)
never bind. Differences that remain are by design, named and bounded below:
- surfel depth: gsplat blends each surfel's centre depth, this project the depth of the ray-splat
  intersection (as 2DGS); equal for fronto-parallel surfels, bounded by the surfels' depth extent
  otherwise.
"""

from __future__ import annotations

import pytest
import torch

from surfsplat import Gaussians
from surfsplat.render import CpuRenderSettings, TorchRenderSettings, render

pytest.importorskip("gsplat", reason="gsplat is part of the test extra: pip install -e '.[test]'")
from surfsplat.testing.gsplat_reference import (  # noqa: E402
    ALIGNED,
    facing_normals,
    render_2dgs,
    render_3dgs,
    with_intrinsics,
)
from surfsplat.testing.gsplat_reference import reference_scene as scene  # noqa: E402

SIZES = [(64, 48), (128, 96)]


def ours(g, cams, width, height, mode, backend):
    settings = (CpuRenderSettings if backend == "cpu" else TorchRenderSettings)(**ALIGNED)
    out = render(g, cams, width, height, mode=mode, backend=backend, alpha_threshold=None, settings=settings)
    return out.color, out.alpha, out.depth, out.normal


def tolerance(dtype: torch.dtype) -> float:
    return 1e-10 if dtype == torch.float64 else 1e-4


CASES = [
    # (surfels, seed, SH degree, size)
    (200, 0, 0, SIZES[0]),
    (2000, 1, 3, SIZES[0]),
    (800, 2, 3, SIZES[1]),
]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c[0]}-sh{c[2]}-{c[3][0]}")
def test_surfel_mode_is_gsplats_2dgs(case, backend, dtype):
    n, seed, degree, (W, H) = case
    g, cams = scene(n, seed, dtype, degree)
    cams = with_intrinsics(cams, W, H)
    color, alpha, depth, normal = ours(g, cams, W, H, "surfel", backend)
    ref = render_2dgs(g, cams.w2c[0], cams.K[0], cams.centers[0], W, H)
    ref_color, ref_alpha, ref_center_depth, ref_normal = ref
    assert float(ref_alpha.max()) > 0.9 and float((ref_alpha > 0.01).double().mean()) > 0.3  # a real scene
    tol = tolerance(dtype)
    assert (color - ref_color).abs().max() < tol
    assert (alpha - ref_alpha).abs().max() < tol
    assert (normal - ref_normal).abs().max() < tol
    # Named difference: intersection depth (ours) against blended centre depth (gsplat). Each weight
    # multiplies z_intersection - z_centre, which a surfel's tilt bounds by its 3.3-sigma extent in depth.
    extent = 3.33 * g.scales.double().max() * 1.5
    assert (depth - ref_center_depth).abs().max() < extent * float(ref_alpha.max()) + tol


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_depth_distortion_is_gsplats(backend, dtype):
    """2DGS's depth distortion against gsplat's kernel's (`distloss=True`), computed on gsplat's
    reference pairs and weights: same centre depths, same linear distance and factor 2, so no
    difference is left by design (gsplat's pure-PyTorch reference itself has no distortion)."""
    n, seed, degree, (W, H) = CASES[1]
    g, cams = scene(n, seed, dtype, degree)
    cams = with_intrinsics(cams, W, H)
    settings = (CpuRenderSettings if backend == "cpu" else TorchRenderSettings)(**ALIGNED)
    out = render(g, cams, W, H, backend=backend, alpha_threshold=None, settings=settings, distortion=True)
    reference = render_2dgs(g, cams.w2c[0], cams.K[0], cams.centers[0], W, H, distortion=True)[4]
    assert float(reference.max()) > 0.3
    assert (out.distortion - reference).abs().max() < tolerance(dtype) * float(reference.max())


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_surfel_depth_equals_gsplats_for_fronto_parallel_surfels(backend):
    g, cams = scene(400, 3, torch.float64, 1, fronto=True)
    cams = with_intrinsics(cams, 64, 48)
    _, alpha, depth, _ = ours(g, cams, 64, 48, "surfel", backend)
    _, ref_alpha, ref_depth, _ = render_2dgs(g, cams.w2c[0], cams.K[0], cams.centers[0], 64, 48)
    assert float(ref_alpha.max()) > 0.9
    assert (depth - ref_depth).abs().max() < 1e-10
    assert (alpha - ref_alpha).abs().max() < 1e-10


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c[0]}-sh{c[2]}-{c[3][0]}")
def test_ewa_mode_is_gsplats_3dgs(case, backend, dtype):
    n, seed, degree, (W, H) = case
    g, cams = scene(n, seed + 10, dtype, degree)
    cams = with_intrinsics(cams, W, H)
    color, alpha, depth, normal = ours(g, cams, W, H, "ewa", backend)
    # Our camera-facing world normals, blended by gsplat as extra channels.
    facing = facing_normals(g, cams.centers[0])
    ref_color, ref_alpha, ref_depth, ref_normal = render_3dgs(
        g, cams.w2c[0], cams.K[0], cams.centers[0], W, H, extra=facing
    )
    assert float(ref_alpha.max()) > 0.9 and float((ref_alpha > 0.01).double().mean()) > 0.3
    tol = tolerance(dtype)
    for name, a, b in (("colour", color, ref_color), ("alpha", alpha, ref_alpha), ("depth", depth, ref_depth)):
        scale = max(1.0, float(b.abs().max()))
        assert (a - b).abs().max() < tol * scale, name
    assert (normal - ref_normal).abs().max() < tol


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_gradients_match_gsplats_reference(backend):
    """float64 gradients of a fixed random loss with respect to every Gaussian attribute."""
    g, cams = scene(150, 7, torch.float64, 3)
    W, H = 48, 36
    cams = with_intrinsics(cams, W, H)
    gen = torch.Generator().manual_seed(0)
    weights = [torch.rand(1, c, H, W, generator=gen, dtype=torch.float64) for c in (3, 1)]
    grads = []
    for which in ("ours", "reference"):
        leaves = {
            k: getattr(g, k).detach().clone().requires_grad_(True)
            for k in ("means", "quats", "scales", "opacities", "sh")
        }
        gs = Gaussians(**leaves)
        if which == "ours":
            color, alpha, _, _ = ours(gs, cams, W, H, "surfel", backend)
        else:
            color, alpha, _, _ = render_2dgs(gs, cams.w2c[0], cams.K[0], cams.centers[0], W, H)
        loss = (color * weights[0]).sum() + (alpha * weights[1]).sum()
        loss.backward()
        grads.append({k: v.grad for k, v in leaves.items()})
    for k in grads[0]:
        ref = grads[1][k]
        assert (grads[0][k] - ref).norm() <= 1e-8 * ref.norm() + 1e-12, k


def test_the_reference_is_not_trivially_equal():
    """The comparison can fail: the paper's projected low-pass centre differs from gsplat's."""
    g, cams = scene(2000, 1, torch.float64, 0)
    cams = with_intrinsics(cams, 64, 48)
    settings = TorchRenderSettings(lowpass_center_sigma=None)
    out = render(g, cams, 64, 48, backend="torch", alpha_threshold=None, settings=settings)
    _, ref_alpha, _, _ = render_2dgs(g, cams.w2c[0], cams.K[0], cams.centers[0], 64, 48)
    assert (out.alpha - ref_alpha).abs().max() > 1e-4
