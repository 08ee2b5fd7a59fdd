"""The compiled CPU backend against the torch reference, its brute-force twin and closed forms."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from surfsplat import Cameras, Gaussians
from surfsplat.data.synthetic.surfel_scene import frame_from_normal
from surfsplat.geometry.rotations import matrix_to_quat
from surfsplat.render import CpuRenderSettings, TorchRenderSettings, normalize_by_alpha, render, resolve_backend
from surfsplat.render.types import LOWPASS_RHO_SCALE
from surfsplat.utils.checks import SurfSplatInputError
from tests.helpers.reference_render import reference_render

numba = pytest.importorskip("numba", reason="the compiled CPU backend needs numba")
from surfsplat.render.cpu import backend, kernels  # noqa: E402
from surfsplat.render.cpu.backend import contributing_pairs, normalize_cpu, render_cpu  # noqa: E402

PARAMS = ("means", "quats", "scales", "opacities", "sh")


def camera(f: float, width: int, height: int, offset=(0.05, -0.03, 0.1), dtype=torch.float64) -> Cameras:
    c2w = torch.eye(4, dtype=dtype)
    c2w[:3, 3] = torch.tensor(offset, dtype=dtype)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)
    return Cameras(c2w[None], K[None])


def scene(
    n: int, seed: int, sh_degree: int, behind: int = 0, edge_on: int = 0, tilt: float = 0.0, dtype=torch.float64
) -> Gaussians:
    """Random surfels in front of the camera; `behind` of them behind it, `edge_on` seen edge-on.

    With tilt = 0 the edge-on normals are exactly perpendicular to the ray from the camera centre,
    so which way they face is decided by rounding; a tilt (radians) turns them to face the camera.
    """
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    means = torch.randn(n, 3, generator=g, dtype=f64) * torch.tensor([0.5, 0.4, 0.3], dtype=f64)
    means[:, 2] += 2.5
    means[:behind, 2] = -means[:behind, 2]
    quats = torch.randn(n, 4, generator=g, dtype=f64)
    if edge_on:
        # Normal perpendicular to the ray from the camera centre (0.05, -0.03, 0.1) through the mean.
        ray = F.normalize(means[behind : behind + edge_on] - torch.tensor([0.05, -0.03, 0.1], dtype=f64), dim=-1)
        side = F.normalize(torch.linalg.cross(ray, torch.randn(edge_on, 3, generator=g, dtype=f64)), dim=-1)
        side = F.normalize(side - math.tan(tilt) * ray, dim=-1)
        quats[behind : behind + edge_on] = matrix_to_quat(frame_from_normal(side))
    return Gaussians(
        means=means.to(dtype),
        quats=quats.to(dtype),
        scales=(torch.rand(n, 2, generator=g, dtype=f64) * 0.12 + 0.02).to(dtype),
        opacities=(torch.rand(n, generator=g, dtype=f64) * 0.9 + 0.05).to(dtype),
        sh=(torch.randn(n, 3, (sh_degree + 1) ** 2, generator=g, dtype=f64) * 0.4).to(dtype),
    )


def render_and_grads(
    g: Gaussians,
    cams: Cameras,
    width: int,
    height: int,
    mode: str,
    backend: str,
    weights: list[torch.Tensor],
    threshold: float | None = 0.001,
    covariances=None,
):
    """Outputs and gradients of sum(weights * outputs) with respect to every Gaussian parameter."""
    params = {k: getattr(g, k).detach().clone().requires_grad_(True) for k in PARAMS}
    cov = None if covariances is None else covariances.detach().clone().requires_grad_(True)
    gs = Gaussians(**params, explicit_covariances=cov)
    out = render(
        gs, cams, width, height, mode=mode, backend=backend, alpha_threshold=threshold, background=[0.1, 0.2, 0.3]
    )
    maps = (out.color, out.alpha, out.depth, out.normal)
    sum(((m * w).sum() for m, w in zip(maps, weights)), torch.zeros((), dtype=g.means.dtype)).backward()
    grads = {k: p.grad for k, p in params.items()}
    if cov is not None:
        grads["covariances"] = cov.grad
    return maps, grads


def random_weights(cams: Cameras, width: int, height: int, dtype) -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(7)
    C = len(cams)
    return [torch.randn(C, ch, height, width, generator=gen, dtype=dtype) for ch in (3, 1, 1, 3)]


def assert_close_relative(ours: torch.Tensor, ref: torch.Tensor, rel: float, what: str) -> None:
    ours, ref = ours.detach(), ref.detach()
    scale = float(ref.abs().max())
    err = float((ours - ref).abs().max())
    assert err <= rel * max(scale, 1e-12), f"{what}: max error {err:.3g} vs scale {scale:.3g}"


# --------------------------------------------------------------------------- against the torch reference


@pytest.mark.parametrize("mode", ["surfel", "ewa"])
@pytest.mark.parametrize(
    ("seed", "size", "f"),
    [(0, (37, 29), 30.0), (1, (64, 48), 45.0), (2, (23, 41), 20.0), (3, (50, 50), 70.0)],
)
def test_forward_and_gradients_match_torch_reference(mode, seed, size, f):
    # Scenes include surfels behind the camera and surfels seen exactly edge-on; SH degree = seed.
    W, H = size
    g = scene(70, seed, sh_degree=seed, behind=5, edge_on=8)
    cams = camera(f, W, H)
    weights = random_weights(cams, W, H, torch.float64)
    ours, g_ours = render_and_grads(g, cams, W, H, mode, "cpu", weights)
    ref, g_ref = render_and_grads(g, cams, W, H, mode, "torch", weights)
    assert float(ref[1].detach().max()) > 0.5  # the scene covers the view
    for name, a, b in zip(("color", "alpha", "depth", "normal"), ours, ref):
        assert_close_relative(a, b, 1e-9, name)
    for name in PARAMS:
        assert float(g_ref[name].abs().max()) > 0, name  # every gradient is exercised
        assert_close_relative(g_ours[name], g_ref[name], 1e-5, f"d/d{name}")
    # Culled Gaussians (behind the camera) get exactly zero gradient, as in the reference.
    assert torch.equal(g_ours["means"][:5], g_ref["means"][:5])


def test_several_cameras_and_explicit_covariances_match_torch_reference():
    W, H = 31, 27
    g = scene(50, 11, sh_degree=1, behind=2, edge_on=3)
    c2w = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    t = 0.1  # the second camera turned about y
    c2w[1, :3, :3] = torch.tensor(
        [[math.cos(t), 0.0, math.sin(t)], [0.0, 1.0, 0.0], [-math.sin(t), 0.0, math.cos(t)]], dtype=torch.float64
    )
    c2w[1, :3, 3] = torch.tensor([0.2, 0.05, -0.1], dtype=torch.float64)
    K = torch.tensor([[28.0, 0.7, 15.0], [0.0, 26.0, 14.0], [0.0, 0.0, 1.0]], dtype=torch.float64)  # with skew
    cams = Cameras(c2w, K.expand(2, 3, 3).clone())
    # A generic (non-thin) covariance per Gaussian, as the release-compatible adapter passes.
    A = torch.randn(50, 3, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 0.05
    cov = A @ A.transpose(1, 2) + 1e-4 * torch.eye(3, dtype=torch.float64)
    weights = random_weights(cams, W, H, torch.float64)
    ours, g_ours = render_and_grads(g, cams, W, H, "ewa", "cpu", weights, covariances=cov)
    ref, g_ref = render_and_grads(g, cams, W, H, "ewa", "torch", weights, covariances=cov)
    for name, a, b in zip(("color", "alpha", "depth", "normal"), ours, ref):
        assert_close_relative(a, b, 1e-9, name)
    for name in (*PARAMS, "covariances"):
        if name == "scales":
            assert g_ours[name] is None or float(g_ours[name].abs().max()) == 0  # unused with explicit covariances
            continue
        assert_close_relative(g_ours[name], g_ref[name], 1e-5, f"d/d{name}")


@pytest.mark.parametrize("mode", ["surfel", "ewa"])
def test_float32_agrees_with_reference_and_with_float64(mode):
    W, H = 40, 32
    g64 = scene(60, 4, sh_degree=2, behind=3)
    g32 = Gaussians(**{k: getattr(g64, k).float() for k in PARAMS})
    cams64 = camera(35.0, W, H)
    cams32 = camera(35.0, W, H, dtype=torch.float32)
    ours = render(g32, cams32, W, H, mode=mode, backend="cpu")  # "auto": float32 compositing
    wide = render(g32, cams32, W, H, mode=mode, backend="cpu", settings=CpuRenderSettings(precision="float64"))
    ref = render(g32, cams32, W, H, mode=mode, backend="torch")
    exact = render(g64, cams64, W, H, mode=mode, backend="cpu")
    assert ours.color.dtype == wide.color.dtype == torch.float32
    for name in ("color", "alpha", "depth", "normal"):
        a, w, b, c = (getattr(o, name) for o in (ours, wide, ref, exact))
        assert_close_relative(a.double(), b.double(), 2e-5, name)
        assert_close_relative(w.double(), b.double(), 2e-5, name)
        # Compositing in float64 from the float32 inputs: closer to the float64 result than the
        # float32 reference is.
        assert float((w.double() - c).abs().max()) <= float((b.double() - c).abs().max()) + 1e-6, name


# --------------------------------------------------------------------------- float32 compositing


def _precision_pair(g, cams, W, H, mode, weights, threshold=0.001):
    """Maps and gradients of the same Gaussians composited in float32 ("auto" on float32 inputs)
    and in float64 (the reference), as float64 tensors, plus the float32 run's own dtypes."""
    runs = []
    for precision in ("auto", "float64"):
        params = {k: getattr(g, k).detach().clone().requires_grad_(True) for k in PARAMS}
        out = render(
            Gaussians(**params),
            cams,
            W,
            H,
            mode=mode,
            backend="cpu",
            alpha_threshold=threshold,
            settings=CpuRenderSettings(precision=precision),
        )
        maps = (out.color, out.alpha, out.depth, out.normal)
        sum((m * w).sum() for m, w in zip(maps, weights)).backward()
        runs.append((maps, {k: p.grad for k, p in params.items()}))
    (maps32, grads32), (maps64, grads64) = runs
    dtypes = {t.dtype for t in (*maps32, *grads32.values())}
    return maps32, grads32, maps64, grads64, dtypes


