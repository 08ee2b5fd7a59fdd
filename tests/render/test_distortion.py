"""2DGS's depth distortion (`render(..., distortion=True)`): the torch reference against the pairwise
definition, the compiled CPU kernels against the reference, and the maps that must not change.

The gsplat backend's distortion is checked in `test_gsplat_backend.py` (gsplat's kernels stood in by
its references on a CPU).
"""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from surfsplat import Cameras, Gaussians
from surfsplat.geometry.sh import SH_C0
from surfsplat.render import CpuRenderSettings, TorchRenderSettings, render
from surfsplat.utils.checks import SurfSplatInputError
from tests.render.test_cpu import camera, scene

GEOMETRY = ("means", "quats", "scales", "opacities")
PARAMS = (*GEOMETRY, "sh")


def _leaves(g: Gaussians) -> dict:
    return {k: getattr(g, k).detach().clone().requires_grad_(True) for k in PARAMS}


def _two_cameras(width: int, height: int, dtype: torch.dtype) -> Cameras:
    a = camera(0.8 * width, width, height, dtype=dtype)
    b = camera(0.9 * width, width, height, offset=(-0.1, 0.05, 0.0), dtype=dtype)
    return Cameras(torch.cat((a.c2w, b.c2w)), torch.cat((a.K, b.K)))


def _pairwise(g: Gaussians, cams: Cameras, width: int, height: int, settings: TorchRenderSettings) -> Tensor:
    """sum_{i != j} w_i w_j |z_i - z_j| per pixel, O(n^2), from each surfel's own weight map.

    Surfel i's weights are the colour of a render where it alone is white and every other surfel
    black (no forced alpha): the compositing itself, without the moments; z is its centre's camera z.
    """
    n = g.means.shape[0]
    weights = []
    for i in range(n):
        white = torch.arange(n, device=g.sh.device)[:, None] == i
        dc = torch.full((n, 1), -0.5 / SH_C0, dtype=g.sh.dtype).masked_fill(white, 0.5 / SH_C0)
        sh = torch.cat((dc[:, None, :].expand(n, 3, 1), torch.zeros_like(g.sh[..., 1:])), -1)
        one = Gaussians(g.means, g.quats, g.scales, g.opacities, sh)
        weights.append(render(one, cams, width, height, backend="torch", alpha_threshold=None, settings=settings).color)
    w = torch.stack(weights)[:, :, 0]  # [n, C, H, W]
    z = (g.means @ cams.w2c[:, :3, :3].mT + cams.w2c[:, None, :3, 3])[..., 2].T  # [n, C]
    gap = (z[:, None] - z[None, :]).abs()[..., None, None]  # [n, n, C, 1, 1]
    return (w[:, None] * w[None, :] * gap).sum((0, 1))[:, None]


