"""Zoom scores (`surfsplat.metrics.zoom`) against closed forms, with analytic renderers whose every zoom is known."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from surfsplat import Cameras
from surfsplat.metrics.zoom import area_down, zoom_scores
from surfsplat.utils.checks import SurfSplatInputError

W, H = 48, 32


def cameras(n: int = 2) -> Cameras:
    K = torch.tensor([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]]).expand(n, 3, 3)
    return Cameras(torch.eye(4).expand(n, 4, 4), K)


def ramp_renderer(offset: float, alpha: float = 1.0):
    """Renders the colour 0.05 + 0.8 x / W at each pixel centre, x in pixels of the x1 image (read from K's scale), plus
    `offset`: area-averaging the x1 render of a linear function gives the smaller render exactly."""

    def draw(cams: Cameras, w: int, h: int):
        scale = float(cams.K[0, 0, 0]) / 40.0
        x = (torch.arange(w, dtype=torch.float32) + 0.5) / scale  # pixel centres in x1 pixels
        colour = (0.05 + 0.8 * x / W + offset).expand(len(cams), 3, h, w)  # inside [0, 1]: no clipping
        return SimpleNamespace(color=colour.clone(), alpha=torch.full((len(cams), 1, h, w), alpha))

    return draw


def test_area_down_is_the_mean_of_each_block():
    images = torch.rand(2, 3, 9, 14, generator=torch.Generator().manual_seed(0))
    down = area_down(images, 4)
    blocks = images[..., :8, :12].reshape(2, 3, 2, 4, 3, 4).mean((3, 5))
    assert down.shape == (2, 3, 2, 3)
    assert torch.allclose(down, blocks, atol=1e-7)


def test_zoom_scores_of_a_consistent_renderer():
    """Photos = the ramp, the render = the ramp + 0.02: every
    PSNR against the photos is -10 log10(0.02^2); against the x1 render averaged down, infinite
    (float32 rounding aside)."""
    photos = ramp_renderer(0.0)(cameras(), W, H).color
    scores = zoom_scores(ramp_renderer(0.02), cameras(), photos, W, H, up=())
    expected = -10 * math.log10(0.02**2)
    assert scores.x1 == pytest.approx(expected, abs=1e-3)
    for s in (2, 4):
        assert scores.down[s] == pytest.approx(expected, abs=1e-3)
        assert scores.down_vs_render[s] > 100  # equal to float32 rounding
        assert scores.averaged[s] == pytest.approx(expected, abs=1e-3)
        assert scores.colour_shift[s] == pytest.approx(0.02, abs=1e-6)


def test_zoom_scores_of_an_inconsistent_renderer_and_the_upsampled_photos():
    """A renderer whose small renders are brighter by 0.1 and larger ones by 0.05, photos of constant
    colour 0.4 (bicubic upsampling keeps a constant): each figure is that offset's PSNR; alpha 0.5 at x1
    and 0.8 at x4 gives coverage x4 / x1 = 1.6."""

    def draw(cams: Cameras, w: int, h: int):
        scale = float(cams.K[0, 0, 0]) / 40.0
        colour = 0.4 + (0.1 if scale < 1 else 0.05 if scale > 1 else 0.0)
        alpha = 0.5 if scale <= 1 else 0.8
        return SimpleNamespace(
            color=torch.full((len(cams), 3, h, w), colour), alpha=torch.full((len(cams), 1, h, w), alpha)
        )

    photos = torch.full((2, 3, H, W), 0.4)
    scores = zoom_scores(draw, cameras(), photos, W, H).to_dict()
    assert scores["x1"] == math.inf
    for s in (2, 4):
        assert scores[f"x1/{s}"] == pytest.approx(20.0, abs=1e-4)  # 0.1 off the photos averaged down
        assert scores[f"x1/{s}_vs_render"] == pytest.approx(20.0, abs=1e-4)  # and off the x1 render
        assert scores[f"x1/{s}_target"] == math.inf  # the x1 render is the photos
        assert scores[f"x{s}"] == pytest.approx(-10 * math.log10(0.05**2), abs=1e-3)
    assert scores["coverage_x4_over_x1"] == pytest.approx(1.6)


def test_zoom_scores_refuse_bad_factors_and_images():
    photos = torch.zeros(2, 3, H, W)
    with pytest.raises(SurfSplatInputError, match="zoom factors"):
        zoom_scores(ramp_renderer(0.0), cameras(), photos, W, H, down=(1,))
    with pytest.raises(SurfSplatInputError, match="images"):
        zoom_scores(ramp_renderer(0.0), cameras(), photos[:1], W, H)