@pytest.mark.parametrize("mode", ["surfel", "ewa"])
@pytest.mark.parametrize(
    ("seed", "size", "f", "scale"),
    [(0, (37, 29), 30.0, 1.0), (1, (64, 48), 45.0, 1.0), (2, (23, 41), 20.0, 4.0), (3, (50, 50), 70.0, 2.5)],
)
def test_float32_compositing_agrees_with_float64(mode, seed, size, f, scale):
    # The scenes of the reference test (no edge-on surfels: their side is decided by rounding),
    # rendered from float32 inputs at x1 and, scaled, up to 184 px: float32 compositing against
    # float64 compositing of the very same inputs.
    W, H = round(size[0] * scale), round(size[1] * scale)
    g = scene(70, seed, sh_degree=seed, behind=5, dtype=torch.float32)
    cams = camera(f, size[0], size[1], dtype=torch.float32).scaled(scale)
    weights = random_weights(cams, W, H, torch.float32)
    maps32, grads32, maps64, grads64, dtypes = _precision_pair(g, cams, W, H, mode, weights)
    assert dtypes == {torch.float32}
    assert float(maps64[1].detach().max()) > 0.5  # the scene covers the view
    for name, a, b in zip(("color", "alpha"), maps32, maps64):
        err = float((a.detach().double() - b.detach().double()).abs().max())
        assert err <= 1e-4, f"{name}: float32 vs float64 compositing differ by {err:.3g}"
    # Computed in float32, not float64 rounded at the end: the two float32 results differ, by
    # float32 rounding (~1e-7 of values near 1).
    assert not torch.equal(maps32[0], maps64[0])
    for name, a, b in zip(("depth", "normal"), maps32[2:], maps64[2:]):
        assert_close_relative(a.double(), b.double(), 1e-4, name)
    for name in PARAMS:
        assert float(grads64[name].abs().max()) > 0, name
        assert_close_relative(grads32[name].double(), grads64[name].double(), 5e-4, f"d/d{name}")


