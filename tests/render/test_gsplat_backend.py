"""The project's gsplat backend, run on a CPU with gsplat's CUDA entry points replaced by gsplat's own
pure-PyTorch references (`surfsplat.testing.gsplat_reference.cpu_kernels`).

This proves the backend's glue - projection hand-over, tile boxes, channel layout, gradients - on
the machine the suite runs on; the CUDA kernels themselves run in `scripts/gpu_check.py` on a GPU.
The backend renders the torch backend's function except where gsplat's kernels differ by design
(see `surfsplat.render.gsplat_backend`): surfel depth is the blended centre depth.
"""

from __future__ import annotations

import math

import pytest
import torch

from surfsplat import Cameras, Gaussians
from surfsplat.render import TorchRenderSettings, normalize_by_alpha, render

pytest.importorskip("gsplat", reason="gsplat is part of the test extra: pip install -e '.[test]'")
from surfsplat.render.gsplat_backend import render_gsplat  # noqa: E402
from surfsplat.testing.gsplat_reference import cpu_kernels, with_intrinsics  # noqa: E402
from surfsplat.testing.gsplat_reference import reference_scene as scene  # noqa: E402


@pytest.fixture
def cpu_gsplat():
    """gsplat's CUDA entry points answered by its pure-PyTorch references, for this test only."""
    with cpu_kernels():
        yield


def _leaves(g: Gaussians) -> dict:
    return {
        k: getattr(g, k).detach().clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "sh")
    }


@pytest.mark.parametrize(("mode", "support"), [("surfel", "release"), ("ewa", "release"), ("ewa", "alpha")])
def test_gsplat_backend_matches_the_torch_backend(cpu_gsplat, mode, support):
    g, cams = scene(600, 4, torch.float32, 3)
    W, H = 64, 48
    cams = with_intrinsics(cams, W, H)
    settings = TorchRenderSettings(ewa_support=support)
    gen = torch.Generator().manual_seed(1)
    weights = [torch.rand(1, c, H, W, generator=gen) for c in (3, 1, 1, 3)]
    results = []
    for backend in ("gsplat", "torch"):
        leaves = _leaves(g)
        gs = Gaussians(**leaves)
        if backend == "gsplat":
            maps = render_gsplat(gs, cams, W, H, mode, settings)
        else:
            out = render(gs, cams, W, H, mode=mode, backend="torch", alpha_threshold=None, settings=settings)
            maps = (out.color, out.alpha, out.depth, out.normal)
        depth_weight = weights[2] if mode == "ewa" else 0.0  # surfel depth differs by design (centre depth)
        loss = (maps[0] * weights[0]).sum() + (maps[1] * weights[1]).sum() + (maps[3] * weights[3]).sum()
        loss = loss + (maps[2] * depth_weight).sum()
        loss.backward()
        results.append((maps, {k: v.grad for k, v in leaves.items()}))
    (ours, grads), (reference, ref_grads) = results
    assert float(reference[1].max()) > 0.9
    for name, i in (("colour", 0), ("alpha", 1), ("normal", 3)):
        assert (ours[i] - reference[i]).abs().max() < 1e-4, name
    if mode == "ewa":
        assert (ours[2] - reference[2]).abs().max() < 1e-4 * float(reference[2].abs().max())
    else:
        # Named difference: blended centre depth (gsplat) against intersection depth, bounded by the
        # surfels' depth extent.
        assert (ours[2] - reference[2]).abs().max() < 3.33 * 1.5 * float(g.scales.max())
    for k in grads:
        assert (grads[k] - ref_grads[k]).norm() <= 2e-3 * ref_grads[k].norm() + 1e-6, k


