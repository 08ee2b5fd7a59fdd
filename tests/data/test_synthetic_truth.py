"""Procedural truth: exact depth and normals, analytic visibility, area-uniform surface samples."""

from __future__ import annotations

import math

import pytest
import torch

from surfsplat import Cameras
from surfsplat.data.synthetic import (
    Lighting,
    Primitive,
    SyntheticDataset,
    SyntheticDatasetConfig,
    SyntheticScene,
    Texture,
    Viewpoints,
    geometry_truth,
    render_synthetic,
    scene_from_key,
    seen_by,
    surface_samples,
)
from surfsplat.data.synthetic.scene import WORLD_DOWN, SyntheticConfig, _frame_with_normal
from surfsplat.geometry.cameras import look_at
from surfsplat.utils.checks import SurfSplatInputError

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _room_with_sphere(radius: float = 0.5) -> SyntheticScene:
    """A 4 x 4 x 3 room (x, y in [-2, 2], z in [0, 3]) with a sphere of `radius` at (0, 0, 1.5)."""
    tex = Texture(pattern="checker", colors=torch.rand(3, 3, generator=torch.Generator().manual_seed(1)))
    walls = [
        ((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
        ((0.0, 0.0, 3.0), (0.0, 0.0, -1.0)),
        ((-2.0, 0.0, 0.0), (1.0, 0.0, 0.0)),
        ((2.0, 0.0, 0.0), (-1.0, 0.0, 0.0)),
        ((0.0, -2.0, 0.0), (0.0, 1.0, 0.0)),
        ((0.0, 2.0, 0.0), (0.0, -1.0, 0.0)),
    ]
    prims = [Primitive("plane", torch.tensor(p), _frame_with_normal(n), torch.zeros(3), tex) for p, n in walls]
    prims.append(Primitive("sphere", torch.tensor([0.0, 0.0, 1.5]), torch.eye(3), torch.tensor([radius, 0, 0]), tex))
    return SyntheticScene(
        prims, Lighting(), torch.tensor([-2.0, -2.0, 0.0]), torch.tensor([2.0, 2.0, 3.0]), 0, SyntheticConfig()
    )


def _camera(eye: tuple[float, float, float], target: tuple[float, float, float], size: int, f: float) -> Cameras:
    c2w = look_at(torch.tensor([eye]), torch.tensor([target]), WORLD_DOWN)
    K = torch.tensor([[[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]]])
    return Cameras(c2w, K)


def test_truth_depth_and_normal_of_a_sphere_seen_head_on():
    # Camera 1.5 m from the sphere's centre, looking at it: the centre ray hits at depth 1.5 - r with
    # the normal pointing back at the camera; every hit point lies on a primitive.
    scene = _room_with_sphere(0.5)
    cams = _camera((-1.5, 0.0, 1.5), (0.0, 0.0, 1.5), 32, 20.0)
    truth = geometry_truth(scene, cams, 32, 32)
    # Pixel centres straddle the image centre; the four central pixels' rays are 0.5 px off axis.
    ray = torch.tensor([0.5 / 20.0, 0.5 / 20.0, 1.0], dtype=torch.float64)
    # Along d = (a, a, 1) from distance D = 1.5: |t d - (0, 0, D)|^2 = r^2 -> smallest root.
    a2, D, r = float(ray[0] ** 2 + ray[1] ** 2), 1.5, 0.5
    t = (D - math.sqrt(D * D - (1 + a2) * (D * D - r * r))) / (1 + a2)
    assert float(truth.depth[0, 0, 15, 15]) == pytest.approx(t, abs=1e-12)
    hit = truth.points[0, :, 15, 15]
    expected_normal = (hit - torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64)) / r
    assert torch.allclose(truth.normal[0, :, 15, 15], expected_normal, atol=1e-12)
    # Every hit point is on a surface (signed distance 0 to its nearest primitive).
    points = truth.points[0].reshape(3, -1).T
    distance = torch.stack([p.signed_distance(points).abs() for p in scene.primitives]).amin(0)
    assert float(distance.max()) < 1e-9
    assert bool(truth.hit.all()) and bool(truth.mask.all())
    # The same depth and normals as the image renderer (which casts in float32).
    image = render_synthetic(scene, cams, 32, 32)
    assert torch.allclose(image.depth.double(), truth.depth, atol=1e-5)
    assert torch.allclose(image.normal.double(), truth.normal, atol=1e-4)


def test_a_sphere_point_is_seen_exactly_when_it_faces_the_camera():
    # From an eye at distance D from the centre c, the seen part of the sphere is (p - c) . (o - c) > r^2.
    scene = _room_with_sphere(0.5)
    eye = torch.tensor([-1.5, 0.3, 1.7], dtype=torch.float64)
    cams = _camera(tuple(eye.tolist()), (0.0, 0.0, 1.5), 64, 16.0)  # wide enough to see the whole sphere
    c = torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64)
    v = torch.randn(4000, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    points = c + 0.5 * torch.nn.functional.normalize(v, dim=-1)
    seen = seen_by(scene, points, Viewpoints(cams, 64, 64))
    closed_form = (points - c) @ (eye - c) > 0.25
    # Points within 1e-6 of the silhouette are left out of the comparison (grazing rays).
    clear = ((points - c) @ (eye - c) - 0.25).abs() > 1e-6
    assert torch.equal(seen[clear], closed_form[clear])
    assert 0.2 < float(closed_form.double().mean()) < 0.5
    # Behind the camera or outside its image: not seen; and the floor under the sphere is occluded.
    behind = eye + torch.tensor([[-0.3, 0.0, 0.0]], dtype=torch.float64)
    assert not bool(seen_by(scene, behind, Viewpoints(cams, 64, 64)).any())
    floor_below = torch.tensor([[0.0, 0.0, 0.0], [-1.0, 1.95, 0.0]], dtype=torch.float64)
    narrow = _camera((0.05, 0.0, 2.9), (0.0, 0.0, 0.0), 64, 200.0)  # above the sphere, sees little of the floor
    assert seen_by(scene, floor_below, Viewpoints(narrow, 64, 64)).tolist() == [False, False]


def test_truth_mask_keeps_what_context_views_see():
    scene = _room_with_sphere(0.5)
    context = _camera((-1.5, 0.0, 1.5), (0.0, 0.0, 1.5), 32, 20.0)
    opposite = _camera((1.5, 0.0, 1.5), (0.0, 0.0, 1.5), 32, 20.0)
    truth = geometry_truth(scene, opposite, 32, 32, seen_from=Viewpoints(context, 32, 32))
    # The target sees the sphere's far side (never seen by the context view) and the wall behind the
    # context camera (outside its image): both are out of the mask; the centre pixel is the sphere.
    assert bool(truth.hit.all())
    assert not bool(truth.mask[0, 0, 16, 16])
    assert float(truth.mask.double().mean()) < 0.2
    # A view scored against itself keeps every pixel.
    own = geometry_truth(scene, context, 32, 32, seen_from=Viewpoints(context, 32, 32))
    assert bool(own.mask.all())


def test_surface_samples_are_uniform_by_area():
    # Room 4 x 4 x 3: floor and ceiling 16 m^2 each, walls 12 m^2 each, sphere 4 pi r^2.
    scene = _room_with_sphere(0.5)
    n = 60_000
    s = surface_samples(scene, n, generator=torch.Generator().manual_seed(4))
    areas = torch.tensor([16.0, 16.0, 12.0, 12.0, 12.0, 12.0, math.pi], dtype=torch.float64)
    share = areas / areas.sum()
    counts = torch.bincount(s.primitive, minlength=7).double() / n
    assert torch.all((counts - share).abs() < 4 * (share * (1 - share) / n).sqrt())
    # Every sample lies on its primitive, inside the room, with that primitive's normal.
    for k, prim in enumerate(scene.primitives):
        on = s.points[s.primitive == k]
        assert float(prim.signed_distance(on).abs().max()) < 1e-9
    assert bool(((s.points >= scene.room_min.double() - 1e-9) & (s.points <= scene.room_max.double() + 1e-9)).all())
    sphere = s.primitive == 6
    radial = torch.nn.functional.normalize(s.points[sphere] - torch.tensor([0.0, 0.0, 1.5]).double(), dim=-1)
    assert torch.allclose(s.normals[sphere], radial, atol=1e-12)


def test_surface_samples_seen_from_views_are_exactly_the_visible_ones():
    scene = _room_with_sphere(0.5)
    views = Viewpoints(_camera((-1.5, 0.3, 1.7), (0.0, 0.0, 1.5), 64, 16.0), 64, 64)
    s = surface_samples(scene, 5000, seen_from=views, generator=torch.Generator().manual_seed(5))
    assert s.points.shape == (5000, 3) and bool(seen_by(scene, s.points, views).all())
    eye, c = torch.tensor([-1.5, 0.3, 1.7], dtype=torch.float64), torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64)
    on_sphere = s.points[s.primitive == 6]
    assert bool(((on_sphere - c) @ (eye - c) > 0.25 - 1e-9).all())
    hidden = _camera((-1.5, 0.3, 1.7), (-1.9, 0.3, 1.7), 8, 4.0)  # faces a wall 0.4 m away: tiny visible area
    with pytest.raises(SurfSplatInputError, match="seen by the viewpoints"):
        surface_samples(scene, 10**6, seen_from=Viewpoints(hidden, 8, 8), max_rounds=2)


def test_scene_from_key_is_the_scene_of_written_chunks():
    dataset = SyntheticDataset(SyntheticDatasetConfig(length=3, seed=90210, image_shape=(16, 16)))
    expected = dataset.scene(2)
    scene = scene_from_key("synthetic-90210-2")
    assert scene is not None and scene.seed == expected.seed
    for a, b in zip(scene.primitives, expected.primitives):
        assert a.kind == b.kind and torch.equal(a.center, b.center) and torch.equal(a.size, b.size)
    assert scene_from_key("re10k-000c3ab189999a83") is None