def test_float32_is_the_default_for_float32_inputs_and_float64_for_float64():
    from surfsplat.render.cpu.backend import compositing_dtype

    auto = CpuRenderSettings()
    assert compositing_dtype(auto, torch.float32) is np.float32
    assert compositing_dtype(auto, torch.bfloat16) is np.float32
    assert compositing_dtype(auto, torch.float64) is np.float64
    assert compositing_dtype(CpuRenderSettings(precision="float64"), torch.float32) is np.float64
    assert compositing_dtype(CpuRenderSettings(precision="float32"), torch.float64) is np.float32
    # float64 inputs with float32 compositing: float64 outputs and gradients, float32-close.
    g = scene(40, 12, sh_degree=1, behind=2)
    cams = camera(30.0, 32, 24)
    ref = render(g, cams, 32, 24, backend="cpu")
    params = {k: getattr(g, k).detach().clone().requires_grad_(True) for k in PARAMS}
    out = render(Gaussians(**params), cams, 32, 24, backend="cpu", settings=CpuRenderSettings(precision="float32"))
    assert out.color.dtype == torch.float64
    assert 0 < float((out.color.detach() - ref.color).abs().max()) <= 1e-4
    out.color.sum().backward()
    assert all(p.grad.dtype == torch.float64 for p in params.values())
    with pytest.raises(SurfSplatInputError, match="settings.precision: expected 'auto', 'float32' or 'float64'"):
        CpuRenderSettings(precision="half")


def test_float32_kernels_compute_in_float32():
    # The compiled renderer has float32 specialisations of its compositing kernels, and the pixel
    # loop compiled for float32 coefficients has no float64 arithmetic (a float64 literal would
    # have widened every lane). Checked on a fresh, uncached compile: cached code has no IR.
    g = scene(20, 13, sh_degree=0, dtype=torch.float32)
    params = {k: getattr(g, k).detach().clone().requires_grad_(True) for k in PARAMS}
    render(Gaussians(**params), camera(20.0, 16, 16, dtype=torch.float32), 16, 16, backend="cpu").color.sum().backward()
    for kernel in (kernels.composite_forward, kernels.composite_backward):
        assert any(sig[2] == numba.float32[:, ::1] for sig in kernel.signatures), kernel  # (surfel, lowpass, geom
    f32 = np.float32
    lanes = kernels.LANES
    rows, g, f = np.ones(16, dtype=np.int64), np.zeros(kernels.GEOM_SIZE, f32), np.ones(kernels.FEATURES, f32)
    g[kernels.GEOM_LOGO] = -0.5
    last = np.zeros((16, lanes), dtype=np.int32)
    box = (0, 0, 1, 0, 3, 0, 3)  # x0, y0, chunks, c0, c1, r0, r1
    # Without and with the depth distortion (its variants are compiled for None and for an array).
    fwd_runs = (kernels.FORWARD_RUNS, kernels.FORWARD_RUNS + kernels.DISTORTION_RUNS)
    bwd_runs = (kernels.BACKWARD_RUNS, kernels.BACKWARD_RUNS + kernels.DISTORTION_BACKWARD_RUNS)
    dist = (None, np.zeros((2, 1, 1), f32))
    calls = [
        (
            kernels._blend,
            [
                (surfel, f32(LOWPASS_RHO_SCALE), g, f, np.zeros((16, runs * lanes), f32), last, *box, np.int32(1), d)
                for runs, d in zip(fwd_runs, dist)
                for surfel in (True, False)
            ],
        ),
        (
            kernels._unblend_box,
            [
                (
                    surfel,
                    f32(LOWPASS_RHO_SCALE),
                    g,
                    f,
                    np.zeros((16, runs * lanes), f32),
                    last,
                    rows,
                    *box,
                    np.int32(0),
                    d,
                    np.zeros((1, kernels.GRAD_SIZE), f32),
                    0,
                    *absolute,
                )
                for runs, d in zip(bwd_runs, dist)
                for surfel in (True, False)
                # without and with the absolute screen gradient (surfels)
                for absolute in ((None, 0, None), (np.zeros((1, kernels.ABS_SIZE), f32), 0, np.zeros((1, 2), f32)))
                if surfel or absolute[0] is None
            ],
        ),
        (kernels._exp_of_8th, [(f32(-0.1), f32)]),
    ]
    for kernel, argument_lists in calls:
        fresh = numba.njit(error_model="numpy", boundscheck=False)(kernel.py_func)
        for args in argument_lists:
            fresh(*args)
        for sig in fresh.signatures:
            # The compiled function itself, not its Python wrapper (which unboxes float arguments as doubles).
            functions = fresh.inspect_llvm(sig).split("\ndefine ")[1:]
            ir = "".join(f for f in functions if "cpython" not in f.split("(")[0])
            assert " float" in ir, kernel
            assert "double" not in ir.replace("double*", ""), (
                f"float64 arithmetic in the float32 pixel loop of {kernel}"
            )


