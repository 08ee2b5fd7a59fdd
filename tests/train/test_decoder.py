"""Decoder (batched predictions -> target views) and the cascade's intermediate surfels."""

from __future__ import annotations

import dataclasses

import pytest
import torch
import torch.nn.functional as F

from surfsplat import Cameras, Gaussians
from surfsplat.geometry.sh import SH_C0
from surfsplat.model.adapter import AdapterConfig
from surfsplat.model.decoder import decoder_mode, render_views
from surfsplat.model.surfsplat import PRESETS, SurfSplat, SurfSplatConfig
from surfsplat.render import render
from surfsplat.train.cascade import coarse_inverse_depth, intermediate_gaussians, num_intermediate_depths
from surfsplat.utils.checks import SurfSplatInputError


def test_convention_render_mode_follows_the_adapter() -> None:
    assert decoder_mode(AdapterConfig()) == "surfel"  # the paper: 2DGS ray-splat intersection
    assert decoder_mode(AdapterConfig(mode="official")) == "ewa"  # the release renders with 3DGS EWA
    assert decoder_mode(AdapterConfig(primitive="gaussian3d")) == "ewa"
    assert decoder_mode(AdapterConfig(), "ewa") == "ewa"
    with pytest.raises(SurfSplatInputError, match="gaussian3d"):
        decoder_mode(AdapterConfig(primitive="gaussian3d"), "surfel")


def _single_surfel_scenes(opacities: list[float], colour: tuple[float, float, float]) -> Gaussians:
    """B scenes of one fronto-parallel surfel at (0, 0, 2), each with its own opacity."""
    b = len(opacities)
    dc = (torch.tensor(colour) - 0.5) / SH_C0
    return Gaussians(
        means=torch.tensor([0.0, 0.0, 2.0]).expand(b, 1, 3).clone(),
        quats=torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(b, 1, 4).clone(),
        scales=torch.full((b, 1, 2), 0.5),
        opacities=torch.tensor(opacities).view(b, 1),
        sh=dc.view(1, 1, 3, 1).expand(b, 1, 3, 1).clone(),
    )


def _centre_cameras(count: int) -> Cameras:
    # The principal point is the centre of pixel (4, 4), so the surfel's centre is hit exactly there.
    K = torch.tensor([[20.0, 0.0, 4.5], [0.0, 20.0, 4.5], [0.0, 0.0, 1.0]])
    return Cameras(torch.eye(4).expand(count, 4, 4).clone(), K.expand(count, 3, 3).clone())


