"""Gaussian adapter: the surface continuity prior, forced-alpha opacities, SH, ablations, the release mode."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scipy.spatial.transform import Rotation

from surfsplat.geometry.gaussians import Gaussians
from surfsplat.geometry.rotations import quat_to_matrix
from surfsplat.geometry.sh import SH_C0, eval_sh, sh_to_color
from surfsplat.geometry.sh_rotation import rotate_sh
from surfsplat.model.adapter import (
    AdapterConfig,
    GaussianAdapter,
    pixel_centers,
    release_quaternion_xyzw,
    release_rotation_from_normal,
    rodrigues_from_z,
    sobel_tangents,
    surface_frames,
    unproject_depth,
)
from surfsplat.utils.checks import SurfSplatInputError
from tests.helpers.adapter import (
    intrinsics,
    plane_depth,
    random_rotation,
    release_reference,
    rigid,
    sphere_depth,
    tilted_normal,
)

F64 = torch.float64


def angle_deg(a: torch.Tensor, b: torch.Tensor, unsigned: bool = False) -> torch.Tensor:
    cos = (F.normalize(a, dim=-1) * F.normalize(b, dim=-1)).sum(-1)
    if unsigned:
        cos = cos.abs()
    return torch.rad2deg(torch.acos(cos.clamp(-1, 1)))


def example_inputs(B=1, V=2, H=8, W=10, channels=32, seed=0, dtype=F64, rotate=True):
    """Smooth random depth, small raw channels, random images and (optionally rotated) cameras."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, H, dtype=dtype), torch.linspace(0, 1, W, dtype=dtype), indexing="ij")
    phase = torch.rand(B, V, 1, 1, generator=g, dtype=dtype) * 6
    depths = 2.0 + 0.3 * torch.sin(3 * xx + phase) * torch.cos(2 * yy) + 0.2 * xx
    raw = 0.3 * torch.randn(B, V, channels, H, W, generator=g, dtype=dtype)
    images = torch.rand(B, V, 3, H, W, generator=g, dtype=dtype)
    K = intrinsics(12.0, 11.0, W / 2 + 0.3, H / 2 - 0.2, dtype).expand(B, V, 3, 3).clone()
    c2w = torch.eye(4, dtype=dtype).repeat(B, V, 1, 1)
    for b in range(B):
        for v in range(V):
            R = random_rotation(100 * seed + 10 * b + v, dtype) if rotate else torch.eye(3, dtype=dtype)
            c2w[b, v] = rigid(R, [0.1 * v, -0.2 * b, 0.3])
    return depths, raw, images, K, c2w


# ---------------------------------------------------------------------------------------------- Sobel
def test_sobel_returns_exact_steps_of_a_linear_ramp_border_included() -> None:
    H, W = 6, 7
    yy, xx = torch.meshgrid(torch.arange(H, dtype=F64), torch.arange(W, dtype=F64), indexing="ij")
    a, b = torch.tensor([0.5, -1.0, 2.0], dtype=F64), torch.tensor([3.0, 0.25, -0.5], dtype=F64)
    points = xx[..., None] * a + yy[..., None] * b + 7.0
    t1, t2 = sobel_tangents(points)
    torch.testing.assert_close(t1, a.expand(H, W, 3), atol=1e-13, rtol=0)
    torch.testing.assert_close(t2, b.expand(H, W, 3), atol=1e-13, rtol=0)


def test_sobel_needs_three_by_three() -> None:
    with pytest.raises(SurfSplatInputError, match="3 x 3"):
        sobel_tangents(torch.zeros(2, 5, 3))


# ---------------------------------------------------------------------------------------------- normals
def test_sphere_normals_match_analytic_within_one_degree_away_from_silhouette() -> None:
    H = W = 128
    K = intrinsics(150.0, 150.0, 64.0, 64.0)
    centre = torch.tensor([0.1, -0.05, 3.0], dtype=F64)
    depth, hit = sphere_depth(K, H, W, centre, 1.0, background=6.0)
    points = unproject_depth(depth, K)
    frames = surface_frames(points)
    # Away from the silhouette: the pixel's whole 5x5 neighbourhood lies on the sphere.
    inner = -F.max_pool2d(-hit[None, None].to(F64), 5, stride=1, padding=2)[0, 0] > 0.5
    assert int(inner.sum()) > 5000
    analytic = points - centre  # outward normal; ours is oriented n_z >= 0, so compare lines
    err = angle_deg(frames.normals, analytic, unsigned=True)[inner]
    assert float(err.max()) < 1.0, f"max normal error {float(err.max()):.3f} deg"
    # The background plane is fronto-parallel away from the sphere.
    far = -F.max_pool2d(-(~hit)[None, None].to(F64), 5, stride=1, padding=2)[0, 0] > 0.5
    assert float(angle_deg(frames.normals[far], torch.tensor([0, 0, 1.0], dtype=F64)).max()) < 1e-6