# --------------------------------------------------------------------------- independent twins


@pytest.mark.parametrize("mode", ["surfel", "ewa"])
@pytest.mark.parametrize("seed", [5, 6])
def test_matches_brute_force_twin(mode, seed):
    # Edge-on within 1e-3 rad: the twin decides the normal's side in another frame and precision.
    g = scene(40, seed, sh_degree=seed - 4, behind=3, edge_on=4, tilt=1e-3, dtype=torch.float32)
    W, H = 33, 25
    cams = camera(28.0, W, H, dtype=torch.float32)
    out = render(g, cams, W, H, mode=mode, backend="cpu", alpha_threshold=None)
    twin = reference_render(g, cams, W, H, mode)
    assert float(twin[1].max()) > 0.5
    maps = (out.color, out.alpha, out.depth, out.normal)
    for name, ours, ref in zip(("color", "alpha", "depth", "normal"), maps, twin):
        assert_close_relative(ours.double(), ref, 2e-5, name)


@pytest.mark.parametrize("mode", ["surfel", "ewa"])
def test_gradcheck_float64(mode):
    g0 = scene(5, 21, sh_degree=2)
    cams = camera(12.0, 10, 9)

    def fn(means, quats, scales, opacities, sh):
        out = render(
            Gaussians(means, quats, scales, opacities, sh),
            cams,
            10,
            9,
            mode=mode,
            backend="cpu",
            alpha_threshold=0.001,
            background=[0.3, 0.2, 0.1],
        )
        return out.color, out.alpha, out.depth, out.normal

    inputs = tuple(getattr(g0, k).detach().clone().requires_grad_(True) for k in PARAMS)
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_gradcheck_float64_explicit_covariances():
    g0 = scene(4, 22, sh_degree=0)
    cams = camera(12.0, 9, 9)
    A = torch.randn(4, 3, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 0.1
    cov0 = A @ A.transpose(1, 2) + 0.01 * torch.eye(3, dtype=torch.float64)

    def fn(means, cov, opacities):
        symmetric = (cov + cov.transpose(1, 2)) / 2
        g = Gaussians(means, g0.quats, g0.scales, opacities, g0.sh, explicit_covariances=symmetric)
        out = render(g, cams, 9, 9, mode="ewa", backend="cpu", alpha_threshold=None)
        return out.color, out.alpha, out.depth

    inputs = tuple(t.clone().requires_grad_(True) for t in (g0.means, cov0, g0.opacities))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


# --------------------------------------------------------------------------- closed forms and invariances


def test_fronto_parallel_surfel_is_the_analytic_gaussian_with_analytic_gradient():
    # One camera-facing surfel at depth z: alpha(p) = o exp(-(u^2 + v^2) / 2) with u = (X - mx) / su,
    # X the back-projection of the pixel onto the plane; d alpha / d o = alpha / o in closed form.
    W, H, f, z = 40, 36, 50.0, 2.0
    mean = torch.tensor([[0.05, -0.03, z]], dtype=torch.float64)
    su, sv, o = 0.11, 0.07, 0.6
    params = dict(
        means=mean,
        quats=torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
        scales=torch.tensor([[su, sv]], dtype=torch.float64),
        opacities=torch.tensor([o], dtype=torch.float64, requires_grad=True),
        sh=torch.zeros(1, 3, 1, dtype=torch.float64),
    )
    cams = Cameras(
        torch.eye(4, dtype=torch.float64)[None],
        torch.tensor([[[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]]], dtype=torch.float64),
    )
    out = render(Gaussians(**params), cams, W, H, backend="cpu", alpha_threshold=None)
    j = torch.arange(W, dtype=torch.float64) + 0.5
    i = torch.arange(H, dtype=torch.float64) + 0.5
    yy, xx = torch.meshgrid(i, j, indexing="ij")
    u = ((xx - W / 2) / f * z - 0.05) / su
    v = ((yy - H / 2) / f * z + 0.03) / sv
    expected = o * torch.exp(-0.5 * (u * u + v * v))
    inside = expected >= 1 / 255
    # Where the ray-splat branch is taken alpha is exact; the 1/255 level bounds the footprint.
    assert torch.allclose(out.alpha[0, 0][inside], expected[inside], atol=1e-12)
    assert float(out.alpha.detach()[0, 0][~inside].abs().max()) == 0.0
    assert torch.allclose(out.depth[0, 0][inside], out.alpha[0, 0][inside] * z, atol=1e-12)
    out.alpha.sum().backward()
    assert math.isclose(float(params["opacities"].grad), float(expected[inside].sum()) / o, rel_tol=1e-12)


def test_result_does_not_depend_on_tile_size_or_threads():
    # Each pixel blends the same Gaussians in the same order whatever the tiling, so the forward
    # pass is bitwise identical; gradients only differ by how the per-tile sums are grouped.
    W, H = 50, 38
    g = scene(200, 8, sh_degree=1, behind=4, edge_on=6)
    cams = camera(40.0, W, H)
    weights = random_weights(cams, W, H, torch.float64)
    base, g_base = _with_settings(g, cams, W, H, weights, CpuRenderSettings(tile_size=16))
    threads = numba.get_num_threads()
    for tile, n_threads in ((4, threads), (7, threads), (32, 1)):
        numba.set_num_threads(n_threads)
        try:
            maps, grads = _with_settings(g, cams, W, H, weights, CpuRenderSettings(tile_size=tile, parallel_chunk=1))
        finally:
            numba.set_num_threads(threads)
        for a, b in zip(maps, base):
            assert torch.equal(a, b), tile
        for name in PARAMS:
            assert_close_relative(grads[name], g_base[name], 1e-12, f"d/d{name}")


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_gradients_are_bitwise_identical_for_any_thread_count_and_schedule(dtype):
    # Per-(tile, Gaussian) gradient rows are summed in a fixed order, so neither the number of
    # threads nor which thread took which tile changes a bit (what exact training resume needs),
    # in float64 and in float32 compositing alike.
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba was started with one thread (NUMBA_NUM_THREADS=1)")
    W, H = 96, 80
    g = scene(600, 21, sh_degree=2, behind=4, edge_on=10, dtype=dtype)
    cams = camera(70.0, W, H, dtype=dtype)
    weights = random_weights(cams, W, H, dtype)
    threads = numba.get_num_threads()
    results = []
    try:
        for n_threads, chunk in ((1, 4), (2, 1), (2, 1), (2, 3), (2, 16)):
            numba.set_num_threads(n_threads)
            results.append(_with_settings(g, cams, W, H, weights, CpuRenderSettings(parallel_chunk=chunk)))
    finally:
        numba.set_num_threads(threads)
    (base, g_base), rest = results[0], results[1:]
    assert sum(int((grad != 0).sum()) for grad in g_base.values()) > 1000  # the scene has real gradients
    assert base[0].dtype == g_base["means"].dtype == dtype
    for maps, grads in rest:
        for a, b in zip(maps, base):
            assert torch.equal(a, b)
        for name in PARAMS:
            assert torch.equal(grads[name], g_base[name]), name


@pytest.mark.parametrize("mode", ["surfel", "ewa"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("wanted", [("sh", "opacities"), ("sh", "opacities", "scales"), ("means",), ("quats",)])
def test_gradients_of_some_inputs_are_those_of_all_inputs(mode, dtype, wanted):
    # A fit of colours, opacities and sizes (the capture refinement, the 3DGS bake) asks for some
    # gradients only; the backward then skips the others' chain rule, and the ones it returns are
    # bit for bit those of a backward that computes everything.
    W, H = 64, 48
    g = scene(400, 31, sh_degree=2, behind=3, edge_on=6, dtype=dtype)
    cams = camera(60.0, W, H, dtype=dtype)
    weights = random_weights(cams, W, H, dtype)
    _, every = render_and_grads(g, cams, W, H, mode, "cpu", weights)
    params = {k: getattr(g, k).detach().clone().requires_grad_(k in wanted) for k in PARAMS}
    out = render(Gaussians(**params), cams, W, H, mode=mode, backend="cpu", background=[0.1, 0.2, 0.3])
    maps = (out.color, out.alpha, out.depth, out.normal)
    sum((m * w).sum() for m, w in zip(maps, weights)).backward()
    for name in PARAMS:
        if name in wanted:
            assert int((every[name] != 0).sum()) > 100, name
            assert torch.equal(params[name].grad, every[name]), name
        else:
            assert params[name].grad is None, name


def _with_settings(g, cams, W, H, weights, settings):
    params = {k: getattr(g, k).detach().clone().requires_grad_(True) for k in PARAMS}
    out = render(Gaussians(**params), cams, W, H, backend="cpu", settings=settings)
    maps = (out.color, out.alpha, out.depth, out.normal)
    sum((m * w).sum() for m, w in zip(maps, weights)).backward()
    return maps, {k: p.grad for k, p in params.items()}


def test_early_termination_rule_and_gradient_through_it():
    # Stacked opaque layers: after two (alpha 0.99, 0.98) T = 2e-4; the third (alpha 0.99) would
    # take T below 1e-4, so it ends the pixel unblended, and the faint fourth is never reached.
    # The third and fourth Gaussians then get no gradient at all.
    dt = torch.float64
    sh_dc = torch.tensor([1.0, 0.3, -1.0, 0.7], dtype=dt)
    params = dict(
        means=torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.5], [0.0, 0.0, 3.0], [0.0, 0.0, 3.5]], dtype=dt),
        quats=torch.tensor([[1.0, 0, 0, 0]], dtype=dt).expand(4, 4).clone(),
        scales=torch.full((4, 2), 1e4, dtype=dt),
        opacities=torch.tensor([0.99, 0.98, 0.99, 0.1], dtype=dt),
        sh=sh_dc[:, None, None].expand(4, 3, 1).clone(),
    )
    params = {k: v.requires_grad_(True) for k, v in params.items()}
    cams = camera(20.0, 8, 8, offset=(0.0, 0.0, 0.0))
    out = render(Gaussians(**params), cams, 8, 8, backend="cpu", alpha_threshold=None)
    c = sh_dc * 0.28209479177387814 + 0.5
    assert torch.allclose(out.color, torch.full_like(out.color, float(0.99 * c[0] + 0.01 * 0.98 * c[1])), atol=1e-9)
    assert torch.allclose(out.alpha, torch.full_like(out.alpha, 1 - 0.01 * 0.02), atol=1e-9)
    out.color.sum().backward()
    # d color / d o_1 = T_1 c_1 = 0.01 c_1 per pixel and channel (o_1 = 0.98 < 0.99: not clamped).
    # (alpha_0 = 0.99 exp(-rho / 2) with rho ~ 1e-9 at these huge scales, hence the tolerance)
    assert math.isclose(float(params["opacities"].grad[1]), 64 * 0.01 * float(c[1]) * 3, rel_tol=1e-6)
    assert float(params["opacities"].grad[2:].abs().max()) == 0.0
    assert float(params["sh"].grad[2:].abs().max()) == 0.0