def test_gsplat_backend_distortion_matches_the_torch_backend(cpu_gsplat):
    """Depth distortion: gsplat's kernel (`distloss=True`, stood in by its formula on gsplat's reference
    pairs and weights) against the torch reference, forward and gradients. Both take each surfel's
    centre depth, so unlike the depth map no difference is left by design; two cameras in one call."""
    g, cams = scene(600, 4, torch.float32, 3)
    W, H = 64, 48
    cams = with_intrinsics(cams, W, H)
    c2w = cams.c2w.repeat(2, 1, 1)
    c2w[1, :3, 3] += torch.tensor([0.1, -0.05, 0.0])
    cams = Cameras(c2w, cams.K.repeat(2, 1, 1))
    weight = torch.rand(2, 1, H, W, generator=torch.Generator().manual_seed(6))
    results = []
    for backend in ("gsplat", "torch"):
        leaves = _leaves(g)
        gs = Gaussians(**leaves)
        if backend == "gsplat":
            distortion = render_gsplat(gs, cams, W, H, "surfel", distortion=True)[4]
        else:
            distortion = render(gs, cams, W, H, backend="torch", distortion=True).distortion
        (distortion * weight).sum().backward()
        results.append((distortion.detach(), {k: v.grad for k, v in leaves.items() if k != "sh"}))
    (ours, grads), (reference, ref_grads) = results
    assert float(reference.max()) > 0.3
    assert (ours - reference).abs().max() < 1e-4 * float(reference.max())
    for k in grads:
        assert float(ref_grads[k].norm()) > 0, k
        assert (grads[k] - ref_grads[k]).norm() <= 2e-3 * ref_grads[k].norm(), k


def test_gsplat_backend_asks_gsplat_for_the_distortion_only_when_asked(cpu_gsplat, monkeypatch):
    from gsplat.cuda import _wrapper

    asked = []
    original = _wrapper.rasterize_to_pixels_2dgs

    def recorded(*args, **kwargs):
        asked.append(kwargs.get("distloss", False))
        return original(*args, **kwargs)

    monkeypatch.setattr(_wrapper, "rasterize_to_pixels_2dgs", recorded)
    g, cams = scene(200, 3, torch.float32, 0)
    cams = with_intrinsics(cams, 32, 32)
    plain = render_gsplat(g, cams, 32, 32, "surfel")
    with_distortion = render_gsplat(g, cams, 32, 32, "surfel", distortion=True)
    assert asked == [False, True]
    assert len(plain) == 4 and len(with_distortion) == 5
    for a, b in zip(plain, with_distortion):
        assert torch.equal(a, b)
    assert float(with_distortion[4].max()) > 0


def test_gsplat_backend_fits_colours_opacities_and_sizes_over_many_cameras_as_the_cpu_backend(cpu_gsplat):
    # A fit as the capture refinement runs it: several cameras a call, forced alpha blending, only
    # SH, opacities and scales differentiated, a few Adam steps. Through gsplat's references the
    # glue must end where the compiled CPU renderer does (a fit on an H200 through gsplat's CUDA
    # kernels raised its loss instead, which these references do not reproduce).
    g, cams = scene(400, 6, torch.float32, 1)
    W, H = 40, 32
    cams = with_intrinsics(cams, W, H)
    shift = torch.tensor([[0.0, 0.0, 0.0], [0.08, 0.0, 0.0], [0.0, 0.06, 0.0]], dtype=cams.c2w.dtype)
    c2w = cams.c2w.repeat(3, 1, 1)
    c2w[:, :3, 3] += shift
    cams = Cameras(c2w, cams.K.repeat(3, 1, 1))
    target = render(g, cams, W, H, backend="torch").color.detach().flip(-1)  # a picture to fit towards
    ends = {}
    for backend in ("cpu", "gsplat"):
        sh, logits = g.sh.clone().requires_grad_(True), torch.logit(g.opacities).requires_grad_(True)
        log_scales = g.scales.log().requires_grad_(True)
        optimizer = torch.optim.Adam([sh, logits, log_scales], lr=0.02)
        losses = []
        for _ in range(4):
            fitted = Gaussians(g.means, g.quats, log_scales.exp(), torch.sigmoid(logits), sh)
            if backend == "cpu":
                color = render(fitted, cams, W, H, backend="cpu", alpha_threshold=0.001).color
            else:  # the dispatcher's forced alpha blending around the backend (black background)
                color = normalize_by_alpha(*render_gsplat(fitted, cams, W, H, "surfel"), 0.001)[0]
            loss = (color - target).square().mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            losses.append(float(loss))
        ends[backend] = (losses, sh.detach(), logits.detach(), log_scales.detach())
    (cpu_losses, *cpu_params), (gs_losses, *gs_params) = ends["cpu"], ends["gsplat"]
    assert cpu_losses[-1] < cpu_losses[0]
    assert all(abs(a - b) <= 1e-4 * a for a, b in zip(cpu_losses, gs_losses)), (cpu_losses, gs_losses)
    for a, b in zip(cpu_params, gs_params):
        assert (a - b).abs().max() < 1e-3