@pytest.mark.parametrize("theta,phi", [(0, 0), (30, 90), (45, 0), (60, 37), (75, -120)])
def test_tilted_plane_normals_are_exact(theta: float, phi: float) -> None:
    # Every Sobel tangent is a weighted sum of chords of the plane, so it lies in the plane: the
    # estimated normal is exact up to rounding at every pixel, border included.
    H, W = 24, 32
    K = intrinsics(120.0, 110.0, 15.0, 12.5)
    n = tilted_normal(theta, phi)
    depth = plane_depth(K, H, W, n, distance=2.0)
    assert bool((depth > 0).all())
    frames = surface_frames(unproject_depth(depth, K))
    assert float(angle_deg(frames.normals, n.expand(H, W, 3)).max()) < 1e-5
    R = frames.rotations
    torch.testing.assert_close(R[..., :, 2], frames.normals, atol=1e-12, rtol=0)


def test_fronto_parallel_plane_gives_identity_rotation_and_pixel_footprint() -> None:
    H, W, depth_value = 9, 11, 2.5
    K = intrinsics(200.0, 150.0, 5.0, 4.0)
    frames = surface_frames(unproject_depth(torch.full((H, W), depth_value, dtype=F64), K))
    torch.testing.assert_close(frames.normals, torch.tensor([0, 0, 1.0], dtype=F64).expand(H, W, 3))
    torch.testing.assert_close(frames.rotations, torch.eye(3, dtype=F64).expand(H, W, 3, 3), atol=1e-15, rtol=0)
    footprint = torch.tensor([depth_value / 200.0, depth_value / 150.0], dtype=F64)
    torch.testing.assert_close(frames.base_scales, footprint.expand(H, W, 2), atol=1e-15, rtol=1e-12)


def test_rodrigues_matches_axis_angle_rotation() -> None:
    g = torch.Generator().manual_seed(0)
    n = F.normalize(torch.randn(200, 3, generator=g, dtype=F64), dim=-1)
    n[:, 2] = n[:, 2].abs()
    axis = F.normalize(torch.linalg.cross(torch.tensor([0, 0, 1.0], dtype=F64).expand_as(n), n), dim=-1)
    rotvec = axis * torch.acos(n[:, 2:])
    expected = torch.from_numpy(Rotation.from_rotvec(rotvec.numpy()).as_matrix())
    torch.testing.assert_close(rodrigues_from_z(n), expected, atol=1e-12, rtol=0)