def test_contributing_pair_count_matches_brute_force():
    # The benchmark's work measure: pairs with alpha >= 1/255, counted here by brute force.
    W, H = 30, 26
    g = scene(60, 9, sh_degree=0, behind=2, edge_on=3)
    cams = camera(26.0, W, H)
    (count,) = contributing_pairs(g, cams, W, H, "ewa", CpuRenderSettings(tile_size=8))
    twin = 0
    for n in range(len(g)):
        single = g.subset(torch.tensor([n]))
        alpha = reference_render(single, cams, W, H, "ewa")[1]
        twin += int((alpha >= 1 / 255).sum())
    assert count == twin and count > 500


def test_polynomial_exp_is_accurate_over_the_used_range():
    x = np.linspace(kernels.LOG_ALPHA_MIN - 2.0, 0.0, 20001)
    ours = np.array([kernels._exp_nonpositive(v, np.float64) for v in x])
    assert np.max(np.abs(ours / np.exp(x) - 1)) < 1e-14
    # float32: the series' roundings, squared three times (relative errors add up 8-fold).
    x32 = x.astype(np.float32)
    ours32 = np.array([kernels._exp_nonpositive(v, np.float32) for v in x32])
    assert np.max(np.abs(ours32 / np.exp(x32.astype(np.float64)) - 1)) < 2e-6
    assert numba.float32 in {sig.return_type for sig in kernels._exp_nonpositive.nopython_signatures}


