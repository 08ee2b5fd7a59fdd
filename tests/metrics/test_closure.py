"""Closure metrics on closed forms: a fronto-parallel plane of surfels, one per pixel of one view."""

from __future__ import annotations

import math

import pytest
import torch

from surfsplat import Cameras, Gaussians
from surfsplat.geometry.pixels import pixel_footprints, views_of_pixels
from surfsplat.geometry.sh import SH_C0
from surfsplat.metrics.closure import (
    CLOSURE_MIN,
    ClosureAccumulator,
    closure_metrics,
    format_closure_table,
)
from surfsplat.utils.checks import SurfSplatInputError

SIZE, FOCAL, DEPTH = 24, 24.0, 4.0


def _camera() -> Cameras:
    K = torch.tensor([[FOCAL, 0, SIZE / 2], [0, FOCAL, SIZE / 2], [0, 0, 1.0]])
    return Cameras(torch.eye(4)[None], K[None])


def _plane(multiplier: float, opacity: float = 0.6) -> Gaussians:
    """One surfel per pixel centre on the plane z = DEPTH, tangent scales multiplier * footprint."""
    ys, xs = torch.meshgrid(torch.arange(SIZE) + 0.5, torch.arange(SIZE) + 0.5, indexing="ij")
    means = torch.stack(((xs - SIZE / 2) / FOCAL * DEPTH, (ys - SIZE / 2) / FOCAL * DEPTH, torch.full_like(xs, DEPTH)))
    means = means.reshape(3, -1).T
    n = len(means)
    sh = torch.zeros(n, 3, 1)
    sh[:, :, 0] = (0.7 - 0.5) / SH_C0
    return Gaussians(
        means=means,
        quats=torch.tensor([1.0, 0, 0, 0]).expand(n, 4).clone(),
        scales=torch.full((n, 2), multiplier * DEPTH / FOCAL),
        opacities=torch.full((n,), opacity),
        sh=sh,
    )


def test_plane_at_multiplier_one_is_closed():
    m = closure_metrics(_plane(1.0), _camera(), SIZE, SIZE, (1, 2, 4), backend="torch")
    assert m.closure >= 0.98
    assert m.undersized == 0.0
    assert m.closed and m.problems() == []
    # Nearly every pixel is covered at every factor: Gaussians one pixel wide at pixel spacing.
    for s in (1, 2, 4):
        assert m.coverage[s][0.9] > 0.8
    assert m.size_ratio_median == pytest.approx(1.0, rel=1e-5)


def test_plane_at_a_third_is_flagged():
    m = closure_metrics(_plane(1 / 3), _camera(), SIZE, SIZE, (1, 2, 4), backend="torch")
    # At x1 the screen-space low-pass widens each surfel to ~0.7 px and the plane looks nearly whole;
    # at x4 the gaps between surfels of a third of a pixel show.
    assert m.mean_alpha[1] > 0.8
    assert m.closure < CLOSURE_MIN
    assert m.undersized == 1.0
    assert not m.closed
    assert len(m.problems()) == 2
    assert m.mean_alpha[4] < m.mean_alpha[2] < m.mean_alpha[1]


def test_coverage_levels_and_pixel_weighting():
    acc = ClosureAccumulator()
    # Scene one: 4 pixels of alpha 1 at x1; scene two: 4 pixels of alpha 0 at x1. At x2 the first
    # scene has 16 pixels of 0.6 and the second 16 of 0.95.
    acc.add_alpha({1: torch.ones(1, 1, 2, 2), 2: torch.full((1, 1, 4, 4), 0.6)})
    acc.add_alpha({1: torch.zeros(1, 1, 2, 2), 2: torch.full((1, 1, 4, 4), 0.95)})
    acc.add_surfels(_plane(1.0), torch.full((SIZE * SIZE,), DEPTH / FOCAL))
    m = acc.report()
    assert m.mean_alpha == {1: 0.5, 2: pytest.approx(0.775)}
    assert m.coverage[1] == {0.5: 0.5, 0.9: 0.5}
    assert m.coverage[2] == {0.5: 1.0, 0.9: 0.5}
    assert m.closure == pytest.approx(1.55)


def test_multiplier_bounds_and_opacity_quantiles():
    g = _plane(1.0)
    n = len(g)
    r = 3.0
    multipliers = torch.ones(n, 2)
    multipliers[: n // 4] = 1 / r  # a quarter at the lower bound (both axes)
    multipliers[n // 4 : n // 4 + n // 8, 0] = r  # an eighth of the rows at the upper bound on one axis
    g.opacities = torch.linspace(0, 1, n)
    acc = ClosureAccumulator()
    acc.add_alpha({1: torch.ones(1, 1, 2, 2)})
    acc.add_surfels(g, torch.full((n,), DEPTH / FOCAL), multipliers, r)
    m = acc.report()
    assert m.multiplier_at_low == pytest.approx(0.25)
    assert m.multiplier_at_high == pytest.approx(1 / 16)
    assert m.opacity_quantiles[0.5] == pytest.approx(0.5, abs=1e-6)
    assert m.opacity_quantiles[0.1] == pytest.approx(0.1, abs=1e-6)
    assert m.closure is None and not m.closed  # only x1 was added


def test_pixel_footprints_match_depth_over_focal():
    g = _plane(1.0)
    cams = _camera()
    by_view = pixel_footprints(g, cams, SIZE, SIZE, views_of_pixels(1, SIZE, SIZE))
    finest = pixel_footprints(g, cams, SIZE, SIZE)
    assert torch.allclose(by_view, torch.full_like(by_view, DEPTH / FOCAL))
    assert torch.equal(by_view, finest)
    # A second camera twice as close sees the plane's centre: the finest footprint halves there.
    c2w = torch.eye(4)
    c2w[2, 3] = DEPTH / 2
    both = Cameras(torch.stack((torch.eye(4), c2w)), cams.K.expand(2, 3, 3).clone())
    finest = pixel_footprints(g, both, SIZE, SIZE)
    centre = (SIZE // 2) * SIZE + SIZE // 2
    assert finest[centre] == pytest.approx(DEPTH / 2 / FOCAL)
    corner = 0  # projects outside the near camera's frame (x = -2 at depth 2, beyond the half width 1)
    assert finest[corner] == pytest.approx(DEPTH / FOCAL)


def test_views_of_pixels_and_errors():
    assert views_of_pixels(2, 2, 3).tolist() == [0] * 6 + [1] * 6
    with pytest.raises(SurfSplatInputError, match="views"):
        pixel_footprints(_plane(1.0), _camera(), SIZE, SIZE, torch.ones(SIZE * SIZE, dtype=torch.long))
    with pytest.raises(SurfSplatInputError, match="nothing was added"):
        ClosureAccumulator().report()
    with pytest.raises(SurfSplatInputError, match="x1"):
        closure_metrics(_plane(1.0), _camera(), SIZE, SIZE, (2, 4))


def test_table_and_json_name_the_verdict():
    closed = closure_metrics(_plane(1.0), _camera(), SIZE, SIZE, (1, 4), backend="torch")
    broken = closure_metrics(_plane(1 / 3), _camera(), SIZE, SIZE, (1, 4), backend="torch")
    table = format_closure_table({"whole": closed, "thirds": broken})
    assert "| whole |" in table and "| thirds |" in table
    assert table.splitlines()[2].endswith("| yes |") and table.splitlines()[3].endswith("| no |")
    data = broken.to_json()
    assert data["closed"] is False and math.isclose(data["closure"], broken.closure)
    assert data["undersized_share"] == 1.0 and len(data["problems"]) == 2
