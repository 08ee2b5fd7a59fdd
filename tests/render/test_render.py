"""The renderer against closed forms, against its brute-force twin, and through gradcheck."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scipy.special import sph_harm_y

from surfsplat import Cameras, Gaussians
from surfsplat.data.synthetic.surfel_scene import frame_from_normal
from surfsplat.geometry.rotations import matrix_to_quat
from surfsplat.geometry.sh import sh_basis, sh_to_color
from surfsplat.render import TorchRenderSettings, render
from surfsplat.utils.checks import SurfSplatInputError
from tests.helpers.reference_render import reference_render

# The pure-PyTorch reference and the compiled CPU backend must both pass the closed-form checks.
BACKENDS = ["torch", "cpu"]


def pinhole(f: float, width: int, height: int, c2w: torch.Tensor | None = None, dtype=torch.float32) -> Cameras:
    K = torch.tensor([[[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]]], dtype=dtype)
    return Cameras(torch.eye(4, dtype=dtype)[None] if c2w is None else c2w[None].to(dtype), K)


def pixel_centres(width: int, height: int, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    j = torch.arange(width, dtype=dtype) + 0.5
    i = torch.arange(height, dtype=dtype) + 0.5
    yy, xx = torch.meshgrid(i, j, indexing="ij")
    return xx, yy


def random_scene(
    n: int, seed: int, dtype=torch.float32, sh_degree: int = 1, behind: int = 0, edge_on: int = 0
) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * torch.tensor([0.5, 0.4, 0.3], dtype=torch.float64)
    means[:, 2] += 2.5
    means[:behind, 2] = -means[:behind, 2]  # these lie behind the camera
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    if edge_on:
        # Normals perpendicular to the viewing ray through the mean: seen exactly edge-on.
        view = F.normalize(means[behind : behind + edge_on], dim=-1)
        side = F.normalize(torch.linalg.cross(view, torch.randn(edge_on, 3, generator=g, dtype=torch.float64)), dim=-1)
        quats[behind : behind + edge_on] = matrix_to_quat(frame_from_normal(side))
    return Gaussians(
        means=means.to(dtype),
        quats=quats.to(dtype),
        scales=(torch.rand(n, 2, generator=g, dtype=torch.float64) * 0.12 + 0.02).to(dtype),
        opacities=(torch.rand(n, generator=g, dtype=torch.float64) * 0.9 + 0.05).to(dtype),
        sh=(torch.randn(n, 3, (sh_degree + 1) ** 2, generator=g, dtype=torch.float64) * 0.4).to(dtype),
    )


# --------------------------------------------------------------------------- closed forms


@pytest.mark.parametrize("scale", [1, 4])
@pytest.mark.parametrize("backend", BACKENDS)
def test_fronto_parallel_surfel_renders_closed_form_gaussian(scale, backend):
    W, H, f = 48, 40, 60.0
    cam = pinhole(f, W, H)
    mean = torch.tensor([0.07, -0.04, 2.0])
    su, sv, o = 0.09, 0.05, 0.8
    g = Gaussians(
        mean[None], torch.tensor([[1.0, 0, 0, 0]]), torch.tensor([[su, sv]]), torch.tensor([o]), torch.zeros(1, 3, 1)
    )
    out = render(g, cam.scaled(scale), W * scale, H * scale, alpha_threshold=None, backend=backend)
    xx, yy = pixel_centres(W * scale, H * scale)
    # Back-project pixel centres of the scaled camera onto the plane z = 2.
    X = (xx - W * scale / 2) / (f * scale) * 2.0
    Y = (yy - H * scale / 2) / (f * scale) * 2.0
    u, v = (X - 0.07) / su, (Y + 0.04) / sv
    expected = o * torch.exp(-0.5 * (u * u + v * v))
    mask = expected > 2 / 255
    assert mask.sum() > 100 * scale * scale
    err = (out.alpha[0, 0].double() - expected)[mask].abs().max()
    assert err <= 1e-4, err
    # Outside the 1/255 level nothing is drawn.
    assert out.alpha[0, 0][expected < 0.9 / 255].abs().max() == 0


def tilted_plane(spacing: float, tilt_deg: float, extent: float, opacity: float = 0.7):
    """A dense grid of surfels on the plane through (0, 0, 3) with a normal tilted about x and y."""
    t = math.radians(tilt_deg)
    normal = F.normalize(torch.tensor([math.sin(t) * 0.5, math.sin(t), -math.cos(t)], dtype=torch.float64), dim=0)
    R = frame_from_normal(normal[None])[0]
    ticks = torch.arange(-extent, extent + 1e-9, spacing, dtype=torch.float64)
    uu, vv = torch.meshgrid(ticks, ticks, indexing="ij")
    pts = torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64) + uu.reshape(-1, 1) * R[:, 0] + vv.reshape(-1, 1) * R[:, 1]
    n = pts.shape[0]
    g = Gaussians(
        means=pts.float(),
        quats=matrix_to_quat(R).float().expand(n, 4).contiguous(),
        scales=torch.full((n, 2), spacing),
        opacities=torch.full((n,), opacity),
        sh=torch.rand(n, 3, 1, generator=torch.Generator().manual_seed(0)),
    )
    return g, normal, R


@pytest.mark.parametrize("scale", [1, 2, 4])
@pytest.mark.parametrize("backend", BACKENDS)
def test_tilted_plane_renders_analytic_depth_and_normal(scale, backend):
    W, H, f = 40, 32, 40.0
    # Surfels stay wider than a pixel everywhere at x1: for sub-pixel surfels 2DGS's screen-space
    # filter wins and reports the centre depth instead of the ray-splat intersection.
    g, normal, R = tilted_plane(spacing=0.15, tilt_deg=30, extent=2.4)
    out = render(g, pinhole(f, W, H).scaled(scale), W * scale, H * scale, backend=backend)
    xx, yy = pixel_centres(W * scale, H * scale)
    rays = torch.stack(
        ((xx - W * scale / 2) / (f * scale), (yy - H * scale / 2) / (f * scale), torch.ones_like(xx)), -1
    )
    p0 = torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)
    z = (p0 @ normal) / (rays @ normal)  # camera z of the ray-plane hit (rays have z = 1)
    hit = rays * z[..., None] - p0
    # Interior: the hit lies inside the grid by more than 3 surfel sigmas.
    interior = ((hit @ R[:, 0]).abs() < 2.4 - 0.45) & ((hit @ R[:, 1]).abs() < 2.4 - 0.45)
    assert interior.float().mean() > 0.9
    depth = out.depth[0, 0].double()
    rel = ((depth - z).abs() / z)[interior]
    assert rel.max() <= 1e-3, rel.max()
    facing = normal  # built with a negative z component: it already faces the camera
    cos = out.normal[0].double().permute(1, 2, 0)[interior] @ facing
    assert cos.min() >= 1 - 1e-5, cos.min()
    if scale == 4:
        assert out.alpha[0, 0][interior].min() > 0.99  # full coverage: no holes between surfels


def test_surfel_and_ewa_agree_on_camera_facing_surfels_larger_than_a_pixel():
    W, H, f = 64, 64, 80.0
    g = torch.Generator().manual_seed(1)
    n = 5
    means = torch.cat(
        (torch.rand(n, 2, generator=g) * 0.4 - 0.2, torch.full((n, 1), 2.0) + torch.rand(n, 1, generator=g)), -1
    )
    gs = Gaussians(
        means,
        torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4).contiguous(),
        torch.rand(n, 2, generator=g) * 0.06 + 0.08,
        torch.rand(n, generator=g) * 0.5 + 0.3,
        torch.rand(n, 3, 1, generator=g),
    )
    cam = pinhole(f, W, H)
    a = render(gs, cam, W, H, mode="surfel", alpha_threshold=None)
    b = render(gs, cam, W, H, mode="ewa", alpha_threshold=None)
    assert a.alpha.max() > 0.3
    assert (a.alpha - b.alpha).abs().max() < 0.02  # only the 0.3 px^2 dilation differs
    assert (a.color - b.color).abs().max() < 0.03


# --------------------------------------------------------------------------- brute-force twin


@pytest.mark.parametrize("mode", ["surfel", "ewa"])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("backend", BACKENDS)
def test_tile_renderer_matches_brute_force_reference(mode, seed, backend):
    g = random_scene(40, seed, sh_degree=seed, behind=3, edge_on=4)
    W, H = 37, 29  # not multiples of the tile size
    c2w = torch.eye(4)
    c2w[:3, 3] = torch.tensor([0.05, -0.03, 0.1])
    cam = pinhole(30.0, W, H, c2w)
    out = render(g, cam, W, H, mode=mode, alpha_threshold=None, backend=backend)
    color, alpha, depth, normal = reference_render(g, cam, W, H, mode)
    assert alpha.max() > 0.5
    for ours, ref in ((out.color, color), (out.alpha, alpha), (out.depth, depth), (out.normal, normal)):
        assert (ours.double() - ref).abs().max() < 2e-5 * max(1.0, float(ref.abs().max()))


def test_result_does_not_depend_on_tiling_or_block_size():
    g = random_scene(300, 5)
    cam = pinhole(50.0, 64, 48)
    base = render(g, cam, 64, 48, settings=TorchRenderSettings(tile_size=16))
    for settings in (
        TorchRenderSettings(tile_size=4),
        TorchRenderSettings(tile_size=8, block_elements=256, max_block_depth=3),
    ):
        other = render(g, cam, 64, 48, settings=settings)
        # float32: a pixel's terms are expanded around its tile's origin, up to 16 px from the
        # pixel, so rho carries ~2 * 16^2 * 6e-8 of rounding at tile size 16.
        for name in ("color", "alpha", "depth", "normal"):
            assert torch.allclose(getattr(base, name), getattr(other, name), atol=3e-5), name


def test_early_termination_follows_the_3dgs_rule():
    # Four huge fronto-parallel surfels stacked along the axis (alpha = opacity everywhere, 0.99 at
    # most). After the first two, T = 0.01 * 0.02 = 2e-4; the third (alpha 0.99) would take T to
    # 2e-6 < 1e-4, so it ends the pixel and is not blended - and neither is the faint fourth,
    # although on its own it would keep T above the floor.
    dt = torch.float64
    n = 4
    sh_dc = torch.tensor([1.0, 0.3, -1.0, 0.7], dtype=dt)
    g = Gaussians(
        means=torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.5], [0.0, 0.0, 3.0], [0.0, 0.0, 3.5]], dtype=dt),
        quats=torch.tensor([[1.0, 0, 0, 0]], dtype=dt).expand(n, 4),
        scales=torch.full((n, 2), 1e4, dtype=dt),
        opacities=torch.tensor([1.0, 0.98, 0.99, 0.1], dtype=dt),
        sh=sh_dc[:, None, None].expand(n, 3, 1),
    )
    cam = pinhole(20.0, 8, 8, dtype=dt)
    out = render(g, cam, 8, 8, alpha_threshold=None)
    colours = sh_dc * 0.28209479177387814 + 0.5
    expected = 0.99 * colours[0] + 0.01 * 0.98 * colours[1]
    assert torch.allclose(out.color, torch.full_like(out.color, float(expected)), atol=1e-6)
    assert torch.allclose(out.alpha, torch.full_like(out.alpha, 1 - 0.01 * 0.02), atol=1e-6)
    assert torch.allclose(out.color, reference_render(g, cam, 8, 8)[0], atol=1e-9)


# --------------------------------------------------------------------------- normalization, colours


def test_forced_alpha_normalization_and_background():
    g = random_scene(60, 3)
    cam = pinhole(40.0, 32, 32)
    bg = torch.tensor([0.2, 0.5, 0.9])
    plain = render(g, cam, 32, 32, alpha_threshold=None, background=bg)
    raw = render(g, cam, 32, 32, alpha_threshold=None)
    fab = render(g, cam, 32, 32, alpha_threshold=0.1, background=bg)
    alpha = raw.alpha
    assert torch.allclose(plain.color, raw.color + (1 - alpha) * bg[None, :, None, None], atol=1e-6)
    normalized = alpha >= 0.1
    assert normalized.any() and (~normalized).any()
    expected = torch.where(
        normalized, raw.color / alpha.clamp_min(1e-8), raw.color + (1 - alpha) * bg[None, :, None, None]
    )
    assert torch.allclose(fab.color, expected, atol=1e-5)
    expected_depth = torch.where(normalized, raw.depth / alpha.clamp_min(1e-8), raw.depth)
    assert torch.allclose(fab.depth, expected_depth, atol=1e-5)
    assert torch.equal(fab.alpha, raw.alpha)


def real_sh_direct(dirs: np.ndarray, degree: int) -> np.ndarray:
    """Real SH from scipy's complex harmonics (Condon-Shortley phase), m = -l..l within each degree."""
    theta = np.arccos(np.clip(dirs[:, 2], -1, 1))
    phi = np.arctan2(dirs[:, 1], dirs[:, 0])
    cols = []
    for l in range(degree + 1):
        for m in range(-l, l + 1):
            Y = sph_harm_y(l, abs(m), theta, phi)
            cols.append(np.sqrt(2) * Y.real if m > 0 else np.sqrt(2) * Y.imag if m < 0 else Y.real)
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_colours_match_direct_evaluation(degree):
    rng = np.random.default_rng(degree)
    dirs = rng.normal(size=(200, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    basis = sh_basis(torch.from_numpy(dirs), degree).numpy()
    np.testing.assert_allclose(basis, real_sh_direct(dirs, degree), atol=1e-12)

    # Through the renderer: one opaque surfel, normalized by alpha, shows exactly its SH colour
    # for the direction from the camera to its centre.
    sh = torch.from_numpy(rng.normal(size=(1, 3, (degree + 1) ** 2)) * 0.3)
    mean = torch.tensor([[0.3, -0.2, 2.0]], dtype=torch.float64)
    g = Gaussians(
        mean,
        torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
        torch.tensor([[0.3, 0.3]], dtype=torch.float64),
        torch.tensor([0.9], dtype=torch.float64),
        sh,
    )
    cam = pinhole(20.0, 16, 16, dtype=torch.float64)
    out = render(g, cam, 16, 16)
    d = F.normalize(mean[0], dim=0).numpy()
    direct = (sh[0].numpy() * real_sh_direct(d[None], degree)[0]).sum(-1) + 0.5
    centre = K_project(cam, mean[0])
    np.testing.assert_allclose(out.color[0, :, centre[1], centre[0]].numpy(), np.maximum(direct, 0), atol=1e-10)
    assert torch.allclose(sh_to_color(sh[0], torch.from_numpy(d)), torch.from_numpy(np.maximum(direct, 0)))


def K_project(cam: Cameras, point: torch.Tensor) -> tuple[int, int]:
    p = cam.K[0].double() @ point.double()
    return int(p[0] / p[2]), int(p[1] / p[2])


# --------------------------------------------------------------------------- gradients


@pytest.mark.parametrize("mode", ["surfel", "ewa"])
@pytest.mark.parametrize("threshold", [None, 0.001])
@pytest.mark.parametrize("backend", BACKENDS)
def test_gradcheck_float64(mode, threshold, backend):
    g0 = random_scene(6, 11, dtype=torch.float64, sh_degree=1)
    cam = pinhole(14.0, 12, 10, dtype=torch.float64)

    def fn(means, quats, scales, opacities, sh):
        out = render(
            Gaussians(means, quats, scales, opacities, sh),
            cam,
            12,
            10,
            mode=mode,
            alpha_threshold=threshold,
            background=[0.1, 0.2, 0.3],
            backend=backend,
        )
        return out.color, out.alpha, out.depth, out.normal

    inputs = tuple(
        t.detach().clone().requires_grad_(True) for t in (g0.means, g0.quats, g0.scales, g0.opacities, g0.sh)
    )
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_gradcheck_with_saturated_alpha_and_termination():
    # Opacity above 0.99 (alpha clamped) and several stacked layers (transmittance floor reached).
    dt = torch.float64
    n = 4
    means = torch.tensor([[0.02, 0.01, 2.0], [-0.03, 0.02, 2.3], [0.01, -0.02, 2.6], [0.0, 0.03, 2.9]], dtype=dt)
    quats = torch.tensor([[1.0, 0.1, -0.05, 0.02]], dtype=dt).expand(n, 4).clone()
    scales = torch.full((n, 2), 0.25, dtype=dt)
    opacities = torch.tensor([0.9995, 0.9993, 0.6, 0.7], dtype=dt)
    sh = torch.randn(n, 3, 1, dtype=dt, generator=torch.Generator().manual_seed(2))
    cam = pinhole(10.0, 8, 8, dtype=dt)

    def fn(means, quats, scales, sh):
        out = render(Gaussians(means, quats, scales, opacities, sh), cam, 8, 8, alpha_threshold=None)
        return out.color, out.depth

    inputs = tuple(t.clone().requires_grad_(True) for t in (means, quats, scales, sh))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-7, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_backward_is_finite_for_degenerate_geometry():
    g = random_scene(50, 7, behind=5, edge_on=10)
    params = {k: getattr(g, k).clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "sh")}
    params["scales"].data[:3] = 0.0  # zero-area surfels
    out = render(Gaussians(**params), pinhole(30.0, 24, 24), 24, 24)
    (out.color.sum() + out.depth.sum() + out.normal.sum() + out.alpha.sum()).backward()
    for name, p in params.items():
        assert torch.isfinite(p.grad).all(), name
    assert torch.isfinite(out.color).all() and torch.isfinite(out.depth).all()


# --------------------------------------------------------------------------- bad input


def test_bad_input_gets_one_clear_error():
    g = random_scene(4, 0)
    cam = pinhole(10.0, 8, 8)
    with pytest.raises(SurfSplatInputError, match="width"):
        render(g, cam, 0, 8)
    with pytest.raises(SurfSplatInputError, match="mode"):
        render(g, cam, 8, 8, mode="splat")
    with pytest.raises(SurfSplatInputError, match="background"):
        render(g, cam, 8, 8, background=[0.0, 1.0])
    with pytest.raises(SurfSplatInputError, match="backend"):
        render(g, cam, 8, 8, backend="gsplat")  # no CUDA here
    with pytest.raises(SurfSplatInputError, match="gaussians.means"):
        Gaussians(torch.zeros(4, 2), g.quats, g.scales, g.opacities, g.sh)
    with pytest.raises(SurfSplatInputError, match="gaussians.scales"):
        Gaussians(g.means, g.quats, g.scales[:3], g.opacities, g.sh)
    bad = g.means.clone()
    bad[2, 1] = float("nan")
    with pytest.raises(SurfSplatInputError, match=r"gaussians.means: contains NaN"):
        Gaussians(bad, g.quats, g.scales, g.opacities, g.sh)
    with pytest.raises(SurfSplatInputError, match="gaussians.sh"):
        Gaussians(g.means, g.quats, g.scales, g.opacities, torch.zeros(4, 3, 5))
    with pytest.raises(SurfSplatInputError, match="gaussians.opacities"):
        Gaussians(g.means, g.quats, g.scales, g.opacities + 2, g.sh)
    with pytest.raises(SurfSplatInputError, match="unbatched"):
        render(Gaussians(g.means[None], g.quats[None], g.scales[None], g.opacities[None], g.sh[None]), cam, 8, 8)


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["surfel", "ewa"])
def test_gradcheck_float64_full_jacobian(mode):
    # The complete Jacobian (slow mode) on a tiny scene; the default run checks random projections.
    g0 = random_scene(3, 12, dtype=torch.float64, sh_degree=1)
    cam = pinhole(8.0, 6, 6, dtype=torch.float64)

    def fn(means, quats, scales, opacities, sh):
        out = render(Gaussians(means, quats, scales, opacities, sh), cam, 6, 6, mode=mode, alpha_threshold=0.001)
        return out.color, out.alpha, out.depth, out.normal

    inputs = tuple(
        t.detach().clone().requires_grad_(True) for t in (g0.means, g0.quats, g0.scales, g0.opacities, g0.sh)
    )
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_termination_holds_across_depth_blocks():
    # 300 stacked faint layers (alpha 0.07) end every pixel after ~127 layers; a bright layer just
    # behind that point, and far behind it, must stay invisible even when the depth axis is split
    # into blocks (a pixel that stopped in one block must not restart in the next).
    dt = torch.float64
    n = 300
    z = 2.0 + 0.01 * torch.arange(n, dtype=dt)
    means = torch.stack((torch.zeros(n, dtype=dt), torch.zeros(n, dtype=dt), z), dim=-1)
    sh = torch.full((n, 3, 1), -1.0, dtype=dt)
    opac = torch.full((n,), 0.07, dtype=dt)
    for bright in (128, 256):
        sh[bright] = 3.0
        opac[bright] = 0.02
    g = Gaussians(
        means, torch.tensor([[1.0, 0, 0, 0]], dtype=dt).expand(n, 4), torch.full((n, 2), 1e3, dtype=dt), opac, sh
    )
    cam = pinhole(10.0, 4, 4, dtype=dt)
    ref = reference_render(g, cam, 4, 4)
    for depth_block in (512, 128, 50, 7):
        out = render(
            g,
            cam,
            4,
            4,
            alpha_threshold=None,
            backend="torch",
            settings=TorchRenderSettings(max_block_depth=depth_block),
        )
        assert torch.allclose(out.color, ref[0], atol=1e-12), depth_block
        assert torch.allclose(out.alpha, ref[1], atol=1e-12), depth_block


@pytest.mark.parametrize("mode", ["surfel", "ewa"])
def test_torch_backend_gradients_repeat_bit_for_bit_with_several_threads(mode):
    # Gathers use index_select, whose backward adds in index order; advanced indexing's backward
    # adds float32 gradients with parallel atomics on multi-threaded CPUs (last bits varied per run).
    from surfsplat.data.synthetic.surfel_scene import make_scene

    scene = make_scene(resolution=48, views=2, opacity=0.5)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        grads = []
        for _ in range(3):
            params = {
                k: getattr(scene.gaussians, k).detach().clone().requires_grad_(True)
                for k in ("means", "quats", "scales", "opacities", "sh")
            }
            out = render(Gaussians(**params), scene.target, 48, 48, mode=mode, backend="torch")
            (out.color.sum() + out.depth.sum() + out.normal.sum()).backward()
            grads.append({k: p.grad for k, p in params.items()})
    finally:
        torch.set_num_threads(threads)
    assert grads[0]["means"].dtype == torch.float32 and float(grads[0]["means"].abs().max()) > 0
    for other in grads[1:]:
        for name, grad in grads[0].items():
            assert torch.equal(other[name], grad), name