def test_degenerate_geometry_has_finite_forward_and_backward():
    g = scene(60, 10, sh_degree=3, behind=6, edge_on=12, dtype=torch.float32)
    params = {k: getattr(g, k).clone().requires_grad_(True) for k in PARAMS}
    params["scales"].data[:4] = 0.0  # zero-area surfels
    params["opacities"].data[4:6] = 1e-4  # below 1/255: culled
    for mode in ("surfel", "ewa"):
        out = render(Gaussians(**params), camera(30.0, 24, 24, dtype=torch.float32), 24, 24, mode=mode, backend="cpu")
        (out.color.sum() + out.depth.sum() + out.normal.sum() + out.alpha.sum()).backward()
        for name, p in params.items():
            assert torch.isfinite(p.grad).all(), (mode, name)
            p.grad = None
        assert all(torch.isfinite(t).all() for t in (out.color, out.alpha, out.depth, out.normal))


# --------------------------------------------------------------------------- dispatch


def test_auto_picks_the_compiled_backend_on_cpu(monkeypatch):
    g = scene(3, 0, sh_degree=0)
    cams = camera(10.0, 8, 8)
    assert resolve_backend("auto", torch.device("cpu"), None, cams) == "cpu"
    assert resolve_backend("auto", torch.device("cpu"), CpuRenderSettings(), cams) == "cpu"
    assert resolve_backend("auto", torch.device("cpu"), TorchRenderSettings(), cams) == "torch"
    posed = Cameras(cams.c2w.clone().requires_grad_(True), cams.K)
    assert resolve_backend("auto", torch.device("cpu"), None, posed) == "torch"  # only torch differentiates cameras
    calls = []
    monkeypatch.setattr("surfsplat.render.cpu.backend.render_cpu", lambda *a: calls.append(a) or render_cpu(*a))
    render(g, cams, 8, 8)
    assert len(calls) == 1