def test_gsplat_backend_renders_a_surfel_crossing_the_camera_plane(cpu_gsplat):
    """The footprint is unbounded: the backend lists the surfel in every tile, as the other backends render it."""
    a = math.radians(60)
    cams = Cameras(c2w=torch.eye(4)[None], K=torch.tensor([[[32.0, 0, 16], [0, 32.0, 16], [0, 0, 1]]]))
    g = Gaussians(
        means=torch.tensor([[0.0, 0.0, 1.0]]),
        quats=torch.tensor([[math.cos(a / 2), 0.0, math.sin(a / 2), 0.0]]),
        scales=torch.tensor([[0.5, 0.2]]),
        opacities=torch.tensor([0.8]),
        sh=torch.zeros(1, 3, 1),
    )
    _, alpha, _, _ = render_gsplat(g, cams, 32, 32, "surfel")
    reference = render(g, cams, 32, 32, backend="torch", alpha_threshold=None).alpha
    assert float(reference.sum()) > 250
    assert (alpha - reference).abs().max() < 1e-5


# ------------------------------------------------------------------ NaN from uninitialised padding
@pytest.fixture
def uninitialised_is_nan():
    """Uninitialised memory (`torch.empty`) filled with NaN, as PyTorch's deterministic mode does: a
    CUDA caching allocator hands back whatever a freed block held, NaN and inf bit patterns included."""
    was = torch.are_deterministic_algorithms_enabled()
    fill = torch.utils.deterministic.fill_uninitialized_memory
    torch.use_deterministic_algorithms(True)
    torch.utils.deterministic.fill_uninitialized_memory = True
    yield
    torch.use_deterministic_algorithms(was)
    torch.utils.deterministic.fill_uninitialized_memory = fill


