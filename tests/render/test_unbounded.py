"""Surfels whose footprint is unbounded (their k-sigma ellipse crosses the camera plane) render on
every backend, with the same values and gradients: no backend may cull what another renders."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from surfsplat import Cameras, Gaussians
from surfsplat.render import render

ATTRS = ("means", "quats", "scales", "opacities", "sh")


def _both_backends(g: Gaussians, cams: Cameras, W: int, H: int, mode: str = "surfel"):
    gen = torch.Generator().manual_seed(3)
    weights = [torch.rand(len(cams), c, H, W, generator=gen, dtype=torch.float64) for c in (3, 1, 1, 3)]
    results = {}
    for backend in ("torch", "cpu"):
        leaves = {k: getattr(g, k).detach().clone().requires_grad_(True) for k in ATTRS}
        out = render(Gaussians(**leaves), cams, W, H, mode=mode, backend=backend, alpha_threshold=None)
        maps = (out.color, out.alpha, out.depth, out.normal)
        sum(((m * w).sum() for m, w in zip(maps, weights))).backward()
        results[backend] = (maps, {k: v.grad for k, v in leaves.items()})
    return results


def _assert_agree(results, min_alpha_sum: float):
    (maps_t, grads_t), (maps_c, grads_c) = results["torch"], results["cpu"]
    assert float(maps_t[1].sum()) > min_alpha_sum
    for a, b in zip(maps_t, maps_c):
        assert (a - b).abs().max() < 1e-9 * max(1.0, float(a.abs().max()))
    for k in ATTRS:
        assert (grads_t[k] - grads_c[k]).norm() <= 1e-8 * grads_t[k].norm() + 1e-12, k
        assert grads_c[k].abs().sum() > 0, k


def test_surfel_straddling_the_camera_plane():
    """The case that was culled: a 60-degree tilted surfel 1 unit ahead whose 1/255 ellipse reaches behind."""
    a = math.radians(60)
    d = torch.float64
    cams = Cameras(
        c2w=torch.eye(4, dtype=d)[None], K=torch.tensor([[[32.0, 0, 16], [0, 32.0, 16], [0, 0, 1]]], dtype=d)
    )
    g = Gaussians(
        means=torch.tensor([[0.0, 0.0, 1.0]], dtype=d),
        quats=torch.tensor([[math.cos(a / 2), 0.0, math.sin(a / 2), 0.0]], dtype=d),
        scales=torch.tensor([[0.5, 0.2]], dtype=d),
        opacities=torch.tensor([0.8], dtype=d),
        sh=torch.zeros(1, 3, 4, dtype=d) + 0.1,
    )
    _assert_agree(_both_backends(g, cams, 32, 32), min_alpha_sum=250)


def _room(n: int, seed: int) -> Gaussians:
    """Surfels on the walls, floor and ceiling of a 2 x 2 x 2 room, facing inwards, large enough to overlap."""
    gen = torch.Generator().manual_seed(seed)
    d = torch.float64
    uv = torch.rand(n, 2, generator=gen, dtype=d) * 2 - 1
    face = torch.randint(0, 6, (n,), generator=gen)
    axis, sign = face // 2, (face % 2) * 2 - 1
    means = torch.zeros(n, 3, dtype=d)
    for i in range(3):
        others = [j for j in range(3) if j != i]
        on = axis == i
        means[on, i] = sign[on].to(d)
        means[on, others[0]] = uv[on, 0]
        means[on, others[1]] = uv[on, 1]
    # quaternion taking +z to each face's axis
    q = torch.zeros(n, 4, dtype=d)
    h = math.sqrt(0.5)
    q[axis == 2] = torch.tensor([1.0, 0, 0, 0], dtype=d)
    q[axis == 0] = torch.tensor([h, 0, h, 0], dtype=d)
    q[axis == 1] = torch.tensor([h, -h, 0, 0], dtype=d)
    return Gaussians(
        means=means,
        quats=q + 0.05 * torch.randn(n, 4, generator=gen, dtype=d),
        scales=torch.rand(n, 2, generator=gen, dtype=d) * 0.3 + 0.15,
        opacities=torch.rand(n, generator=gen, dtype=d) * 0.5 + 0.3,
        sh=torch.randn(n, 3, 4, generator=gen, dtype=d) * 0.3,
    )


@pytest.mark.parametrize("mode", ["surfel", "ewa"])
def test_camera_standing_inside_a_room_of_surfels(mode):
    g = _room(300, 0)
    d = torch.float64
    c2w = torch.eye(4, dtype=d)
    c2w[:3, 3] = torch.tensor([0.2, -0.1, 0.3], dtype=d)
    K = torch.tensor([[[20.0, 0, 24], [0, 20.0, 16], [0, 0, 1]]], dtype=d)
    results = _both_backends(g, Cameras(c2w[None], K), 48, 32, mode)
    _assert_agree(results, min_alpha_sum=0.9 * 48 * 32)  # the room surrounds the camera: the view is covered


def test_close_up_path_towards_a_wall():
    """A camera walking up to a wall: at the last frames surfels beside it cross the camera plane."""
    g = _room(300, 1)
    d = torch.float64
    frames = []
    for z in (0.0, 0.5, 0.8, 0.95):
        c2w = torch.eye(4, dtype=d)
        c2w[:3, :3] = torch.tensor([[1.0, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=d)
        c2w[2, 3] = z  # towards the wall at z = +1
        frames.append(c2w)
    K = torch.tensor([[20.0, 0, 16], [0, 20.0, 16], [0, 0, 1]], dtype=d).repeat(len(frames), 1, 1)
    _assert_agree(_both_backends(g, Cameras(torch.stack(frames), K), 32, 32), min_alpha_sum=0.9 * 4 * 32 * 32)


def test_culling_before_projection_keeps_every_footprint_that_reaches_the_image():
    """The compiled backend culls surfels whose bounding sphere projects off the image before it
    projects them; the torch backend culls nothing early. Surfels scattered past the image borders
    and across the camera plane (spheres that reach it are never culled early) render the same."""
    from surfsplat.render.cpu import kernels
    from surfsplat.render.types import LOWPASS_RHO_SCALE, RenderConventions

    gen = torch.Generator().manual_seed(11)
    d, n, size, f = torch.float64, 300, 32, 32.0
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=d)
    cams = Cameras(c2w=torch.eye(4, dtype=d)[None], K=K[None])
    z = torch.rand(n, generator=gen, dtype=d) * 3.0 + 0.05
    u, v = ((torch.rand(2, n, generator=gen, dtype=d) * 2.4 - 0.7) * size - size / 2) * z / f
    quats = F.normalize(torch.randn(n, 4, generator=gen, dtype=d), dim=-1)
    g = Gaussians(
        means=torch.stack((u, v, z), -1),
        quats=quats,
        scales=torch.rand(n, 2, generator=gen, dtype=d) * 0.3 + 0.01,
        opacities=torch.rand(n, generator=gen, dtype=d) * 0.95 + 0.02,
        sh=torch.randn(n, 3, 1, generator=gen, dtype=d) * 0.3,
    )
    _assert_agree(_both_backends(g, cams, size, size), min_alpha_sum=5)
    # The early cull did take part: some spheres lie off the image, some straddle the camera plane.
    sigma = RenderConventions().lowpass_center_sigma
    culled, straddling = 0, 0
    for mu, s, o in zip(g.means.numpy(), g.scales.numpy(), g.opacities.numpy()):
        k2 = kernels._opacity_extent(math.log(o))
        reach = max(math.sqrt(k2), sigma) * s.max()
        culled += kernels._surfel_off_image(mu, reach, math.sqrt(k2 / LOWPASS_RHO_SCALE) + 1.0, K.numpy(), size, size)
        straddling += mu[2] <= reach
    assert culled > 30 and straddling > 10