def test_auto_falls_back_to_torch_with_one_notice_when_the_backend_cannot_load(monkeypatch):
    g = scene(3, 0, sh_degree=0)
    cams = camera(10.0, 8, 8)
    monkeypatch.setattr("surfsplat.render.cpu_backend_unavailable", lambda: "numba is not importable (test)")
    with pytest.warns(UserWarning, match="compiled CPU backend unavailable.*numba is not importable"):
        out = render(g, cams, 8, 8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ref = render(g, cams, 8, 8, backend="torch")
    assert torch.equal(out.color, ref.color)
    with pytest.raises(SurfSplatInputError, match="backend: 'cpu' cannot load"):
        render(g, cams, 8, 8, backend="cpu")


def test_bad_backend_requests_get_one_clear_error():
    g = scene(3, 0, sh_degree=0)
    cams = camera(10.0, 8, 8)
    with pytest.raises(SurfSplatInputError, match="backend: expected"):
        render(g, cams, 8, 8, backend="numba")
    with pytest.raises(SurfSplatInputError, match="settings: backend 'cpu' takes CpuRenderSettings"):
        render(g, cams, 8, 8, backend="cpu", settings=TorchRenderSettings())
    with pytest.raises(SurfSplatInputError, match="settings: backend 'torch' takes TorchRenderSettings"):
        render(g, cams, 8, 8, backend="torch", settings=CpuRenderSettings())
    with pytest.raises(SurfSplatInputError, match="settings.tile_size"):
        CpuRenderSettings(tile_size=0)
    posed = Cameras(cams.c2w.clone().requires_grad_(True), cams.K)
    with pytest.raises(SurfSplatInputError, match="cameras: the 'cpu' backend does not differentiate cameras"):
        render(g, posed, 8, 8, backend="cpu")


# --------------------------------------------------------------------------- the benchmark scene


def test_termination_holds_across_many_layers():
    # 300 stacked camera-facing layers of alpha 0.07: after 126 of them T = 0.93^126 = 1.07e-4 and
    # the 127th would take it below 1e-4, so the pixel stops there for good. A faint but bright
    # layer further back (index 128) would on its own keep T above the floor: it must not be
    # blended. Checked against the brute-force twin and the closed form. (The torch backend, whose
    # depth blocks hold 128 Gaussians, blends it: it resumes a stopped pixel in its next block.)
    dt = torch.float64
    n = 300
    z = 2.0 + 0.01 * torch.arange(n, dtype=dt)
    opac = torch.full((n,), 0.07, dtype=dt)
    opac[128] = 0.004
    sh = torch.zeros(n, 3, 1, dtype=dt)
    sh[128] = 10.0
    g = Gaussians(
        torch.stack((torch.zeros(n, dtype=dt), torch.zeros(n, dtype=dt), z), -1),
        torch.tensor([[1.0, 0, 0, 0]], dtype=dt).expand(n, 4).clone(),
        torch.full((n, 2), 1e3, dtype=dt),
        opac,
        sh,
    )
    cams = camera(10.0, 4, 4, offset=(0.0, 0.0, 0.0))
    out = render(g, cams, 4, 4, backend="cpu", alpha_threshold=None)
    twin = reference_render(g, cams, 4, 4)
    assert torch.allclose(out.color, twin[0], atol=1e-12) and torch.allclose(out.alpha, twin[1], atol=1e-12)
    kept = 0.07 * 0.93 ** torch.arange(126, dtype=dt)
    assert math.isclose(float(out.alpha[0, 0, 0, 0]), float(kept.sum()), rel_tol=1e-9)
    assert math.isclose(float(out.color[0, 0, 0, 0]), 0.5 * float(kept.sum()), rel_tol=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["surfel", "ewa"])
def test_benchmark_scene_matches_torch_reference(mode):
    # The benchmark's surfel scene at a small size, in float64. The torch backend runs with one
    # depth block per tile so that its stopped pixels stay stopped (see the test above).
    from surfsplat.data.synthetic.surfel_scene import make_scene

    sc = make_scene(resolution=64)
    cams = sc.target.to(torch.float64).scaled(1.5)
    g = sc.gaussians.to(torch.float64)
    weights = random_weights(cams, 96, 96, torch.float64)
    one_block = TorchRenderSettings(max_block_depth=1 << 20, block_elements=1 << 26)
    ours, g_ours = render_and_grads(g, cams, 96, 96, mode, "cpu", weights)
    ref, g_ref = _with_backend_settings(g, cams, 96, 96, mode, weights, one_block)
    for name, a, b in zip(("color", "alpha", "depth", "normal"), ours, ref):
        assert_close_relative(a, b, 1e-9, name)
    for name in PARAMS:
        assert_close_relative(g_ours[name], g_ref[name], 1e-5, f"d/d{name}")


def _with_backend_settings(g, cams, W, H, mode, weights, settings):
    params = {k: getattr(g, k).detach().clone().requires_grad_(True) for k in PARAMS}
    out = render(
        Gaussians(**params), cams, W, H, mode=mode, backend="torch", settings=settings, background=[0.1, 0.2, 0.3]
    )
    maps = (out.color, out.alpha, out.depth, out.normal)
    sum((m * w).sum() for m, w in zip(maps, weights)).backward()
    return maps, {k: p.grad for k, p in params.items()}


def test_depth_order_is_the_stable_sort_of_the_survivors():
    # many exact ties (depths on a coarse grid, -0.0 beside 0.0) and culled entries between them
    rng = np.random.default_rng(3)
    depth = rng.integers(0, 40, 5000).astype(np.float64) / 8
    depth[rng.random(5000) < 0.05] = -0.0
    keep = rng.random(5000) < 0.8
    index = np.flatnonzero(keep)
    expected = index[np.argsort(depth[index], kind="stable")]
    np.testing.assert_array_equal(kernels.depth_order(keep, depth), expected)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("threshold", [0.3, None])
def test_normalization_kernels_match_the_torch_ops(dtype, threshold):
    # Rows of 37 pixels: two whole SIMD chunks and a masked last one; two cameras.
    gen = torch.Generator().manual_seed(7)
    C, H, W = 2, 5, 37
    maps = [torch.rand(C, k, H, W, generator=gen, dtype=dtype) for k in (3, 1, 1, 3)]
    maps[1][0, 0, 0, :5] = 0.0  # uncovered pixels
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=dtype)
    ours_in = [m.clone().requires_grad_(True) for m in maps]
    ref_in = [m.clone().requires_grad_(True) for m in maps]
    ours = normalize_cpu(*ours_in, threshold, bg)
    color, depth, normal, coverage = normalize_by_alpha(*ref_in, threshold)
    ref = (color + (1 - coverage) * bg[None, :, None, None], depth, normal)
    for name, a, b in zip(("color", "depth", "normal"), ours, ref):
        assert torch.equal(a, b), name  # the same operations in the same order: the same bits
    upstream = [torch.randn(r.shape, generator=gen, dtype=dtype) for r in ref]
    torch.autograd.backward(ours, upstream)
    torch.autograd.backward(ref, upstream)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    for name, a, b in zip(("color", "alpha", "depth", "normal"), ours_in, ref_in):
        torch.testing.assert_close(a.grad, b.grad, rtol=tol, atol=tol, msg=name)