def test_forced_alpha_threshold_reaches_the_renderer() -> None:
    # At the surfel's centre the Gaussian is 1, so alpha = opacity: plain compositing gives
    # opacity * colour on black, forced alpha blending (tau 0.1 <= opacity) the colour itself.
    colour = (0.2, 0.5, 0.8)
    scenes = _single_surfel_scenes([0.5, 0.3], colour)
    cams = _centre_cameras(4)  # two target views per scene
    plain = render_views(scenes, cams, 9, 9, alpha_threshold=None)
    forced = render_views(scenes, cams, 9, 9, alpha_threshold=0.1)
    assert plain.color.shape == (2, 2, 3, 9, 9)
    expected = torch.tensor(colour)
    for b, o in enumerate((0.5, 0.3)):
        for v in range(2):
            torch.testing.assert_close(plain.color[b, v, :, 4, 4], o * expected, rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(forced.color[b, v, :, 4, 4], expected, rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(plain.alpha[b, v, 0, 4, 4], torch.tensor(o), rtol=1e-6, atol=1e-7)
            torch.testing.assert_close(forced.depth[b, v, 0, 4, 4], torch.tensor(2.0), rtol=1e-6, atol=1e-6)


def test_batch_equals_scene_by_scene_rendering() -> None:
    torch.manual_seed(0)
    b, n, v = 2, 64, 3
    scenes = Gaussians(
        means=torch.randn(b, n, 3) * 0.5 + torch.tensor([0.0, 0.0, 3.0]),
        quats=F.normalize(torch.randn(b, n, 4), dim=-1),
        scales=torch.rand(b, n, 2) * 0.2 + 0.05,
        opacities=torch.rand(b, n) * 0.6,
        sh=torch.randn(b, n, 3, 4) * 0.3,
    )
    angles = torch.linspace(-0.2, 0.2, b * v)
    c2w = torch.eye(4).repeat(b * v, 1, 1)
    c2w[:, 0, 0], c2w[:, 0, 2], c2w[:, 2, 0], c2w[:, 2, 2] = angles.cos(), angles.sin(), -angles.sin(), angles.cos()
    c2w[:, 0, 3] = angles
    cams = Cameras(c2w, torch.tensor([[16.0, 0, 8], [0, 16.0, 8], [0, 0, 1]]).expand(b * v, 3, 3).clone())
    batched = render_views(scenes, cams, 16, 16, mode="ewa", alpha_threshold=0.1)
    for i in range(b):
        alone = render(scenes.select(i), cams[i * v : (i + 1) * v], 16, 16, mode="ewa", alpha_threshold=0.1)
        assert torch.equal(batched.color[i], alone.color)
        assert torch.equal(batched.depth[i], alone.depth)
        assert torch.equal(batched.normal[i], alone.normal)


def test_decoder_errors() -> None:
    scenes = _single_surfel_scenes([0.5, 0.5], (0.5, 0.5, 0.5))
    with pytest.raises(SurfSplatInputError, match="multiple of the batch size 2"):
        render_views(scenes, _centre_cameras(3), 9, 9, alpha_threshold=0.1)
    with pytest.raises(SurfSplatInputError, match=r"means \[B, N, 3\]"):
        render_views(scenes.select(0), _centre_cameras(2), 9, 9, alpha_threshold=0.1)


# --------------------------------------------------------------------------------------- cascade
def _context(b: int = 1, size: int = 32) -> tuple[torch.Tensor, Cameras, torch.Tensor, torch.Tensor]:
    torch.manual_seed(1)
    images = torch.rand(b, 2, 3, size, size)
    c2w = torch.eye(4).repeat(b * 2, 1, 1)
    c2w[1::2, 0, 3] = 0.3  # second view 0.3 to the right
    K = torch.tensor([[30.0, 0, 16], [0, 30.0, 16], [0, 0, 1]]).expand(b * 2, 3, 3).clone()
    return images, Cameras(c2w, K), torch.full((b, 2), 0.5), torch.full((b, 2), 20.0)


def test_coarse_inverse_depth_is_the_encoders() -> None:
    """The formula recomputing the first scale's depth reproduces the encoder's own value (a
    one-scale model records that scale's inverse depth as `mv_upsampler_coarse_invdepth`)."""
    torch.manual_seed(0)
    model = SurfSplat.from_preset("tiny")
    images, cams, near, far = _context()
    with torch.no_grad():
        pred = model(images, cams, near, far, return_intermediates=True)
    ours = coarse_inverse_depth(pred.intermediates["depth_head_logits"], near.reshape(-1), far.reshape(-1))
    torch.testing.assert_close(ours, pred.intermediates["mv_upsampler_coarse_invdepth"], rtol=1e-6, atol=1e-7)
    assert num_intermediate_depths(model) == 0
    assert intermediate_gaussians(model, pred, images, cams, near, far) == []


def test_two_scale_cascade_intermediate_surfels() -> None:
    torch.manual_seed(0)
    model = SurfSplat(SurfSplatConfig(encoder=dataclasses.replace(PRESETS["tiny"], num_scales=2)))
    images, cams, near, far = _context(b=2)
    with torch.no_grad():
        pred = model(images, cams, near, far, return_intermediates=True)
        (coarse,) = intermediate_gaussians(model, pred, images, cams, near, far)
        with pytest.raises(SurfSplatInputError, match="return_intermediates=True"):
            intermediate_gaussians(model, model(images, cams, near, far), images, cams, near, far)
    # The release's intermediate depth: the first scale's inverse depth, bilinear x4 (align
    # corners), inverted; the surfels sit at exactly that camera z (all cameras look along +z).
    inv = coarse_inverse_depth(pred.intermediates["depth_head_logits"], near.reshape(-1), far.reshape(-1))
    depth = 1.0 / F.interpolate(inv, scale_factor=4, mode="bilinear", align_corners=True)  # [(B V), 1, H, W]
    z = coarse.means[..., 2].reshape(2, 2, 32, 32)
    torch.testing.assert_close(z, depth.view(2, 2, 32, 32), rtol=1e-5, atol=1e-5)
    # Colours and opacities come from the same head output as the final surfels.
    torch.testing.assert_close(coarse.opacities, pred.gaussians.opacities)
    assert (pred.gaussians.means[..., 2].reshape(2, 2, 32, 32) - z).abs().max() > 1e-3  # not the final depth
