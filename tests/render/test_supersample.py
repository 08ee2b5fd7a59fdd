"""Zoomed-out renders drawn at the fitted zoom (`render(..., supersample=k)`, `surfsplat.render.supersample`).

- `supersample=k` is the k-times-larger render (K scaled exactly) averaged over k x k blocks, every map, on the
  torch and compiled CPU backends, and its gradient is that of the pooled render's.
- The factor against closed forms: surfels on a plane facing the fitted camera at depth d; the same camera with
  the image s times smaller, moved back to depth s d, or with a focal s times shorter needs s; zoomed in, at the
  fitted zoom, or seeing nothing: 1; capped at 4.
- A scene's x1/2 and x1/4 zoom scores then equal those of its x1 render averaged down.
- Zoomed in (`render(..., filter_zoom=z)`): a surfel far below a pixel drawn as the filter of a camera z times
  coarser, o exp(-|p - c|^2 / z^2) (EWA: the dilation 0.3 z^2), on both backends, whose gradients agree;
  `zoom_plan` picks it for views zoomed in 1.5 x or more with z the zoom, and the surface of thin surfels below
  drawn with it at x4 is the x1 render, finer.
- On gsplat (`zoom_in_floor`): the tangent scales' floor against its closed form (the fitted footprint d / f
  times sqrt(1 - 1 / z^2) / sqrt(2) for the zoom z, however the view zooms in), surfels wider than it and views
  below 1.5 x untouched; on a surface of surfels a tenth of a pixel wide it keeps the x4 render covered and equal
  to the x1 render where, drawn as asked, the surface breaks into dots.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from surfsplat import Cameras, Gaussians
from surfsplat.render import CpuRenderSettings, TorchRenderSettings, render
from surfsplat.render.supersample import (
    MAX_SUPERSAMPLE,
    ZoomPlan,
    pixel_footprints,
    supersampling,
    zoom_in_floor,
    zoom_plan,
)
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
    for bad in (0.5, 0, float("nan"), float("inf"), True, "2"):
        with pytest.raises(SurfSplatInputError, match="filter_zoom"):
            render(g, cam, 8, 8, filter_zoom=bad)
    for other in ({"supersample": 2}, {"absgrad": True}):
        with pytest.raises(SurfSplatInputError, match="filter_zoom"):
            render(g, cam, 8, 8, backend="torch", filter_zoom=2, **other)


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
    assert ss["x1"] == asked["x1"]  # at the fitted zoom: unchanged


def test_zoom_in_floor_against_closed_forms():
    d, f, W, H = 3.0, 100.0, 64, 48
    g = plane(d)  # tangent scales 0.01, a third of the pixel footprint d / f = 0.03
    fitted = pinhole(f, W, H, dtype=torch.float64)

    def floor_of(cams, w, h):
        return zoom_in_floor(g, fitted, W, H, cams, w, h)

    assert floor_of(fitted, W, H) is g  # the fitted zoom
    assert floor_of(fitted.scaled(1.3), round(1.3 * W), round(1.3 * H)) is g  # below 1.5: as asked
    assert floor_of(fitted.scaled(1 / 2), W // 2, H // 2) is g  # zoomed out: supersampled instead
    for z in (2.0, 4.0):
        expected = (d / f) * (1 - 1 / z**2) ** 0.5 / 2**0.5
        closer = pinhole(f, W, H, c2w=moved_back(-(1 - 1 / z) * d), dtype=torch.float64)  # at depth d / z
        for cams, w, h in ((fitted.scaled(z), int(z * W), int(z * H)), (closer, W, H)):
            out = floor_of(cams, w, h)
            assert torch.allclose(out.scales, torch.full_like(g.scales, expected), rtol=1e-9, atol=0)
            assert out.means is g.means and out.opacities is g.opacities and out.sh is g.sh
    wide = Gaussians(g.means, g.quats, torch.full_like(g.scales, 0.05), g.opacities, g.sh)
    assert torch.equal(zoom_in_floor(wide, fitted, W, H, fitted.scaled(4), 4 * W, 4 * H).scales, wide.scales)


def test_zoom_in_floor_keeps_a_surface_of_thin_surfels_whole():
    """A wall of surfels a tenth of a pixel wide, one a pixel apart: at x1 the low-pass draws it whole; at x4
    drawn as asked it is dots on black, with the floor it is the x1 render, finer."""
    d, f, W, H = 3.0, 40.0, 32, 24
    step = d / f  # one pixel on the wall
    ys, xs = torch.meshgrid(torch.arange(-16, 16), torch.arange(-20, 20), indexing="ij")
    xy = torch.stack((xs.flatten() + 0.5, ys.flatten() + 0.5), -1).double() * step
    n = len(xy)
    colours = torch.rand(n, 3, 1, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    g = Gaussians(
        torch.cat((xy, torch.full((n, 1), d, dtype=torch.float64)), 1),
        torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).expand(n, 4),
        torch.full((n, 2), step / 10, dtype=torch.float64),
        torch.full((n,), 0.9, dtype=torch.float64),
        (colours - 0.5) / 0.28209479177387814,  # SH DC of the colour
    )
    fitted = pinhole(f, W, H, dtype=torch.float64)
    x1 = render(g, fitted, W, H, backend="torch")
    big = fitted.scaled(4)
    plain = render(g, big, 4 * W, 4 * H, backend="torch")
    floored = render(zoom_in_floor(g, fitted, W, H, big, 4 * W, 4 * H), big, 4 * W, 4 * H, backend="torch")
    filtered = render(g, big, 4 * W, 4 * H, backend="torch", filter_zoom=4)
    assert float(x1.alpha.mean()) > 0.9
    assert float(plain.alpha.mean()) < 0.5 * float(x1.alpha.mean())  # broken into dots
    assert float(floored.alpha.mean()) > 0.97 * float(x1.alpha.mean())
    assert float(filtered.alpha.mean()) > 0.97 * float(x1.alpha.mean())
    error = float((F.avg_pool2d(floored.color, 4) - x1.color).abs().mean())
    assert error < 0.02 < float((F.avg_pool2d(plain.color, 4) - x1.color).abs().mean())
    # With the fitted pixels' filter it is the x1 picture itself sampled 4 x finer: x4 pixel (4 j + k, 4 i + l)
    # is the x1 render's pixel (j, i) with its principal point moved by 1/2 - (k + 1/2) / 4, (l + 1/2) / 4.
    for k, l in ((0, 0), (3, 1), (2, 3)):
        K = fitted.K.clone()
        K[:, 0, 2] += 0.5 - (k + 0.5) / 4
        K[:, 1, 2] += 0.5 - (l + 0.5) / 4
        shifted = render(g, Cameras(fitted.c2w, K), W, H, backend="torch")
        torch.testing.assert_close(filtered.color[..., l::4, k::4], shifted.color, rtol=0, atol=1e-9)


def tiny_surfel(x: float, y: float, d: float, f: float, opacity: float = 0.8) -> Gaussians:
    """One surfel a ten-thousandth of a pixel wide at pixel (x, y), depth d, facing the identity camera."""
    p = torch.tensor([[x * d / f, y * d / f, d]], dtype=torch.float64)
    return Gaussians(
        p,
        torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
        torch.full((1, 2), 1e-4 * d / f, dtype=torch.float64),
        torch.full((1,), opacity, dtype=torch.float64),
        torch.zeros(1, 3, 1, dtype=torch.float64),
    )


@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize("mode", ["surfel", "ewa"])
def test_filter_zoom_draws_the_coarser_cameras_filter(backend, mode):
    f, W, H, o = 50.0, 24, 20, 0.8
    # centred on a pixel corner: no pixel centre falls on the surfel itself
    g = tiny_surfel(2.0, 1.0, 3.0, f, o)
    cam = pinhole(f, W, H, dtype=torch.float64)
    from .test_render import pixel_centres

    xx, yy = pixel_centres(W, H)
    r2 = (xx - (W / 2 + 2.0)) ** 2 + (yy - (H / 2 + 1.0)) ** 2
    # EWA: every pixel its alpha reaches (not the release's tile squares, which cut the wider footprints)
    settings = (TorchRenderSettings if backend == "torch" else CpuRenderSettings)(ewa_support="alpha")
    for z in (1.0, 2.0, 3.5):
        out = render(g, cam, W, H, mode=mode, backend=backend, alpha_threshold=None, filter_zoom=z, settings=settings)
        if mode == "surfel":  # 2DGS's low-pass 0.5 * 2 |d|^2, over z^2
            expected = o * torch.exp(-r2 / z**2)
        else:  # 3DGS's dilation 0.3 px^2, times z^2 (the surfel's own covariance is ~1e-8 px^2)
            expected = o * torch.exp(-0.5 * r2 / (0.3 * z**2))
        expected = torch.where(expected >= 1 / 255, expected, torch.zeros_like(expected))
        torch.testing.assert_close(out.alpha[0, 0], expected.to(out.alpha), rtol=0, atol=2e-6)
    plain = render(g, cam, W, H, mode=mode, backend=backend)
    torch.testing.assert_close(render(g, cam, W, H, mode=mode, backend=backend, filter_zoom=1).color, plain.color)


@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("mode", ["surfel", "ewa"])
def test_filter_zoom_gradients_agree_between_backends(mode, antialiased):
    g = random_scene(40, seed=7, dtype=torch.float64, edge_on=4)  # surfels up to 1.6 px: most below the filter
    cam = pinhole(30.0, 16, 12, dtype=torch.float64)
    target = torch.rand(1, 3, 12, 16, generator=torch.Generator().manual_seed(1), dtype=torch.float64)

    def grads(backend: str):
        leaves = [t.clone().requires_grad_(True) for t in (g.means, g.quats, g.scales, g.opacities, g.sh)]
        h = Gaussians(*leaves)
        out = render(h, cam, 16, 12, mode=mode, backend=backend, filter_zoom=2.5, antialiased=antialiased)
        ((out.color - target).square().sum() + out.alpha.sum()).backward()
        return out.color.detach(), [t.grad for t in leaves]

    (a, ga), (b, gb) = grads("torch"), grads("cpu")
    torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)
    for x, y in zip(ga, gb):
        assert float(x.abs().max()) > 0
        torch.testing.assert_close(x, y, rtol=1e-7, atol=1e-9)


def test_zoom_plan_picks_the_fitted_zoom():
    d, f, W, H = 3.0, 100.0, 64, 48
    g = plane(d)
    fitted = pinhole(f, W, H, dtype=torch.float64)
    assert zoom_plan(g, fitted, W, H, fitted, W, H) == ZoomPlan(g)
    assert zoom_plan(g, None, None, None, fitted.scaled(4), 4 * W, 4 * H) == ZoomPlan(g)  # no fitted views
    assert zoom_plan(g, fitted, W, H, fitted.scaled(1.3), 83, 62) == ZoomPlan(g)  # below 1.5 x: as asked
    assert zoom_plan(g, fitted, W, H, fitted.scaled(1 / 2), W // 2, H // 2) == ZoomPlan(g, supersample=2)
    for z in (2.0, 4.0):
        plan = zoom_plan(g, fitted, W, H, fitted.scaled(z), int(z * W), int(z * H))
        assert plan.gaussians is g and plan.supersample == 1 and plan.filter_zoom == pytest.approx(z, rel=1e-12)
        closer = pinhole(f, W, H, c2w=moved_back(-(1 - 1 / z) * d), dtype=torch.float64)  # at depth d / z
        assert zoom_plan(g, fitted, W, H, closer, W, H).filter_zoom == pytest.approx(z, rel=1e-9)


def test_zoom_plan_widens_the_surfels_on_gsplat(monkeypatch):
    import surfsplat.render as render_module

    d, f, W, H = 3.0, 100.0, 64, 48
    g = plane(d)
    fitted = pinhole(f, W, H, dtype=torch.float64)
    monkeypatch.setattr(render_module, "resolve_backend", lambda *args: "gsplat")
    plan = zoom_plan(g, fitted, W, H, fitted.scaled(4), 4 * W, 4 * H)
    assert plan.filter_zoom == 1 and plan.supersample == 1
    assert torch.equal(plan.gaussians.scales, zoom_in_floor(g, fitted, W, H, fitted.scaled(4), 4 * W, 4 * H).scales)