def test_backward_work_arrays_are_held_from_call_to_call():
    # The backward's largest work arrays come from one buffer per thread and name, so a training
    # loop does not get fresh memory from the system (and zero it) every step.
    first = backend._held_empty("test", (10, 20), np.float32)
    again = backend._held_empty("test", (8, 20), np.float32)
    assert again.shape == (8, 20) and np.shares_memory(first, again)
    other = backend._held_empty("test", (10, 20), np.float64)
    assert not np.shares_memory(first, other)
    # Much smaller: the large buffer is let go; larger: a new one.
    small = backend._held_empty("test", (1, 20), np.float32)
    assert not np.shares_memory(first, small)
    large = backend._held_empty("test", (50, 20), np.float32)
    assert large.shape == (50, 20) and not np.shares_memory(small, large)


@pytest.mark.parametrize("case", ["random", "ties", "signed zeros", "lowest bits", "negative"])
def test_depth_order_integer_keys_give_the_stable_sort(case):
    # One integer sort of depth keys with the index in their lowest bits, then exact order within
    # keys that agree but for those bits: it must be NumPy's stable sort of the depths.
    rng = np.random.default_rng(7)
    n = 70_000
    depth = {
        "random": rng.random(n) * 5 + 0.1,
        "ties": np.round(rng.random(n) * 5, 1),  # many exactly equal depths
        "signed zeros": rng.choice([-0.0, 0.0, 1.0, -2.0], n),
        "lowest bits": 1.0 + rng.integers(0, 4, n) * 1e-15,  # equal but for the dropped bits
        "negative": rng.standard_normal(n),
    }[case]
    keep = rng.random(n) < 0.9
    survivors = np.flatnonzero(keep)
    expected = survivors[np.argsort(depth[survivors], kind="stable")]
    np.testing.assert_array_equal(kernels.depth_order(keep, depth), expected)


@pytest.mark.parametrize("mode", ["surfel", "ewa"])
def test_the_tile_size_changes_no_pixel(mode):
    # Tiles are the unit of parallel work and of a tile's early stop, not of the result: every pixel
    # blends the same Gaussians in the same order whatever the tiling. EWA's release support keeps
    # its own 16-pixel tiles inside larger ones (a 32-pixel tiling once composited past them).
    g = scene(400, 5, sh_degree=1, dtype=torch.float32)
    cams = camera(40.0, 72, 56, dtype=torch.float32)
    outs = [
        render(g, cams, 72, 56, mode=mode, backend="cpu", settings=CpuRenderSettings(tile_size=tile))
        for tile in (16, 8, 32, 48)
    ]
    assert float(outs[0].alpha.max()) > 0.5
    for out in outs[1:]:
        for name in ("color", "alpha", "depth", "normal"):
            torch.testing.assert_close(getattr(out, name), getattr(outs[0], name), rtol=0, atol=0)


def test_plain_compositing_over_black_skips_the_normalization_to_the_same_bits():
    # alpha_threshold None and the default (black) background: the maps are returned as blended, where an
    # explicit black background runs the normalization pass, which then divides nothing and adds zero.
    g = scene(40, 21, sh_degree=1)
    cams = camera(30.0, 32, 24)
    outs, grads = [], []
    for background in (None, (0.0, 0.0, 0.0)):
        params = {k: getattr(g, k).detach().clone().requires_grad_(True) for k in PARAMS}
        out = render(Gaussians(**params), cams, 32, 24, backend="cpu", alpha_threshold=None, background=background)
        (out.color.square().sum() + out.depth.sum() + out.normal.sum() + out.alpha.sum()).backward()
        outs.append(out)
        grads.append({k: p.grad for k, p in params.items()})
    for name in ("color", "alpha", "depth", "normal"):
        assert torch.equal(getattr(outs[0], name), getattr(outs[1], name)), name
    for k in PARAMS:
        assert float(grads[0][k].abs().max()) > 0
        assert torch.equal(grads[0][k], grads[1][k]), k