@pytest.mark.parametrize("block_depth", [128, 2])
def test_torch_distortion_is_the_pairwise_sum_forward_and_backward(block_depth):
    # block_depth 2 splits every tile's list into blocks of two: the moments carry across blocks.
    g = scene(10, 11, 0)
    W, H = 14, 12
    cams = _two_cameras(W, H, torch.float64)
    settings = TorchRenderSettings(max_block_depth=block_depth)
    weight = torch.rand(2, 1, H, W, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    results = []
    for method in ("moments", "pairwise"):
        leaves = _leaves(g)
        gs = Gaussians(**leaves)
        if method == "moments":
            out = render(gs, cams, W, H, backend="torch", alpha_threshold=None, settings=settings, distortion=True)
            d = out.distortion
        else:
            d = _pairwise(gs, cams, W, H, settings)
        (d * weight).sum().backward()
        results.append((d.detach(), {k: leaves[k].grad for k in GEOMETRY}))
    (moments, grads), (pairwise, ref_grads) = results
    assert float(pairwise.max()) > 0.05 and int((pairwise > 1e-3).sum()) > 50  # overlapping surfels
    assert (moments - pairwise).abs().max() < 1e-12
    for k in GEOMETRY:
        assert float(ref_grads[k].abs().max()) > 1e-3, k
        assert (grads[k] - ref_grads[k]).abs().max() < 1e-10 * (1 + float(ref_grads[k].abs().max())), k


@pytest.mark.parametrize(("dtype", "tol"), [(torch.float64, 1e-9), (torch.float32, 1e-4)])
def test_cpu_distortion_matches_the_torch_reference(dtype, tol):
    """Forward and every gradient, with the distortion in a loss beside colour and depth (whose
    gradients share the weights' chain rule), over two cameras."""
    g = scene(60, 5, 1, dtype=dtype)
    W, H = 40, 30
    cams = _two_cameras(W, H, dtype)
    gen = torch.Generator().manual_seed(2)
    wd, wc, wz = (torch.rand(2, c, H, W, generator=gen).to(dtype) for c in (1, 3, 1))
    results = {}
    for backend in ("torch", "cpu"):
        leaves = _leaves(g)
        out = render(Gaussians(**leaves), cams, W, H, backend=backend, distortion=True, alpha_threshold=0.1)
        loss = (out.distortion * wd).sum() + 0.1 * (out.color * wc).sum() + 0.1 * (out.depth * wz).sum()
        loss.backward()
        results[backend] = (out.distortion.detach(), {k: v.grad for k, v in leaves.items()})
    (ref, ref_grads), (ours, grads) = results["torch"], results["cpu"]
    assert float(ref.max()) > 0.1
    assert (ours - ref).abs().max() <= tol * float(ref.abs().max())
    for k in PARAMS:
        scale = float(ref_grads[k].abs().max())
        assert scale > 0, k
        assert (grads[k] - ref_grads[k]).abs().max() <= tol * scale, k


def test_cpu_distortion_gradient_alone_matches_the_reference():
    """Only the distortion in the loss: its own gradient, through alphas and centre depths."""
    g = scene(40, 9, 0)
    W, H = 32, 24
    cams = camera(28.0, W, H)
    grads = {}
    for backend in ("torch", "cpu"):
        leaves = _leaves(g)
        render(Gaussians(**leaves), cams, W, H, backend=backend, distortion=True).distortion.sum().backward()
        grads[backend] = {k: leaves[k].grad for k in GEOMETRY}
        assert leaves["sh"].grad is None or float(leaves["sh"].grad.abs().max()) == 0.0
    for k in GEOMETRY:
        ref = grads["torch"][k]
        assert float(ref.abs().max()) > 1e-3, k
        assert (grads["cpu"][k] - ref).abs().max() <= 1e-9 * float(ref.abs().max()), k


@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_distortion_off_leaves_every_output_and_gradient_bit_identical(backend, dtype):
    g = scene(50, 4, 1, dtype=dtype)
    W, H = 36, 28
    cams = _two_cameras(W, H, dtype)
    gen = torch.Generator().manual_seed(5)
    wc, wa, wz, wn = (torch.rand(2, c, H, W, generator=gen).to(dtype) for c in (3, 1, 1, 3))
    runs = []
    for distortion in (False, True):
        leaves = _leaves(g)
        out = render(Gaussians(**leaves), cams, W, H, backend=backend, distortion=distortion)
        assert (out.distortion is not None) == distortion
        loss = (out.color * wc).sum() + (out.alpha * wa).sum() + (out.depth * wz).sum() + (out.normal * wn).sum()
        loss.backward()
        runs.append(((out.color, out.alpha, out.depth, out.normal), [leaves[k].grad for k in PARAMS]))
    (maps_off, grads_off), (maps_on, grads_on) = runs
    for a, b in zip(maps_off, maps_on):
        assert torch.equal(a, b)
    for a, b in zip(grads_off, grads_on):
        assert torch.equal(a, b)


def test_distortion_is_zero_for_one_surfel_and_grows_with_the_gap_between_two():
    """Closed form: two fronto-parallel surfels on the axis, weights w1 = a1, w2 = (1 - a1) a2 at the
    centre pixel, give 2 w1 w2 (z2 - z1) there; one surfel alone gives 0."""
    W = H = 9
    cams = Cameras(torch.eye(4, dtype=torch.float64)[None], torch.tensor([[[8.0, 0, 4.5], [0, 8.0, 4.5], [0, 0, 1]]]))

    def pair(z2: float, count: int) -> Gaussians:
        return Gaussians(
            means=torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, z2]], dtype=torch.float64)[:count],
            quats=torch.tensor([[1.0, 0, 0, 0]] * count, dtype=torch.float64),
            scales=torch.full((count, 2), 0.5, dtype=torch.float64),
            opacities=torch.tensor([0.6, 0.7], dtype=torch.float64)[:count],
            sh=torch.zeros(count, 3, 1, dtype=torch.float64),
        )

    for backend in ("torch", "cpu"):
        single = render(pair(0.0, 1), cams, W, H, backend=backend, distortion=True).distortion
        assert float(single.abs().max()) == 0.0
        for z2 in (2.5, 4.0):
            d = render(pair(z2, 2), cams, W, H, backend=backend, distortion=True).distortion
            expected = 2 * 0.6 * (0.4 * 0.7) * (z2 - 2.0)
            assert abs(float(d[0, 0, 4, 4]) - expected) < 1e-12, backend


def test_distortion_is_asked_in_surfel_mode_only():
    g = scene(5, 1, 0)
    cams = camera(20.0, 8, 8)
    with pytest.raises(SurfSplatInputError, match="distortion"):
        render(g, cams, 8, 8, mode="ewa", distortion=True)
    with pytest.raises(SurfSplatInputError, match="distortion"):
        render(g, cams, 8, 8, distortion="yes")
    # Both backends' settings keep working with it.
    for settings in (TorchRenderSettings(tile_size=8), CpuRenderSettings(tile_size=8)):
        out = render(g, cams, 8, 8, settings=settings, distortion=True)
        assert out.distortion is not None and bool(out.distortion.isfinite().all())
