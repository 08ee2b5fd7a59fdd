"""Zoomed-out renders drawn at the fitted zoom (`render(..., supersample=k)`, `surfsplat.render.supersample`).

- `supersample=k` is the k-times-larger render (K scaled exactly) averaged over k x k blocks, every map, on the
  torch and compiled CPU backends, and its gradient is that of the pooled render's.
- The factor against closed forms: surfels on a plane facing the fitted camera at depth d; the same camera with
  the image s times smaller, moved back to depth s d, or with a focal s times shorter needs s; zoomed in, at the
  fitted zoom, or seeing nothing: 1; capped at 4.
- A scene's x1/2 and x1/4 zoom scores then equal those of its x1 render averaged down.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from surfsplat import Cameras, Gaussians
from surfsplat.render import render
from surfsplat.render.supersample import MAX_SUPERSAMPLE, pixel_footprints, supersampling
from surfsplat.utils.checks import SurfSplatInputError

from .test_render import pinhole, random_scene


@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize("k", [2, 3])
def test_supersample_is_the_larger_render_averaged_down(backend, k):
    g = random_scene(60, seed=3)
    W, H = 20, 16
    cam = pinhole(24.0, W, H)
    fine = render(g, cam.scaled(k), W * k, H * k, backend=backend, antialiased=True)
    out = render(g, cam, W, H, backend=backend, antialiased=True, supersample=k)
    for name in ("color", "alpha", "depth", "normal"):
        got, want = getattr(out, name), F.avg_pool2d(getattr(fine, name), k)
        assert got.shape == (1, want.shape[1], H, W)
        torch.testing.assert_close(got, want, rtol=0, atol=0)
    # and it is not the render at the size asked (the scene has detail below the small pixels)
    plain = render(g, cam, W, H, backend=backend, antialiased=True)
    assert float((plain.color - out.color).abs().max()) > 1e-3


def test_supersample_gradient_is_the_pooled_renders():
    g = random_scene(40, seed=5, dtype=torch.float64)
    cam = pinhole(24.0, 12, 10, dtype=torch.float64)
    target = torch.rand(1, 3, 10, 12, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def grads(supersampled: bool):
        means = g.means.clone().requires_grad_(True)
        sh = g.sh.clone().requires_grad_(True)
        h = Gaussians(means, g.quats, g.scales, g.opacities, sh)
        if supersampled:
            colour = render(h, cam, 12, 10, backend="torch", supersample=2).color
        else:
            colour = F.avg_pool2d(render(h, cam.scaled(2), 24, 20, backend="torch").color, 2)
        (colour - target).square().sum().backward()
        return means.grad, sh.grad

    for a, b in zip(grads(True), grads(False)):
        assert float(a.abs().max()) > 0
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_supersample_refuses_bad_values():
    g = random_scene(4, seed=0)
    cam = pinhole(24.0, 8, 8)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(SurfSplatInputError, match="supersample"):
            render(g, cam, 8, 8, supersample=bad)
    with pytest.raises(SurfSplatInputError, match="supersample"):
        render(g, cam, 8, 8, backend="torch", supersample=2, absgrad=True)


def plane(depth: float, n: int = 400) -> Gaussians:
    """Surfels on the plane z = depth in front of the identity camera, facing it."""
    gen = torch.Generator().manual_seed(1)
    xy = (torch.rand(n, 2, generator=gen, dtype=torch.float64) - 0.5) * depth * 0.5
    means = torch.cat((xy, torch.full((n, 1), depth, dtype=torch.float64)), 1)
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).expand(n, 4)
    return Gaussians(
        means,
        quats,
        torch.full((n, 2), 0.01, dtype=torch.float64),
        torch.full((n,), 0.5, dtype=torch.float64),
        torch.zeros(n, 3, 1, dtype=torch.float64),
    )


def moved_back(distance: float) -> torch.Tensor:
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[2, 3] = -distance  # the camera steps back along its axis
    return c2w


def test_factor_against_closed_forms():
    d, f, W, H = 3.0, 100.0, 64, 48
    g = plane(d)
    fitted = pinhole(f, W, H, dtype=torch.float64)
    # a pixel on the plane is d / f wide
    assert float(pixel_footprints(g.means, fitted, W, H)[0]) == pytest.approx(d / f, rel=1e-12)

    def factor(cams, w, h):
        return supersampling(g, fitted, W, H, cams, w, h)

    assert factor(fitted, W, H) == 1
    assert factor(fitted.scaled(2), 2 * W, 2 * H) == 1  # zoomed in
    for s in (2, 3, 4):
        assert factor(fitted.scaled(1 / s), W // s, H // s) == s  # the image s times smaller
        assert factor(pinhole(f / s, W, H, dtype=torch.float64), W, H) == s  # a focal s times shorter
        back = pinhole(f, W, H, c2w=moved_back((s - 1) * d), dtype=torch.float64)
        assert factor(back, W, H) == s  # the camera moved back to s d
    assert factor(fitted.scaled(1 / 8), W // 8, H // 8) == MAX_SUPERSAMPLE
    assert factor(fitted.scaled(1 / 1.3), round(W / 1.3), round(H / 1.3)) == 1  # below 1.5: as asked
    away = torch.eye(4, dtype=torch.float64)
    away[0, 0], away[2, 2] = -1.0, -1.0  # turned around: sees no surfel
    assert factor(Cameras(away[None], fitted.K), W, H) == 1


def test_scene_zoom_out_scores_equal_the_x1_render_averaged_down():
    from surfsplat.reconstruction.scene import HeldOut, Scene

    g = random_scene(300, seed=7)
    W, H = 32, 24
    cams = Cameras(torch.eye(4)[None].expand(2, 4, 4).clone(), pinhole(30.0, W, H).K.expand(2, 3, 3).clone())
    cams.c2w[1, 0, 3] = 0.05
    photos = torch.rand(2, 3, H, W, generator=torch.Generator().manual_seed(2))
    scene = Scene(
        gaussians=g, cameras=cams, width=W, height=H, names=["a", "b"], near=0.5, far=10.0, mode="surfel",
        alpha_threshold=None, model="test", checkpoint="test", sources=["a", "b"], cameras_source="given",
        passes=[["a", "b"]],
    )  # fmt: skip
    scene.holdout = HeldOut(names=["a", "b"], cameras=cams, images=photos)
    ss = scene.zoom_scores().to_dict()
    asked = scene.zoom_scores(supersample=False).to_dict()
    for s in (2, 4):
        assert ss[f"x1/{s}"] == pytest.approx(ss[f"x1/{s}_target"], abs=1e-4)
        assert ss[f"x1/{s}_vs_render"] > 60  # the same image up to float rounding
        assert asked[f"x1/{s}_vs_render"] < 45  # drawn at the size asked it is not
    assert ss["x1"] == asked["x1"] and ss["x2"] == asked["x2"]  # at and above the fitted zoom: unchanged
