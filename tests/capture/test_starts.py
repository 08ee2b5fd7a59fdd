"""The optimizer's starts: COLMAP's points on a room whose depth is exact, points made surfels as 2DGS
makes them, the network's surfels thinned, both together, and the errors where a start cannot be made."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import surfsplat
from surfsplat.capture.starts import (
    Points,
    StartConfig,
    choose_start,
    make_start,
    nearest_neighbour_scale,
    points_to_surfels,
    thin,
    triangulate,
)
from surfsplat.data.synthetic import make_scene, make_trajectory, render_synthetic
from surfsplat.geometry.sh import SH_C0
from surfsplat.utils.checks import SurfSplatInputError

SIZE = 256


@pytest.fixture(scope="module")
def room():
    """Five views along a path in a procedural room at 256x256, with the exact depth."""
    scene = make_scene(7)
    path = make_trajectory(scene, torch.Generator().manual_seed(3))
    cameras = path.cameras(torch.linspace(0, 1, 5), SIZE, SIZE)
    truth = render_synthetic(scene, cameras, SIZE, SIZE)
    return cameras, truth


def test_triangulated_points_lie_on_the_room_and_carry_its_colours(room):
    cameras, truth = room
    points = triangulate(truth.image, cameras)
    assert len(points.xyz) >= 50 and points.seconds > 0
    assert float(points.errors.max()) <= StartConfig().max_reprojection_error
    assert int(points.track_lengths.min()) >= 2
    # each point's depth from the first camera against the room's exact depth at its pixel
    c2w, K = cameras.c2w[0].double(), cameras.K[0].double()
    local = (points.xyz.double() - c2w[:3, 3]) @ c2w[:3, :3]
    pixel = local @ K.T
    u, v = pixel[:, 0] / pixel[:, 2], pixel[:, 1] / pixel[:, 2]
    inside = (local[:, 2] > 0) & (u >= 0) & (u < SIZE) & (v >= 0) & (v < SIZE)
    rows, cols = v[inside].long(), u[inside].long()
    exact = truth.depth[0, 0].double()[rows, cols]
    relative = ((local[inside, 2] - exact).abs() / exact).numpy()
    assert inside.sum() >= 30
    # most points sit on the surface they were seen on (a few land on a depth edge's other side)
    # (at 256 px and a 0.23 m baseline at 1.3 m a 0.5 px error is a 1 % depth error)
    assert np.median(relative) < 0.01 and np.mean(relative < 0.05) > 0.85
    colour = truth.image[0].permute(1, 2, 0)[rows, cols]
    assert float((colour - points.rgb[inside]).abs().median()) < 0.1


def test_triangulated_points_repeat_bit_for_bit_in_a_canonical_order(room):
    """COLMAP's threads number the points in an order that varies between runs; the start takes the points
    ordered by x, then y, then z, so two triangulations of the same photos give the same tensors (the
    surfels made from them take seeded random rotations by position in that order: another order is another
    start, 3.6 dB apart after the fit on DTU scan 24 through a fisheye lens)."""
    cameras, truth = room
    first, second = triangulate(truth.image, cameras), triangulate(truth.image, cameras)
    xyz = first.xyz.double().numpy()
    assert np.array_equal(np.lexsort((xyz[:, 2], xyz[:, 1], xyz[:, 0])), np.arange(len(xyz)))
    for field in ("xyz", "rgb", "errors", "track_lengths"):
        assert torch.equal(getattr(first, field), getattr(second, field)), field


def test_points_become_surfels_as_2dgs_makes_them():
    g = torch.Generator().manual_seed(0)
    xyz = torch.randn(40, 3, generator=g)
    rgb = torch.rand(40, 3, generator=g)
    points = Points(xyz, rgb, torch.zeros(40), torch.full((40,), 2))
    surfels = points_to_surfels(points, opacity=0.1, sh_degree=2, seed=1)
    distances = torch.cdist(xyz.double(), xyz.double())
    distances.fill_diagonal_(float("inf"))
    expected = distances.topk(3, largest=False).values.square().mean(1).sqrt()
    assert torch.allclose(surfels.scales[:, 0].double(), expected, rtol=1e-5)
    assert torch.equal(surfels.scales[:, 0], surfels.scales[:, 1])
    assert torch.allclose(surfels.sh[..., 0] * SH_C0 + 0.5, rgb, atol=1e-6)
    assert float(surfels.sh[..., 1:].abs().max()) == 0.0 and surfels.sh.shape == (40, 3, 9)
    assert torch.allclose(surfels.opacities, torch.full((40,), 0.1))
    assert torch.allclose(surfels.quats.norm(dim=-1), torch.ones(40))
    assert not torch.equal(surfels.quats, points_to_surfels(points, seed=2).quats)  # drawn, seeded
    assert torch.equal(surfels.quats, points_to_surfels(points, sh_degree=2, seed=1).quats)
    assert nearest_neighbour_scale(torch.zeros(1, 3)).tolist() == [1.0]  # a lone point: no neighbour


def _surfels(n: int, seed: int = 0) -> surfsplat.Gaussians:
    g = torch.Generator().manual_seed(seed)
    return surfsplat.Gaussians(
        torch.randn(n, 3, generator=g),
        torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1),
        torch.rand(n, 2, generator=g) + 0.1,
        torch.rand(n, generator=g) * 0.9 + 0.05,
        torch.randn(n, 3, 4, generator=g),
    )


def test_thinning_keeps_a_seeded_sample_grown_to_cover_the_same_area():
    surfels = _surfels(1000)
    kept = thin(surfels, 250, seed=3)
    assert len(kept) == 250
    index = [int((surfels.means == m).all(-1).nonzero()) for m in kept.means]
    assert index == sorted(index) and len(set(index)) == 250  # a subset, in order
    assert torch.allclose(kept.scales, surfels.scales[index] * 2.0)  # sqrt(1000 / 250)
    assert torch.equal(kept.sh, surfels.sh[index])
    assert thin(surfels, 2000) is surfels
    assert torch.equal(thin(surfels, 250, seed=3).means, kept.means)


def test_each_start_and_the_figures_it_reports(room):
    cameras, truth = room
    network = _surfels(500)
    points, figures = make_start(StartConfig(kind="points"), network, truth.image, cameras, sh_degree=3)
    assert figures["start"] == "points" and figures["start_surfels"] == figures["points"] == len(points)
    assert points.sh.shape[-1] == 16 and points.means.dtype == torch.float32
    thinned, figures = make_start(StartConfig(kind="network", budget=100), network, truth.image, cameras, 3)
    assert figures == {**figures, "start": "network", "start_surfels": 100} and "points" not in figures
    assert thinned.sh.shape[-1] == 16 and torch.equal(thinned.sh[..., :4], thin(network, 100).sh)
    both, figures = make_start(StartConfig(kind="both", budget=100), network, truth.image, cameras, 3)
    assert len(both) == len(points) + 100 and figures["start"] == "both"
    assert torch.equal(both.means[: len(points)], points.means)
    with pytest.raises(SurfSplatInputError, match="no network surfels"):
        make_start(StartConfig(kind="network"), None, truth.image, cameras)


def test_photos_that_share_nothing_give_a_clear_error(room):
    cameras, _ = room
    noise = torch.rand(5, 3, SIZE, SIZE, generator=torch.Generator().manual_seed(0))
    with pytest.raises(SurfSplatInputError, match="triangulate"):
        triangulate(noise, cameras)
    with pytest.raises(SurfSplatInputError, match="--optimize-start"):
        StartConfig(kind="colmap")


def test_a_continued_start_is_the_given_surfels_as_they_are(monkeypatch):
    """ "continue" (a saved fit) and "network" are decided without COLMAP; "continue" keeps every surfel."""
    import surfsplat.capture.starts as starts

    monkeypatch.setattr(starts, "triangulate", lambda *a, **k: pytest.fail("COLMAP ran for a start without points"))
    K = torch.tensor([[[10.0, 0.0, 4.0], [0.0, 10.0, 4.0], [0.0, 0.0, 1.0]]])
    surfels, cameras = _surfels(500), surfsplat.Cameras(torch.eye(4)[None], K)
    images = torch.zeros(1, 3, 8, 8)
    assert choose_start(StartConfig(kind="network"), images, cameras).needs_network
    continued, figures = make_start(StartConfig(kind="continue", budget=100), surfels, images, cameras, sh_degree=1)
    assert figures["start"] == "continue" and figures["start_surfels"] == 500  # the budget does not thin it
    for name in ("means", "quats", "scales", "opacities", "sh"):
        assert torch.equal(getattr(continued, name), getattr(surfels, name)), name
    with pytest.raises(SurfSplatInputError, match="no saved surfels"):
        make_start(StartConfig(kind="continue"), None, images, cameras)