def test_gsplat_pads_2dgs_channels_with_uninitialised_memory(cpu_gsplat, uninitialised_is_nan):
    """The quirk behind training that turned non-finite at its first step on a GPU (gsplat 1.5.3):
    `rasterize_to_pixels_2dgs` pads a channel count its kernels are not compiled for (here 7, the
    layout this backend used) with `torch.empty`; the backward multiplies the padding by its zero
    gradient, and 0 x NaN poisons every geometry gradient while the forward stays finite."""
    from gsplat.cuda import _wrapper

    from surfsplat.render.gsplat_backend import tile_boxes
    from surfsplat.render.torch_backend import _pixel_box, surfel_footprint, surfel_transforms

    g, cams = scene(300, 2, torch.float32, 1)
    W, H = 32, 32
    cams = with_intrinsics(cams, W, H)
    leaves = _leaves(g)
    gs = Gaussians(**leaves)
    T, mu = surfel_transforms(gs.means, gs.rotations, gs.scales, cams.w2c, cams.K, torch.float32)  # [1, N, ...]
    _, lowpass, bounds = surfel_footprint(T, mu[..., 2], gs.opacities, 3.0)
    middle, radii = tile_boxes(_pixel_box(*(b.detach() for b in bounds), W, H))
    _, isect_ids, flatten_ids = _wrapper.isect_tiles(middle, radii, mu[..., 2].detach(), 16, 2, 2)
    offsets = _wrapper.isect_offset_encode(isect_ids, 1, 2, 2)
    colors = torch.cat((gs.sh[None, :, :, 0] + 0.5, mu, mu[..., 2:]), -1)  # 7 channels: padded to 8
    out = _wrapper.rasterize_to_pixels_2dgs(
        lowpass,
        T,
        colors,
        gs.opacities[None],
        torch.zeros_like(mu),
        torch.zeros_like(lowpass),
        W,
        H,
        16,
        offsets,
        flatten_ids,
    )
    assert bool(out[0].isfinite().all()) and float(out[1].max()) > 0.9
    out[0].sum().backward()
    assert bool(leaves["sh"].grad.isfinite().all())  # colours: their own gradient is clean
    for name in ("means", "quats", "scales", "opacities"):  # through alpha: 0 x NaN
        assert not bool(leaves[name].grad.isfinite().all()), name


@pytest.mark.parametrize("mode", ["surfel", "ewa"])
def test_gsplat_backend_gradients_are_finite_when_uninitialised_memory_is_nan(cpu_gsplat, uninitialised_is_nan, mode):
    """The backend hands gsplat only channel counts its kernels are compiled for, so no padding, and
    no uninitialised value, ever reaches a gradient (the test above shows what one would do)."""
    g, cams = scene(400, 5, torch.float32, 2)
    W, H = 48, 40
    cams = with_intrinsics(cams, W, H)
    leaves = _leaves(g)
    maps = render_gsplat(Gaussians(**leaves), cams, W, H, mode)
    assert float(maps[1].max()) > 0.9
    loss = sum((m * torch.linspace(0, 1, m.numel()).reshape(m.shape)).sum() for m in maps)
    loss.backward()
    for name, leaf in leaves.items():
        assert bool(leaf.grad.isfinite().all()), name
        assert float(leaf.grad.abs().max()) > 0, name


# ------------------------------------------------------------------ every camera in one call
def test_gsplat_backend_renders_every_camera_in_one_batched_call(cpu_gsplat, monkeypatch):
    from gsplat.cuda import _wrapper

    calls = {"isect_tiles": 0, "rasterize_to_pixels_2dgs": 0, "rasterize_to_pixels": 0}
    for name in calls:
        original = getattr(_wrapper, name)

        def counted(*args, _name=name, _original=original, **kwargs):
            calls[_name] += 1
            return _original(*args, **kwargs)

        monkeypatch.setattr(_wrapper, name, counted)
    g, cams = scene(300, 7, torch.float32, 1)
    W, H = 40, 32
    cams = with_intrinsics(cams, W, H)
    shift = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, -0.08, 0.05]])
    c2w = cams.c2w.repeat(3, 1, 1)
    c2w[:, :3, 3] += shift
    K = cams.K.repeat(3, 1, 1)
    K[:, :2, :2] *= torch.tensor([1.0, 1.1, 0.9])[:, None, None]  # three focal lengths
    cams = Cameras(c2w, K)
    for mode, kernel in (("surfel", "rasterize_to_pixels_2dgs"), ("ewa", "rasterize_to_pixels")):
        before = dict(calls)
        together = render_gsplat(g, cams, W, H, mode)
        assert calls["isect_tiles"] - before["isect_tiles"] == 1
        assert calls[kernel] - before[kernel] == 1
        apart = [render_gsplat(g, cams[c : c + 1], W, H, mode) for c in range(3)]
        for i in range(4):
            assert (together[i] - torch.cat([a[i] for a in apart])).abs().max() < 1e-6