def test_every_rotation_is_orthonormal_and_maps_ez_to_the_normal_float32() -> None:
    torch.manual_seed(0)
    H, W = 48, 64
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, H), torch.linspace(-1, 1, W), indexing="ij")
    depth = 3 + torch.sin(4 * xx) * torch.cos(3 * yy) + 0.5 * torch.rand(H, W)  # rough, with steep parts
    depth[:, W // 2 :] += 2.0  # a depth discontinuity
    frames = surface_frames(unproject_depth(depth, intrinsics(50.0, 50.0, 32.0, 24.0, torch.float32)), 0.1)
    R = frames.rotations
    eye = torch.eye(3).expand_as(R)
    assert float((R.transpose(-1, -2) @ R - eye).abs().max()) < 1e-6
    assert float((torch.linalg.det(R) - 1).abs().max()) < 1e-6
    assert float((R[..., :, 2] - frames.normals).abs().max()) < 1e-6
    assert float((frames.normals.norm(dim=-1) - 1).abs().max()) < 1e-6
    assert bool((frames.normals[..., 2] >= 0).all())


def test_tangent_clamp_bounds_the_base_scales_at_depth_edges() -> None:
    H, W = 8, 8
    K = intrinsics(10.0, 10.0, 4.0, 4.0)
    depth = torch.ones(H, W, dtype=F64)
    depth[:, 4:] = 50.0  # a wall far behind
    points = unproject_depth(depth, K)
    unclamped = surface_frames(points).base_scales
    clamped = surface_frames(points, tangent_clamp=0.1).base_scales
    assert float(unclamped.max()) > 10  # the edge makes a huge tangent
    assert float(clamped.max()) <= math.sqrt(2) * 0.1 + 1e-12
    # away from the edge the clamp does not bite: 1/10 and 50/10 per pixel are clamped only if > 0.1
    torch.testing.assert_close(clamped[:, :2], unclamped[:, :2])


def test_surface_frames_accepts_a_single_unbatched_map() -> None:
    frames = surface_frames(torch.rand(5, 6, 3, dtype=F64) + torch.tensor([0, 0, 2.0], dtype=F64))
    assert frames.normals.shape == (5, 6, 3) and frames.rotations.shape == (5, 6, 3, 3)
    torch.testing.assert_close(frames.normals.norm(dim=-1), torch.ones(5, 6, dtype=F64))


# ---------------------------------------------------------------------------------------------- paper mode
def test_paper_means_project_back_to_offset_pixel_centres_at_the_given_depth() -> None:
    depths, raw, images, K, c2w = example_inputs()
    out = GaussianAdapter()(depths, raw, images, K, c2w)
    B, V, H, W = depths.shape
    means = out.gaussians.means.reshape(B, V, H, W, 3)
    R, t = c2w[..., :3, :3], c2w[..., :3, 3]
    cam = torch.einsum("bvji,bvhwj->bvhwi", R, means - t[:, :, None, None])  # R^T (X - t)
    torch.testing.assert_close(cam[..., 2], depths, atol=1e-12, rtol=0)
    pix = torch.einsum("bvij,bvhwj->bvhwi", K, cam / cam[..., 2:])[..., :2]
    expected = pixel_centers(H, W, dtype=F64) + torch.sigmoid(raw[:, :, 1:3]).movedim(2, -1) - 0.5
    torch.testing.assert_close(pix, expected, atol=1e-10, rtol=0)


def test_paper_world_normals_of_a_tilted_plane_seen_by_a_rotated_camera() -> None:
    H, W = 12, 14
    K = intrinsics(40.0, 40.0, 7.0, 6.0)
    n_cam = tilted_normal(50, 20)
    depth = plane_depth(K, H, W, n_cam, 1.5)
    R = random_rotation(3)
    c2w = rigid(R, [1.0, 2.0, -0.5])
    raw = torch.zeros(1, 1, 32, H, W, dtype=F64)
    out = GaussianAdapter()(
        depth[None, None], raw, torch.rand(1, 1, 3, H, W, dtype=F64), K[None, None], c2w[None, None]
    )
    torch.testing.assert_close(out.normals[0], (R @ n_cam).expand(H * W, 3), atol=1e-10, rtol=0)
    Rw = quat_to_matrix(out.rotations[0])
    torch.testing.assert_close(Rw[:, :, 2], out.normals[0], atol=1e-10, rtol=0)
    # The world rotation is the camera rotation times the camera-frame Rodrigues rotation (Eq. 5).
    torch.testing.assert_close(Rw, (R @ rodrigues_from_z(n_cam)).expand(H * W, 3, 3), atol=1e-10, rtol=0)


def test_paper_outputs_move_with_the_camera() -> None:
    # Turning the whole rig by Q (c2w -> Q c2w) must turn means, normals, rotations and the colour
    # field by Q and leave scales and opacities unchanged.
    depths, raw, images, K, c2w = example_inputs(V=1)
    Q = rigid(random_rotation(11), [0.3, -1.0, 2.0])
    a = GaussianAdapter()(depths, raw, images, K, c2w)
    b = GaussianAdapter()(depths, raw, images, K, Q @ c2w)
    Qr, Qt = Q[:3, :3], Q[:3, 3]
    torch.testing.assert_close(b.gaussians.means, a.gaussians.means @ Qr.T + Qt, atol=1e-12, rtol=0)
    torch.testing.assert_close(b.normals, a.normals @ Qr.T, atol=1e-12, rtol=0)
    torch.testing.assert_close(quat_to_matrix(b.rotations), Qr @ quat_to_matrix(a.rotations), atol=1e-12, rtol=0)
    torch.testing.assert_close(b.scales, a.scales, atol=1e-14, rtol=0)
    torch.testing.assert_close(b.gaussians.opacities, a.gaussians.opacities)
    d = F.normalize(torch.randn(a.gaussians.means.shape[1], 3, dtype=F64), dim=-1)
    torch.testing.assert_close(eval_sh(b.gaussians.sh[0], d @ Qr.T), eval_sh(a.gaussians.sh[0], d), atol=1e-11, rtol=0)


def test_paper_activations_follow_the_closed_forms() -> None:
    depths, raw, images, K, c2w = example_inputs(rotate=False)
    B, V, H, W = depths.shape
    raw[:, :, 3:5] = torch.linspace(-3, 4, 2 * H * W, dtype=F64).reshape(1, 1, 2, H, W)  # spans both clamps
    out = GaussianAdapter()(depths, raw, images, K, c2w)
    flat = lambda x: x.movedim(2, -1).reshape(B, V * H * W, -1)  # noqa: E731  [B, V, C, H, W] -> [B, N, C]
    torch.testing.assert_close(out.gaussians.opacities, 0.6 * torch.sigmoid(flat(raw[:, :, :1]))[..., 0])
    multipliers = F.softplus(flat(raw[:, :, 3:5])).clamp(1 / 3, 3)
    assert float((multipliers == 3).float().mean()) > 0.05 and float((multipliers == 1 / 3).float().mean()) > 0.05
    torch.testing.assert_close(out.scales_mul, multipliers)
    points = unproject_depth(depths, K, torch.sigmoid(raw[:, :, 1:3]).movedim(2, -1) - 0.5)
    base = surface_frames(points, 0.1).base_scales.reshape(B, -1, 2)
    torch.testing.assert_close(out.scales[..., :2], base * multipliers)
    torch.testing.assert_close(out.scales[..., 2], torch.full_like(out.scales[..., 2], 1e-10))
    torch.testing.assert_close(out.gaussians.scales, out.scales[..., :2])
    # SH (identity camera): raw times [1, 0.025 x3, 0.00625 x5], plus (rgb - 0.5) / C0 on the DC term.
    sh_raw = flat(raw[:, :, 5:]).reshape(B, -1, 3, 9)
    mask = torch.tensor([1.0] + [0.025] * 3 + [0.00625] * 5, dtype=F64)
    expected = sh_raw * mask
    expected[..., 0] += (flat(images) - 0.5) / SH_C0
    torch.testing.assert_close(out.gaussians.sh, expected)


def test_colour_is_initialised_to_the_input_image() -> None:
    # With zero raw SH, every Gaussian shows its pixel's colour from every direction (Sec. 3.4).
    depths, raw, images, K, c2w = example_inputs()
    raw[:, :, 5:] = 0
    out = GaussianAdapter()(depths, raw, images, K, c2w)
    d = F.normalize(torch.randn(out.gaussians.means.shape[1], 3, dtype=F64), dim=-1)
    rgb = images.movedim(2, -1).reshape(1, -1, 3)
    torch.testing.assert_close(sh_to_color(out.gaussians.sh[0], d), rgb[0], atol=1e-12, rtol=0)


# ---------------------------------------------------------------------------------------------- registry
VARIANTS = [
    # (prior, primitive, opacity_max, raw channels)
    ("surface", "surfel", 0.6, 32),
    ("surface", "gaussian3d", 0.6, 33),
    ("none", "surfel", 0.6, 36),
    ("none", "gaussian3d", 1.0, 37),  # DepthSplat's 3DGS adapter: the "w/o FAB, SCP" baseline
    ("surface", "surfel", 1.0, 32),  # "w/o FAB"
]


@pytest.mark.parametrize("prior,primitive,opacity_max,channels", VARIANTS)
def test_variants_make_valid_gaussians(prior: str, primitive: str, opacity_max: float, channels: int) -> None:
    adapter = GaussianAdapter(AdapterConfig(prior=prior, primitive=primitive, opacity_max=opacity_max))
    assert adapter.num_raw_channels == channels
    depths, raw, images, K, c2w = example_inputs(channels=channels)
    raw[:, :, 0] = torch.linspace(-30, 30, raw[0, 0, 0].numel(), dtype=F64).reshape(raw.shape[-2:])
    out = adapter(depths, raw, images, K, c2w)
    g = out.gaussians
    Gaussians(g.means, g.quats, g.scales, g.opacities, g.sh, g.explicit_covariances)  # full validation
    assert float(g.opacities.max()) <= opacity_max and float(g.opacities.max()) > 0.99 * opacity_max
    if primitive == "gaussian3d":
        # The explicit covariance is R diag(s^2) R^T with all three scales.
        eig = torch.linalg.eigvalsh(g.explicit_covariances)
        torch.testing.assert_close(eig, out.scales.square().sort(dim=-1).values, atol=1e-12, rtol=1e-9)
        assert float(out.scales[..., 2].min()) > 1e-4  # a real third axis, not a flat surfel
    else:
        assert g.explicit_covariances is None
        torch.testing.assert_close(out.scales[..., 2], torch.full_like(out.scales[..., 2], 1e-10))
    assert adapter.alpha_threshold() == (None if opacity_max == 1.0 else 0.1)
    adapter.eval()
    assert adapter.alpha_threshold() == (None if opacity_max == 1.0 else 0.001)


def test_prior_none_regresses_rotation_and_scales_like_depthsplat() -> None:
    adapter = GaussianAdapter(AdapterConfig(prior="none", primitive="gaussian3d"))
    ch = adapter.channel_slices()
    assert (ch["scale"], ch["rotation"], ch["sh"]) == (slice(3, 6), slice(6, 10), slice(10, 37))
    depths, raw, images, K, c2w = example_inputs(channels=37, V=1)
    out = adapter(depths, raw, images, K, c2w)
    q = raw[0, 0, 6:10].movedim(0, -1).reshape(-1, 4)
    R_cam = quat_to_matrix(q)
    torch.testing.assert_close(quat_to_matrix(out.rotations[0]), c2w[0, 0, :3, :3] @ R_cam, atol=1e-12, rtol=0)
    scales = F.softplus(raw[0, 0, 3:6] - 4).movedim(0, -1).reshape(-1, 3)
    torch.testing.assert_close(out.scales[0], scales)
    torch.testing.assert_close(out.scales_mul, torch.ones_like(out.scales_mul))


def test_surface_prior_gaussian3d_third_scale_is_mean_tangent_scale_times_multiplier() -> None:
    adapter = GaussianAdapter(AdapterConfig(primitive="gaussian3d"))
    depths, raw, images, K, c2w = example_inputs(channels=33, V=1)
    out = adapter(depths, raw, images, K, c2w)
    m = F.softplus(raw[0, 0, 3:6]).clamp(1 / 3, 3).movedim(0, -1).reshape(-1, 3)
    base = out.scales[0, :, :2] / m[:, :2]
    torch.testing.assert_close(out.scales[0, :, 2], base.mean(-1) * m[:, 2])


# ---------------------------------------------------------------------------------------------- robustness
def _degenerate_depth(case: str, H: int = 9, W: int = 10) -> torch.Tensor:
    K = intrinsics(12.0, 11.0, W / 2 + 0.3, H / 2 - 0.2)
    if case == "constant":
        return torch.full((H, W), 2.0, dtype=F64)
    if case == "zero":
        return torch.zeros(H, W, dtype=F64)
    if case == "discontinuous":
        d = torch.full((H, W), 1.0, dtype=F64)
        d[:, W // 2 :] = 80.0
        d[H // 2 :, :3] = 1e-4
        return d
    if case == "behind_camera":
        return torch.linspace(-3.0, 2.0, H * W, dtype=F64).reshape(H, W)
    if case == "edge_on":
        # A plane tilted 89.99 degrees: nearly parallel to the rays, depth runs away across a row.
        return plane_depth(K, H, W, tilted_normal(89.99, 90), 0.05)
    raise ValueError(case)


@pytest.mark.parametrize("case", ["constant", "zero", "discontinuous", "behind_camera", "edge_on"])
@pytest.mark.parametrize(
    "cfg",
    [AdapterConfig(), AdapterConfig(mode="official"), AdapterConfig(prior="none", primitive="gaussian3d")],
    ids=["paper", "official", "none-3d"],
)
def test_degenerate_depth_gives_finite_values_and_gradients(case: str, cfg: AdapterConfig) -> None:
    adapter = GaussianAdapter(cfg)
    _, raw, images, K, c2w = example_inputs(channels=adapter.num_raw_channels, H=9, W=10)
    raw = (raw * 20).requires_grad_(True)  # saturating activations as well
    depths = _degenerate_depth(case).expand(1, 2, 9, 10).clone().requires_grad_(True)
    out = adapter(depths, raw, images, K, c2w)
    g = out.gaussians
    tensors = [g.means, g.quats, g.scales, g.opacities, g.sh, out.normals, out.scales, out.rotations, out.scales_mul]
    if g.explicit_covariances is not None:
        tensors.append(g.explicit_covariances)
    for t in tensors:
        assert bool(torch.isfinite(t).all())
    loss = sum((t * torch.randn_like(t)).sum() for t in tensors)
    loss.backward()
    assert bool(torch.isfinite(depths.grad).all()) and bool(torch.isfinite(raw.grad).all())
    if cfg.mode == "paper":
        R = quat_to_matrix(g.quats)
        torch.testing.assert_close(R[..., :, 2], out.normals, atol=1e-9, rtol=0)


def test_zero_depth_falls_back_to_fronto_parallel_frames() -> None:
    frames = surface_frames(torch.zeros(5, 5, 3, dtype=F64), 0.1)
    torch.testing.assert_close(frames.normals, torch.tensor([0, 0, 1.0], dtype=F64).expand(5, 5, 3))
    torch.testing.assert_close(frames.rotations, torch.eye(3, dtype=F64).expand(5, 5, 3, 3))


def test_gradients_reach_depth_offsets_multipliers_opacity_and_sh() -> None:
    depths, raw, images, K, c2w = example_inputs(H=6, W=6)
    depths.requires_grad_(True)
    raw.requires_grad_(True)
    out = GaussianAdapter()(depths, raw, images, K, c2w)
    g = out.gaussians
    loss = sum((t * torch.randn_like(t)).sum() for t in (g.means, g.quats, g.scales, g.opacities, g.sh))
    loss.backward()
    assert float(depths.grad.abs().min()) > 0
    for name, sl in GaussianAdapter().channel_slices().items():
        if sl.stop > sl.start:
            grad = raw.grad[:, :, sl]
            assert float(grad.abs().amax(dim=(0, 1, 3, 4)).min()) > 0, f"no gradient reaches the {name} channels"


def test_gradcheck_paper_mode_float64() -> None:
    # Analytic against numerical Jacobians for depth and the non-SH head channels (plus the DC of
    # red; the SH path is linear). Inputs stay clear of the clamps, where the Jacobian jumps.
    depths, raw, images, K, c2w = example_inputs(V=1, H=4, W=4)
    adapter = GaussianAdapter()
    head, rest = raw[:, :, :6].clone(), raw[:, :, 6:]

    def fn(depths, head):
        out = adapter(depths, torch.cat((head, rest), dim=2), images, K, c2w)
        g = out.gaussians
        return g.means, g.quats, g.scales, g.opacities, g.sh, out.normals

    assert torch.autograd.gradcheck(fn, (depths.requires_grad_(True), head.requires_grad_(True)), fast_mode=True)


def test_release_sobel_equals_the_slice_sobel() -> None:
    from surfsplat.model.adapter import release_sobel_tangents

    points = torch.randn(2, 3, 7, 9, 3, dtype=F64)
    for ours, release in zip(sobel_tangents(points), release_sobel_tangents(points)):
        torch.testing.assert_close(ours, release, atol=1e-14, rtol=0)


# ---------------------------------------------------------------------------------------------- inputs
def test_bad_inputs_raise_one_named_error() -> None:
    depths, raw, images, K, c2w = example_inputs()
    adapter = GaussianAdapter()
    with pytest.raises(SurfSplatInputError, match="raw"):
        adapter(depths, raw[:, :, :31], images, K, c2w)
    with pytest.raises(SurfSplatInputError, match="images"):
        adapter(depths, raw, images[:, :1], K, c2w)
    bad = depths.clone()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(SurfSplatInputError, match="depths"):
        adapter(bad, raw, images, K, c2w)
    K0 = K.clone()
    K0[0, 1, 0, 0] = 0
    with pytest.raises(SurfSplatInputError, match="focal"):
        adapter(depths, raw, images, K0, c2w)
    skewed = c2w.clone()
    skewed[0, 0, 0, 1] += 0.5
    with pytest.raises(SurfSplatInputError, match="c2w"):
        adapter(depths, raw, images, K, skewed)
    with pytest.raises(SurfSplatInputError, match="3 x 3"):
        adapter(depths[..., :2, :], raw[..., :2, :], images[..., :2, :], K, c2w)


def test_bad_configs_raise() -> None:
    with pytest.raises(SurfSplatInputError, match="official"):
        AdapterConfig(mode="official", prior="none")
    with pytest.raises(SurfSplatInputError, match="opacity_max"):
        AdapterConfig(opacity_max=0.0)
    with pytest.raises(SurfSplatInputError, match="prior"):
        AdapterConfig(prior="smooth")  # type: ignore[arg-type]
    with pytest.raises(SurfSplatInputError, match="sh_degree"):
        AdapterConfig(sh_degree=4)


def test_official_mode_follows_the_release_formulas_with_rotated_cameras() -> None:
    depths, raw, images, K, c2w = example_inputs(H=9, W=11, seed=3)
    H, W = depths.shape[-2:]
    out = GaussianAdapter(AdapterConfig(mode="official"))(depths, raw, images, K, c2w)
    K_norm = K / torch.tensor([W, H, 1.0], dtype=F64)[:, None]
    ref = release_reference(depths[0].numpy(), raw[0].numpy(), images[0].numpy(), K_norm[0].numpy(), c2w[0].numpy())
    g = out.gaussians
    torch.testing.assert_close(g.means[0], ref["means"], atol=1e-12, rtol=0)
    torch.testing.assert_close(g.explicit_covariances[0], ref["cov"], atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(out.normals[0], ref["normals"], atol=1e-12, rtol=0)
    torch.testing.assert_close(out.scales[0], ref["scales"], atol=1e-12, rtol=0)
    torch.testing.assert_close(out.rotations[0], ref["quats"], atol=1e-12, rtol=0)
    torch.testing.assert_close(g.opacities[0], ref["opacity"], atol=1e-14, rtol=0)
    # SH: predicted in the camera frame, turned by each view's c2w rotation with e3nn's matrices.
    Rv = c2w[0, :, :3, :3].repeat_interleave(H * W, dim=0)[:, None]
    torch.testing.assert_close(g.sh[0], rotate_sh(ref["sh_cam"], Rv, "e3nn"), atol=1e-12, rtol=0)
    # With these rotated cameras the double rotation matters: a single rotation would differ.
    single = (
        torch.from_numpy(np.stack([c2w[0, v, :3, :3].numpy().T for v in range(2)]).repeat(H * W, axis=0))
        @ ref["cov"]
        @ c2w[0, :, :3, :3].repeat_interleave(H * W, dim=0)
    )
    assert float((single - ref["cov"]).abs().max()) > 1e-3 * float(ref["cov"].abs().max())


def test_quirk_release_rotation_is_not_rodrigues() -> None:
    # Exact for fronto-parallel and 90-degree normals, off in between, and not orthonormal there.
    n = torch.stack([tilted_normal(a, 30) for a in (0.0, 45.0, 90.0)])
    R = release_rotation_from_normal(n)
    err = angle_deg(R[..., :, 2], n)
    assert float(err[0]) < 1e-6 and float(err[2]) < 1e-6
    assert float(err[1]) > 5.0
    assert float((torch.linalg.det(R[1]) - 1).abs()) > 0.01
    # The release's quaternion of a proper rotation is the usual one, in (x, y, z, w) order.
    q = release_quaternion_xyzw(rodrigues_from_z(n[:2]))
    torch.testing.assert_close(quat_to_matrix(q[:, [3, 0, 1, 2]]), rodrigues_from_z(n[:2]), atol=1e-12, rtol=0)


def test_official_and_paper_agree_where_the_release_is_exact() -> None:
    # Identity camera rotation: world = camera axes, so means, scales and normal lines agree.
    depths, raw, images, K, c2w = example_inputs(rotate=False)
    paper = GaussianAdapter()(depths, raw, images, K, c2w)
    official = GaussianAdapter(AdapterConfig(mode="official"))(depths, raw, images, K, c2w)
    torch.testing.assert_close(paper.gaussians.means, official.gaussians.means, atol=1e-12, rtol=0)
    torch.testing.assert_close(paper.scales, official.scales, atol=1e-12, rtol=0)
    torch.testing.assert_close(
        paper.normals, official.normals * torch.sign(official.normals[..., 2:]), atol=1e-9, rtol=0
    )
    torch.testing.assert_close(paper.gaussians.sh, official.gaussians.sh, atol=1e-12, rtol=0)


# Release outputs compared with the golden fixture: (our AdapterOutput field, golden key).
GOLDEN_FIELDS = {
    "means": "outputs.gaussians.means",
    "covariances": "outputs.gaussians.covariances",
    "harmonics": "outputs.gaussians.harmonics",
    "opacities": "outputs.gaussians.opacities",
    "scales_mul": "outputs.gaussians.scales_mul",
    "normals": "outputs.gaussians.normals",
    "scales": "outputs.visualization_dump.scales",
    "rotations": "outputs.visualization_dump.rotations",
}


def _golden_fields(out) -> dict[str, torch.Tensor]:
    g = out.gaussians
    fields = (
        g.means,
        g.explicit_covariances,
        g.sh,
        g.opacities,
        out.scales_mul,
        out.normals,
        out.scales,
        out.rotations,
    )
    return dict(zip(GOLDEN_FIELDS, fields))


def test_official_mode_reproduces_the_golden_release_outputs_on_a_crop(golden_subset) -> None:
    """The release's outputs at the pixels of the top-left crop of both views, from the adapter run on
    that crop alone: every output depends on a pixel's 3x3 neighbourhood only, so the crop's pixels
    away from its right and bottom edges (which the full image continues) must match, the image's
    own top and left borders included. Same relative L2 error and bound as the full test, on those
    pixels (tests/data/README.md)."""
    d, c = golden_subset.tensors, golden_subset.crop
    B, V, H, W = golden_subset.shapes["outputs.depths"]
    K = d["context.intrinsics"] * torch.tensor([W, H, 1.0])[:, None]  # normalized -> pixels; the crop starts at (0, 0)
    raw = d["crop.gaussian_head_out"].reshape(B, V, 32, c, c)
    images = d["context.image"][..., :c, :c]
    out = GaussianAdapter(AdapterConfig(mode="official"))(d["crop.depths"], raw, images, K, d["context.extrinsics"])

    v, y, x = torch.meshgrid(torch.arange(V), torch.arange(c - 1), torch.arange(c - 1), indexing="ij")
    inside = (v * c * c + y * c + x).flatten()  # crop rows, away from the crop's right and bottom edges
    full_rows = (v * H * W + y * W + x).flatten()
    position = torch.searchsorted(d["rows"].long(), full_rows)
    assert torch.equal(d["rows"].long()[position], full_rows)

    def rel(ours: torch.Tensor, key: str) -> float:
        ours = ours.reshape(B, V * c * c, -1)[:, inside].double()
        ref = d[key][:, position].reshape(ours.shape).double()
        return float((ours - ref).norm() / ref.norm())

    errors = {name: rel(t, GOLDEN_FIELDS[name]) for name, t in _golden_fields(out).items()}
    # Measured: at most 1.2e-7 (covariances); 0.33 when the crop's edge pixels are included.
    assert max(errors.values()) <= 1e-5, errors


@pytest.mark.slow
def test_official_mode_reproduces_the_golden_release_outputs(golden_dir) -> None:
    from safetensors import safe_open

    keys = [
        "context.image", "context.intrinsics", "context.extrinsics", "intermediates.gaussian_head_out",
        "outputs.depths", "outputs.gaussians.means", "outputs.gaussians.covariances",
        "outputs.gaussians.harmonics", "outputs.gaussians.opacities", "outputs.gaussians.scales_mul",
        "outputs.gaussians.normals", "outputs.visualization_dump.scales", "outputs.visualization_dump.rotations",
    ]  # fmt: skip
    with safe_open(str(golden_dir / "case_identity.safetensors"), framework="pt") as f:
        d = {k: f.get_tensor(k) for k in keys}
    images = d["context.image"]
    B, V, _, H, W = images.shape
    K = d["context.intrinsics"] * torch.tensor([W, H, 1.0])[:, None]  # normalized -> pixels
    raw = d["intermediates.gaussian_head_out"].reshape(B, V, 32, H, W)
    out = GaussianAdapter(AdapterConfig(mode="official"))(d["outputs.depths"], raw, images, K, d["context.extrinsics"])

    def rel(ours: torch.Tensor, key: str) -> float:
        ref = d[key].double()
        return float((ours.double() - ref).norm() / ref.norm())

    g = out.gaussians
    errors = {
        "means": rel(g.means, "outputs.gaussians.means"),
        "covariances": rel(g.explicit_covariances, "outputs.gaussians.covariances"),
        "harmonics": rel(g.sh, "outputs.gaussians.harmonics"),
        "opacities": rel(g.opacities, "outputs.gaussians.opacities"),
        "scales_mul": rel(out.scales_mul, "outputs.gaussians.scales_mul"),
        "normals": rel(out.normals, "outputs.gaussians.normals"),
        "scales": rel(out.scales, "outputs.visualization_dump.scales"),
        "rotations": rel(out.rotations, "outputs.visualization_dump.rotations"),
    }
    assert max(errors.values()) <= 1e-5, errors
