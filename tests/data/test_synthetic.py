"""Synthetic scenes: closed-form depth, conventions, determinism and native high-resolution truth."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from surfsplat import Cameras
from surfsplat.data.synthetic import (
    Lighting,
    Primitive,
    SyntheticDataset,
    SyntheticDatasetConfig,
    SyntheticScene,
    Texture,
    make_scene,
    make_trajectory,
    pixel_rays,
    render_rays,
    render_synthetic,
)
from surfsplat.data.synthetic.scene import SyntheticConfig

# Many small elementwise ops: single-threaded (see conftest.one_torch_thread).
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _texture(pattern: str = "checker", frequency: float = 1.0, detail: float = 0.0) -> Texture:
    colors = torch.tensor([[0.9, 0.1, 0.1], [0.1, 0.1, 0.9], [0.5, 0.5, 0.5]])
    return Texture(pattern=pattern, colors=colors, frequency=frequency, detail=detail, seed=3)


def _flat_light() -> Lighting:
    # Ambient only: the image is the albedo, which makes texture checks exact.
    return Lighting(ambient=1.0, directional=0.0, lamp=0.0)


def _scene(prims: list[Primitive]) -> SyntheticScene:
    return SyntheticScene(prims, _flat_light(), torch.full((3,), -10.0), torch.full((3,), 10.0), 0, SyntheticConfig())


def _plane(
    point: tuple[float, float, float], normal: tuple[float, float, float], texture: Texture | None = None
) -> Primitive:
    n = F.normalize(torch.tensor(normal, dtype=torch.float64), dim=0)
    helper = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    if abs(float(n @ helper)) > 0.9:
        helper = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    u = F.normalize(torch.linalg.cross(helper, n), dim=0)
    v = torch.linalg.cross(n, u)
    return Primitive(
        "plane", torch.tensor(point), torch.stack([u, v, n], 1).float(), torch.zeros(3), texture or _texture()
    )


def _camera(width: int, height: int, f: float, c2w: torch.Tensor | None = None) -> Cameras:
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])[None]
    return Cameras(torch.eye(4)[None] if c2w is None else c2w[None], K)


# ---------------------------------------------------------------------------- closed-form depth
def test_fronto_parallel_plane_depth_is_constant() -> None:
    scene = _scene([_plane((0.0, 0.0, 3.25), (0.0, 0.0, -1.0))])
    out = render_synthetic(scene, _camera(40, 30, 35.0), 40, 30, dtype=torch.float64)
    torch.testing.assert_close(out.depth, torch.full_like(out.depth, 3.25), rtol=0, atol=1e-12)
    # Normal faces the camera (-z in world = camera here).
    torch.testing.assert_close(out.normal[0, :, 5, 7], torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))


def test_tilted_plane_depth_matches_closed_form_at_x1_and_x4() -> None:
    # Plane n . X = n . p0; camera ray X = z K^-1 [u, v, 1] => z = n . p0 / (n . K^-1 [u, v, 1]).
    n = F.normalize(torch.tensor([0.3, -0.2, -1.0], dtype=torch.float64), dim=0)
    p0 = torch.tensor([0.1, 0.2, 4.0], dtype=torch.float64)
    scene = _scene([_plane(tuple(p0.tolist()), tuple(n.tolist()))])
    for s in (1, 4):
        W, H, f = 32 * s, 24 * s, 30.0 * s
        out = render_synthetic(scene, _camera(W, H, f), W, H, dtype=torch.float64)
        v, u = torch.meshgrid(
            torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5, indexing="ij"
        )
        rays = torch.stack([(u - W / 2) / f, (v - H / 2) / f, torch.ones_like(u)], -1)
        expected = (n @ p0) / (rays @ n)
        # The plane's stored centre/rotation are float32; that rounding is the only error source.
        torch.testing.assert_close(out.depth[0, 0], expected, rtol=2e-6, atol=0)


def test_sphere_depth_and_normal_match_closed_form() -> None:
    c = torch.tensor([0.3, -0.2, 5.0], dtype=torch.float64)
    r = 1.5
    sphere = Primitive("sphere", c.float(), torch.eye(3), torch.tensor([r, 0.0, 0.0]), _texture())
    out = render_synthetic(_scene([sphere]), _camera(64, 64, 60.0), 64, 64, dtype=torch.float64)
    v, u = torch.meshgrid(
        torch.arange(64, dtype=torch.float64) + 0.5, torch.arange(64, dtype=torch.float64) + 0.5, indexing="ij"
    )
    d = torch.stack([(u - 32) / 60, (v - 32) / 60, torch.ones_like(u)], -1)  # camera-z = 1
    # |t d - c|^2 = r^2: nearest root.
    a = (d * d).sum(-1)
    b = -2 * (d @ c)
    disc = b * b - 4 * a * (c @ c - r * r)
    hit = disc > 0
    t = (-b - disc.clamp_min(0).sqrt()) / (2 * a)
    assert 0.2 < hit.double().mean() < 0.9
    torch.testing.assert_close(out.depth[0, 0][hit], t[hit], rtol=1e-6, atol=0)
    assert bool((out.depth[0, 0][~hit] == 0).all())  # nothing else in this scene
    normal = F.normalize(t[..., None] * d - c, dim=-1)
    torch.testing.assert_close(out.normal[0].permute(1, 2, 0)[hit], normal[hit], rtol=0, atol=1e-5)


def test_box_and_cylinder_faces_at_known_distances() -> None:
    # A box face at z = 4 - 0.5 and a cylinder's cap at z = 3 - 0.25, each seen head-on.
    box = Primitive("box", torch.tensor([-1.0, 0.0, 4.0]), torch.eye(3), torch.tensor([0.6, 0.6, 0.5]), _texture())
    cyl_rot = torch.eye(3)  # axis along camera z: the cap faces the camera
    cyl = Primitive("cylinder", torch.tensor([1.0, 0.0, 3.0]), cyl_rot, torch.tensor([0.5, 0.25, 0.0]), _texture())
    cams = _camera(64, 32, 20.0)
    out = render_synthetic(_scene([box, cyl]), cams, 64, 32, dtype=torch.float64)
    K = cams.K[0].double()
    u_box = int(K[0, 2] + K[0, 0] * (-1.0 / 3.5))
    u_cyl = int(K[0, 2] + K[0, 0] * (1.0 / 2.75))
    assert float(out.depth[0, 0, 16, u_box]) == pytest.approx(3.5, abs=1e-9)
    assert float(out.depth[0, 0, 16, u_cyl]) == pytest.approx(2.75, abs=1e-9)
    assert int(out.primitive[0, 0, 16, u_box]) == 0 and int(out.primitive[0, 0, 16, u_cyl]) == 1


def test_cylinder_side_depth_matches_closed_form() -> None:
    # Upright cylinder (axis = world y here) seen from the side: along the image row through the
    # axis, the hit depth is zc - sqrt(r^2 - x^2) for x = z u (solved exactly below).
    R = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # local z -> world y
    cyl = Primitive("cylinder", torch.tensor([0.0, 0.0, 5.0]), R, torch.tensor([1.0, 3.0, 0.0]), _texture())
    out = render_synthetic(_scene([cyl]), _camera(64, 64, 40.0), 64, 64, dtype=torch.float64)
    u = (torch.arange(64, dtype=torch.float64) + 0.5 - 32) / 40  # x / z along the middle row (v = 32.5 -> y small)
    vrow = 32
    y_over_z = (vrow + 0.5 - 32) / 40
    # (z u)^2 + (z - 5)^2 = 1 -> (u^2 + 1) z^2 - 10 z + 24 = 0
    a, b, c = u * u + 1, -10.0, 24.0
    disc = b * b - 4 * a * c
    hit = disc >= 0
    z = (-b - disc.clamp_min(0).sqrt()) / (2 * a)
    assert bool((z[hit] * abs(y_over_z) < 3.0).all())
    torch.testing.assert_close(out.depth[0, 0, vrow][hit], z[hit], rtol=1e-6, atol=0)


def test_generated_scene_depth_lies_on_the_hit_surface() -> None:
    scene = make_scene(11)
    path = make_trajectory(scene, torch.Generator().manual_seed(1))
    cams = path.cameras(torch.tensor([0.0, 0.5, 1.0]), 48, 40)
    out = render_synthetic(scene, cams, 48, 40)
    assert bool((out.primitive >= 0).all())  # a closed room: every ray hits something
    origins, dirs = pixel_rays(cams, 48, 40, torch.tensor([[0.5, 0.5]]), torch.float32)
    points = origins[:, 0] + out.depth.permute(0, 2, 3, 1) * dirs[:, 0]  # [C, H, W, 3]
    pts = points.reshape(-1, 3)
    prim = out.primitive.reshape(-1)
    kinds_seen = set()
    for k, p in enumerate(scene.primitives):
        sel = prim == k
        if not bool(sel.any()):
            continue
        kinds_seen.add(p.kind)
        sdf = p.signed_distance(pts[sel])
        assert float(sdf.abs().max()) < 2e-5, (k, p.kind)
        # The rendered normal is the surface normal (up to its camera-facing sign).
        n_local = p.local_normal(p.to_local(pts[sel]))
        n_world = n_local @ p.rotation.T
        rendered = out.normal.permute(0, 2, 3, 1).reshape(-1, 3)[sel]
        assert float((rendered * n_world).sum(-1).abs().min()) > 0.999
    assert "plane" in kinds_seen and len(kinds_seen) >= 2
    # Every visible point is within the configured depth bounds.
    assert float(out.depth.min()) >= scene.config.near and float(out.depth.max()) <= scene.config.far


# ---------------------------------------------------------------------------------- conventions
def test_convention_pixel_centres_at_half_integers() -> None:
    # A vertical checker edge on a fronto-parallel wall at depth 2 seen with f = 10, cx = W/2,
    # placed at image coordinate u = W/2 + 0.25. With pixel centres at j + 0.5, column W/2
    # (centre W/2 + 0.5) lies right of the edge; with centres at integers it would lie left.
    # The wall's local x axis is world y, local y is world x: its texture edge local y = 0 is at
    # world x = 0.05 (u = W/2 + 10 * 0.05 / 2); the centre's y offset keeps the other edge out of view.
    wall = _plane((0.05, 5.0, 2.0), (0.0, 0.0, -1.0), _texture("checker", frequency=0.25))
    W = 16
    out = render_synthetic(_scene([wall]), _camera(W, 8, 10.0), W, 8, dtype=torch.float64)
    reddish = out.image[0, 0] > out.image[0, 2]  # [H, W]: which checker colour each pixel shows
    assert bool((reddish[:, : W // 2] == reddish[0, 0]).all())
    assert bool((reddish[:, W // 2 :] != reddish[0, 0]).all())


def test_convention_opencv_axes() -> None:
    # Identity c2w looks along +z; +x appears to the right (larger u), +y lower (larger v).
    def centroid(center: tuple[float, float, float]) -> tuple[float, float]:
        s = Primitive("sphere", torch.tensor(center), torch.eye(3), torch.tensor([0.3, 0.0, 0.0]), _texture())
        out = render_synthetic(_scene([s]), _camera(64, 64, 50.0), 64, 64)
        mask = out.primitive[0, 0] == 0
        ii, jj = mask.nonzero().double().unbind(-1)
        return float(jj.mean()) + 0.5, float(ii.mean()) + 0.5

    u, v = centroid((0.8, 0.0, 4.0))
    assert u > 32 + 5 and abs(v - 32) < 1
    u, v = centroid((0.0, 0.8, 4.0))
    assert v > 32 + 5 and abs(u - 32) < 1


def test_trajectory_cameras_are_opencv_look_at() -> None:
    scene = make_scene(5)
    path = make_trajectory(scene, torch.Generator().manual_seed(2))
    cams = path.cameras(torch.tensor([0.0, 1.0]), 64, 48)
    forward = cams.c2w[:, :3, 2]
    torch.testing.assert_close(forward[0], F.normalize(path.target0 - path.eye0, dim=0), atol=1e-6, rtol=0)
    torch.testing.assert_close(cams.centers[1], path.eye1, atol=1e-6, rtol=0)
    # No roll: the camera x axis is horizontal and y points down (world z up).
    assert float(cams.c2w[:, 2, 0].abs().max()) < 1e-6
    assert bool((cams.c2w[:, 2, 1] < 0).all())
    baseline = float((path.eye1 - path.eye0).norm())
    lo, hi = scene.config.baseline
    assert lo - 1e-6 <= baseline <= hi + 1e-6


# --------------------------------------------------------------------------------- determinism
def test_same_seed_same_pixels_and_different_seed_different_pixels() -> None:
    cfg = SyntheticDatasetConfig(length=3, seed=7, image_shape=(24, 32), supersample=1)
    a = SyntheticDataset(cfg)[1]
    b = SyntheticDataset(cfg)[1]
    for part in ("context", "target"):
        for key in a[part]:
            assert torch.equal(a[part][key], b[part][key]), (part, key)
    c = SyntheticDataset(SyntheticDatasetConfig(length=3, seed=8, image_shape=(24, 32), supersample=1))[1]
    assert float((a["context"]["image"] - c["context"]["image"]).abs().mean()) > 0.02


# --------------------------------------------------------------- native high-resolution truth
@pytest.fixture(scope="module")
def hr_setup() -> tuple[SyntheticScene, Cameras, torch.Tensor, torch.Tensor]:
    """A room view rendered natively at x4 (192x160) and at x1 (48x40) with 4x4 supersampling."""
    scene = make_scene(21)
    cams = make_trajectory(scene, torch.Generator().manual_seed(3)).cameras(torch.tensor([0.3]), 48, 40)
    hr = render_synthetic(scene, cams.scaled(4), 192, 160)
    lo = render_synthetic(scene, cams, 48, 40, supersample=4)
    return scene, cams, hr, lo


def test_x4_pixels_are_rays_through_the_x1_image_plane(hr_setup) -> None:
    scene, cams, hr, _ = hr_setup
    s = 4
    # x4 pixel (4i + b, 4j + a) is the x1 ray through (j + (a + 0.5)/4, i + (b + 0.5)/4).
    for a, b in ((1, 2), (3, 0)):
        offs = torch.tensor([[(a + 0.5) / s, (b + 0.5) / s]])
        o, d = pixel_rays(cams, 48, 40, offs, torch.float32)
        rgb, depth, _, _ = render_rays(scene, o.reshape(-1, 3), d.reshape(-1, 3))
        sub = hr.image[0, :, b::s, a::s].permute(1, 2, 0).reshape(-1, 3)
        sub_depth = hr.depth[0, 0, b::s, a::s].reshape(-1)
        torch.testing.assert_close(sub_depth, depth, rtol=1e-5, atol=0)
        # Colours agree except where float rounding of the ray moves it across a hard texture edge.
        differs = (sub - rgb).abs().amax(-1) > 1e-4
        assert float(differs.double().mean()) < 0.002


def test_supersampled_x1_equals_pooled_x4(hr_setup) -> None:
    _, _, hr, lo = hr_setup
    pooled = F.avg_pool2d(hr.image, 4)
    diff = (pooled - lo.image).abs()
    assert float(diff.mean()) < 1e-4
    assert float((diff > 1e-3).double().mean()) < 0.01


def test_x4_holds_detail_a_x1_image_cannot(hr_setup) -> None:
    _, _, hr, lo = hr_setup
    up = F.interpolate(lo.image, scale_factor=4, mode="bicubic", align_corners=False).clamp(0, 1)
    mse = float(((hr.image - up) ** 2).mean())
    psnr = -10 * math.log10(mse)
    # A bicubic upsampling of the x1 image misses the x4 truth's fine texture: well below the
    # ~40+ dB an upsampling of itself would score.
    assert psnr < 32.0
    # Energy above the x1 Nyquist frequency: what remains after removing the 4x4 block means.
    residual = hr.image - F.interpolate(F.avg_pool2d(hr.image, 4), scale_factor=4, mode="nearest")
    assert float(residual.pow(2).mean().sqrt()) > 0.02


# -------------------------------------------------------------------------------------- dataset
def test_dataset_sample_layout_and_geometry() -> None:
    ds = SyntheticDataset(SyntheticDatasetConfig(length=2, image_shape=(32, 48), num_target_views=3, supersample=1))
    sample = ds[0]
    ctx, tgt = sample["context"], sample["target"]
    assert ctx["image"].shape == (2, 3, 32, 48) and tgt["image"].shape == (3, 3, 32, 48)
    assert ctx["depth"].shape == (2, 1, 32, 48) and tgt["normal"].shape == (3, 3, 32, 48)
    assert float(ctx["image"].min()) >= 0 and float(ctx["image"].max()) <= 1
    Cameras(ctx["c2w"], ctx["K"])  # validates rigid c2w and pixel K
    torch.testing.assert_close(ctx["K"][:, :2, 2], torch.tensor([[24.0, 16.0]]).expand(2, 2))
    near, far = float(ctx["near"][0]), float(ctx["far"][0])
    for views in (ctx, tgt):
        assert float(views["depth"].min()) >= near and float(views["depth"].max()) <= far
        torch.testing.assert_close(
            views["normal"].norm(dim=1), torch.ones(len(views["image"]), 32, 48), atol=1e-5, rtol=0
        )
    # Targets lie on the path between the two context cameras.
    c0, c1 = ctx["c2w"][0, :3, 3], ctx["c2w"][1, :3, 3]
    seg = c1 - c0
    for t in tgt["c2w"][:, :3, 3]:
        s = float((t - c0) @ seg / (seg @ seg))
        assert -1e-5 <= s <= 1 + 1e-5
        assert float((c0 + s * seg - t).norm()) < 1e-4


def test_dataset_depth_reprojects_between_context_views() -> None:
    ds = SyntheticDataset(SyntheticDatasetConfig(length=1, image_shape=(40, 40), supersample=1))
    ctx = ds[0]["context"]
    cams = Cameras(ctx["c2w"], ctx["K"])
    o, d = pixel_rays(cams[0], 40, 40, torch.tensor([[0.5, 0.5]]), torch.float32)
    X = (o[0, 0] + ctx["depth"][0, 0, :, :, None] * d[0, 0]).reshape(-1, 3)
    w2c = cams.w2c[1]
    x = X @ w2c[:3, :3].T + w2c[:3, 3]
    uv = x @ cams.K[1].T
    uv = uv[:, :2] / uv[:, 2:]
    j, i = torch.floor(uv[:, 0]).long(), torch.floor(uv[:, 1]).long()
    inside = (i >= 0) & (i < 40) & (j >= 0) & (j < 40) & (x[:, 2] > 0)
    # Compare z in view 1 with the depth rendered there (bilinear lookup).
    grid = torch.stack([uv[:, 0] / 40 * 2 - 1, uv[:, 1] / 40 * 2 - 1], -1)
    z1 = F.grid_sample(ctx["depth"][1:2], grid[None, None], align_corners=False)[0, 0, 0]
    rel = ((z1 - x[:, 2]).abs() / x[:, 2])[inside]
    # Most points are visible in both views and land on the same surface (occlusions and depth
    # edges make the rest).
    assert float(inside.double().mean()) > 0.5
    assert float(rel.median()) < 1e-2
    assert float((rel < 0.02).double().mean()) > 0.8


def test_dataset_collates_into_batches() -> None:
    ds = SyntheticDataset(SyntheticDatasetConfig(length=2, image_shape=(16, 16), supersample=1))
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=2)))
    assert batch["context"]["image"].shape == (2, 2, 3, 16, 16)
    assert batch["target"]["c2w"].shape == (2, 4, 4, 4)
    assert batch["scene"] == ["synthetic-0-0", "synthetic-0-1"]
    assert not torch.equal(batch["context"]["image"][0], batch["context"]["image"][1])


def test_synthetic_chunks_stream_like_any_chunk_dataset(tmp_path) -> None:
    from surfsplat.data import BoundedViewSampler, BoundedViewSamplerConfig, ChunkDataset, ChunkDatasetConfig
    from surfsplat.data.synthetic import write_synthetic_chunks

    index = write_synthetic_chunks(tmp_path, num_scenes=2, seed=4, image_shape=(16, 20), num_frames=6, supersample=1)
    assert sorted(index) == ["synthetic-4-0", "synthetic-4-1"]
    sampler = BoundedViewSampler(
        BoundedViewSamplerConfig(
            min_distance_between_context_views=3, max_distance_between_context_views=5, warm_up_steps=0
        )
    )
    ds = ChunkDataset(
        ChunkDatasetConfig(roots=[tmp_path], image_shape=None, near=0.5, far=15.0, shuffle=False), sampler
    )
    samples = list(ds)
    assert [s["scene"] for s in samples] == ["synthetic-4-0", "synthetic-4-1"]
    # Same pixels (8-bit) and depth (millimetres) as a direct rendering of the same frames.
    dataset = SyntheticDataset(SyntheticDatasetConfig(length=2, seed=4, image_shape=(16, 20)))
    scene = dataset.scene(1)
    idx = samples[1]["context"]["index"]
    cams = dataset.trajectory(1, scene).cameras(torch.linspace(0, 1, 6, dtype=torch.float64)[idx], 20, 16)
    truth = render_synthetic(scene, cams, 20, 16)
    ctx = samples[1]["context"]
    assert float((ctx["image"] - truth.image).abs().max()) <= 0.5 / 255 + 1e-6
    assert float((ctx["depth"] - truth.depth).abs().max()) <= 0.5e-3 + 1e-6
    torch.testing.assert_close(ctx["c2w"], cams.c2w, atol=2e-5, rtol=0)
    assert set(samples[0]["context"]) == {"image", "c2w", "K", "near", "far", "index", "depth"}