# ------------------------------------------------------------------ no host synchronisation
class _DeviceKernels:
    """gsplat's entry points as differentiable functions of all their inputs that never read a device
    value on the host, so any synchronisation recorded is the backend's own (gsplat's `isect_tiles`
    reads its intersection count once, as inside gsplat's own `rasterization_2dgs`)."""

    @staticmethod
    def isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height):
        n = 64  # a fixed intersection count: gsplat reads the true one on the host
        device = means2d.device
        zeros = torch.zeros(n, dtype=torch.int64, device=device)
        return radii[..., 0], zeros, zeros.to(torch.int32)

    @staticmethod
    def isect_offset_encode(isect_ids, n_images, tile_width, tile_height):
        return torch.zeros(n_images, tile_height, tile_width, dtype=torch.int32, device=isect_ids.device)

    @staticmethod
    def _maps(geometry, colors, opacities, width, height):
        per_camera = (opacities[..., None] * colors).sum(-2) + geometry[:, None]  # [C, channels]
        alpha = torch.sigmoid(opacities.sum(-1) + geometry)[:, None, None, None]
        c = colors.shape[0]
        return per_camera[:, None, None].expand(c, height, width, -1), alpha.expand(c, height, width, 1)

    @classmethod
    def rasterize_to_pixels_2dgs(cls, means2d, transforms, colors, opacities, normals, densify, W, H, *_, **__):
        geometry = means2d.sum((-1, -2)) + transforms.sum((-1, -2, -3)) + densify.sum((-1, -2))
        maps, alpha = cls._maps(geometry, colors, opacities, W, H)
        normal = normals.sum(-2)[:, None, None].expand(-1, H, W, -1)
        return maps, alpha, normal, alpha, alpha

    @classmethod
    def rasterize_to_pixels(cls, means2d, conics, colors, opacities, W, H, *_):
        return cls._maps(means2d.sum((-1, -2)) + conics.sum((-1, -2)), colors, opacities, W, H)


@pytest.mark.parametrize("antialiased", [False, True], ids=["plain", "antialiased"])
@pytest.mark.parametrize("mode", ["surfel", "ewa"])
def test_render_through_the_gsplat_backend_has_no_host_synchronisation(monkeypatch, mode, antialiased):
    """`render(..., backend="gsplat")`, forward and backward, on the stand-in device (which records every
    op that would make a CUDA host wait): no scalar read, no data-dependent size, no upload."""
    import surfsplat.render as render_module
    from surfsplat.render import gsplat_backend
    from surfsplat.testing.standin_device import StandinDevice, standin

    monkeypatch.setattr(render_module, "gsplat_available", lambda device: True)
    monkeypatch.setattr(gsplat_backend, "_kernels", lambda: _DeviceKernels)
    g, cams = scene(300, 8, torch.float32, 2)
    cams = with_intrinsics(cams, 40, 32)
    cams = Cameras(cams.c2w.repeat(3, 1, 1), cams.K.repeat(3, 1, 1))
    with StandinDevice() as dev:
        leaves = {k: standin(v, requires_grad=True) for k, v in _leaves(g).items()}
        gaussians, on_device = Gaussians(**leaves), cams.to(dev.device)  # inputs checked, cameras uploaded
        inputs = len(dev.syncs)
        distortion = mode == "surfel"
        out = render(
            gaussians,
            on_device,
            40,
            32,
            mode=mode,
            backend="gsplat",
            alpha_threshold=0.1,
            distortion=distortion,
            antialiased=antialiased,
        )
        loss = out.color.sum() + out.alpha.sum() + out.depth.sum() + out.normal.sum()
        loss = loss + (out.distortion.sum() if distortion else 0)
        loss.backward()
        grads = [leaf.grad for leaf in leaves.values()]
        assert all(grad is not None and grad.device == dev.device for grad in grads)
        assert inputs > 0  # the recorder works: the input checks read values on the host
        assert [s.where for s in dev.syncs[inputs:]] == []
