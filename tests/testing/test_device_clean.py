"""Every tensor of the model, the adapter, the losses and a training step stays on the inputs' device.

A single tensor created on the CPU (`torch.eye(3)` instead of `torch.eye(3, device=R.device)`)
stops a user's first CUDA run with "Expected all tensors to be on the same device". These tests run
forward and backward passes with every input, parameter and buffer on a device other than the CPU,
so such a tensor fails here first, on any machine.

Method (details in surfsplat/testing/standin_device.py):
- Without a GPU, the "stand-in device": tensors that report device `meta`, keep their values on
  the CPU, and go through a dispatch mode that applies CUDA's same-device rule to every aten op,
  forward and backward (strictly: 0-dim CPU operands are refused too). Everything runs for real,
  so data-dependent code is covered as well: input validation (`bool(...)`, `.item()`), the torch
  renderer's culling and tile binning, the finite-loss check, AdamW. The meta device alone is not
  enough: bmm, mm, einsum, conv2d, linear, index_select and copy_ accept a CPU operand on meta
  without an error (torch 2.13), meta tensors have no values for the data-dependent parts, and
  `torch.autocast("meta", enabled=False)`, which the model enters, raises.
- With CUDA available, the same tests also run on the GPU itself (parameter `cuda`), plus a bf16
  autocast training step: autocast is not emulated on the stand-in device, so reduced precision is
  covered on a GPU only.

Coverage: cameras (validation and converters), Gaussians, the Gaussian adapter alone in each of its
modes and ablations, forward and backward of every preset (tiny here and in the training steps with
both adapters; small, base and large marked slow, the two-scale ones with their depth cascade's
coarse surfels), the training losses (MSE, LPIPS with random weights, depth, normal, close-up and
closure terms, cascade weighting), full training steps (surfel and EWA renders, every loss term),
and the host synchronisations of a step (exact counts, so a new one is noticed).
"""

from __future__ import annotations

import contextlib
import importlib.util
import math
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from surfsplat import Cameras
from surfsplat.geometry.cameras import rigid_inverse, validate_c2w, validate_intrinsics
from surfsplat.geometry.gaussians import Gaussians
from surfsplat.model import SurfSplat
from surfsplat.model.adapter import AdapterConfig, GaussianAdapter
from surfsplat.testing.standin_device import STANDIN, UPLOAD, DeviceMixError, StandinDevice, StandinTensor, standin
from surfsplat.train.cascade import intermediate_gaussians, num_intermediate_depths
from surfsplat.train.losses import (
    ImageLoss,
    LossConfig,
    alpha_at_window,
    cascade_loss,
    geometry_loss,
    highres_loss,
)

REPO = Path(__file__).resolve().parents[2]
SIZE = 32  # image side of the model tests: the smallest every preset accepts


def _load_host_syncs():
    spec = importlib.util.spec_from_file_location("host_syncs", REPO / "benchmarks" / "host_syncs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


host_syncs = _load_host_syncs()

DEVICES = ["standin"] + (["cuda"] if torch.cuda.is_available() else [])


class _Cuda:
    def __init__(self) -> None:
        self.device = torch.device("cuda", torch.cuda.current_device())  # what tensors report


@contextlib.contextmanager
def on_device(kind: str) -> Iterator[StandinDevice | _Cuda]:
    """The device under test: the stand-in (its rules active in the body) or the real GPU."""
    if kind == "standin":
        with StandinDevice() as dev:
            yield dev
    else:
        yield _Cuda()


def assert_on(device: torch.device, *tensors: torch.Tensor) -> None:
    for t in tensors:
        assert t.device == device, f"tensor of shape {tuple(t.shape)} on {t.device}, expected {device}"
        if device == STANDIN:
            assert isinstance(t, StandinTensor)


def assert_module_on(module: torch.nn.Module, device: torch.device, *, grads: bool) -> None:
    """Every parameter and buffer on `device`; with `grads`, every gradient that exists too (and some do)."""
    assert_on(device, *module.parameters(), *module.buffers())
    if grads:
        with_grad = [p.grad for p in module.parameters() if p.grad is not None]
        assert with_grad, "backward reached no parameter"
        assert_on(device, *with_grad)


def cameras(n: int, size: int, dtype=torch.float32) -> Cameras:
    """n cameras on a short baseline, each turned a little (R != I exercises every rotation path)."""
    K = torch.tensor([[0.9 * size, 0, size / 2], [0, 0.9 * size, size / 2], [0, 0, 1.0]], dtype=dtype)
    c2w = torch.eye(4, dtype=dtype).repeat(n, 1, 1)
    for i in range(n):
        angle = 0.05 * (i + 1)
        c, s = math.cos(angle), math.sin(angle)
        c2w[i, :3, :3] = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=dtype)
        c2w[i, 0, 3] = 0.15 * i
    return Cameras(c2w, K.repeat(n, 1, 1))


# ---------------------------------------------------------------------------------------------- the method
def test_standin_refuses_cpu_operands_where_meta_does_not() -> None:
    """The reported bug's pattern, and ops whose meta kernels let a CPU operand through, all raise."""
    with StandinDevice() as dev:
        R = standin(torch.eye(3).repeat(2, 1, 1))
        with pytest.raises(DeviceMixError, match="found at least two devices, meta and cpu"):
            R.transpose(1, 2) @ R - torch.eye(3, dtype=R.dtype)
        cases = {
            "bmm": lambda: R @ torch.ones(2, 3, 3),
            "mm": lambda: R[0] @ torch.ones(3, 3),
            "einsum": lambda: torch.einsum("bij,bjk->bik", R, torch.ones(2, 3, 3)),
            "conv2d": lambda: F.conv2d(R[None], torch.ones(1, 2, 1, 1)),
            "index_select": lambda: R.index_select(0, torch.tensor([1])),
            "copy_": lambda: R.clone().copy_(torch.ones(2, 3, 3)),
            "cpu scalar": lambda: R * torch.tensor(2.0),
        }
        for name, op in cases.items():
            with pytest.raises(DeviceMixError):
                op()
                pytest.fail(name)
        # Made on the device: accepted, and values are real (data-dependent code runs).
        err = R.transpose(1, 2) @ R - torch.eye(3, dtype=R.dtype, device=R.device)
        assert_on(dev.device, err, torch.tensor([1.0], device=R.device), torch.zeros_like(R), R.new_ones(2))
        assert float(err.abs().max()) == 0.0 and err.tolist() == [[[0.0] * 3] * 3] * 2
        kinds = [s.kind for s in dev.syncs]
        assert kinds == [
            UPLOAD,
            "scalar read (.item/bool/float/int)",
            "copy to the CPU",
        ]  # tensor([1.0]), float, tolist


def test_standin_backward_keeps_gradients_on_the_device() -> None:
    with StandinDevice() as dev:
        x = standin(torch.randn(4, 3), requires_grad=True)
        (x @ torch.ones(3, 2, device=x.device)).square().sum().backward()
        assert_on(dev.device, x.grad)
        with pytest.raises(DeviceMixError):
            (x * torch.ones(4, 3)).sum().backward()


# ---------------------------------------------------------------------------------------------- geometry
@pytest.mark.parametrize("kind", DEVICES)
def test_cameras_validate_and_convert_on_the_device(kind: str) -> None:
    host = cameras(3, 16, dtype=torch.float64)
    with on_device(kind) as dev:
        d = dev.device
        cams = Cameras(host.c2w.to(d), host.K.to(d))  # validates: validate_c2w, validate_intrinsics
        validate_c2w("c2w", cams.c2w.float())
        validate_intrinsics("K", cams.K.float())
        outputs = [cams.w2c, cams.centers, cams.scaled(2.0).K, rigid_inverse(cams.c2w)]
        outputs += [cams.normalized_intrinsics(16, 16), cams.to_opengl(), cams.to_re10k(16, 16)]
        outputs += [cams.to_llff(16, 16)]
        round_trips = [
            Cameras.from_normalized(cams.c2w, cams.normalized_intrinsics(16, 16), 16, 16),
            Cameras.from_opengl(cams.to_opengl(), cams.K),
            Cameras.from_re10k(cams.to_re10k(16, 16), 16, 16),
            Cameras.from_llff(cams.to_llff(16, 16)),
        ]
        for c in round_trips:
            outputs += [c.c2w, c.K]
        assert_on(d, *outputs)


@pytest.mark.parametrize("kind", DEVICES)
def test_gaussians_validate_and_derive_on_the_device(kind: str) -> None:
    n = 8
    g = torch.Generator().manual_seed(0)
    fields = {
        "means": torch.randn(n, 3, generator=g),
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.rand(n, 2, generator=g),
        "opacities": torch.rand(n, generator=g),
        "sh": torch.randn(n, 3, 4, generator=g),
    }
    with on_device(kind) as dev:
        leaves = {k: v.to(dev.device).requires_grad_() for k, v in fields.items()}
        gaussians = Gaussians(**leaves)  # validated
        both = Gaussians.cat([gaussians, gaussians.detach()])
        picked = both.subset(torch.arange(4, device=dev.device))
        total = gaussians.covariances.sum() + gaussians.normals.sum() + picked.means.sum()
        total = total + picked.opacities.sum() + picked.sh.sum()
        total.backward()
        assert_on(dev.device, *(v.grad for v in leaves.values()))


# ---------------------------------------------------------------------------------------------- adapter
ADAPTERS = {
    "paper": {},
    "official": {"mode": "official"},
    "regressed": {"prior": "none"},
    "gaussian3d": {"primitive": "gaussian3d"},
    "footprint-inward-floor": {
        "tangent_clamp_unit": "footprint",
        "multiplier_gradient": "inward",
        "scale_floor": 0.5,
    },
    "no-fab-sh0": {"opacity_max": 1.0, "sh_degree": 0, "init_sh_from_image": False},
}


@pytest.mark.parametrize("kind", DEVICES)
@pytest.mark.parametrize("name", sorted(ADAPTERS))
def test_adapter_forward_backward_on_the_device(kind: str, name: str) -> None:
    adapter = GaussianAdapter(AdapterConfig(**ADAPTERS[name]))
    b, v, h, w = 1, 2, 6, 8
    g = torch.Generator().manual_seed(1)
    cams = cameras(b * v, w)
    inputs = {
        "depths": 1 + torch.rand(b, v, h, w, generator=g),
        "raw": torch.randn(b, v, adapter.num_raw_channels, h, w, generator=g),
        "images": torch.rand(b, v, 3, h, w, generator=g),
    }
    with on_device(kind) as dev:
        leaves = {k: t.to(dev.device).requires_grad_() for k, t in inputs.items()}
        K = cams.K.reshape(b, v, 3, 3).to(dev.device)
        c2w = cams.c2w.reshape(b, v, 4, 4).to(dev.device)
        out = adapter(leaves["depths"], leaves["raw"], leaves["images"], K, c2w)
        g_out = out.gaussians
        tensors = [g_out.means, g_out.quats, g_out.scales, g_out.opacities, g_out.sh]
        tensors += [out.scales_mul, out.normals, out.scales, out.rotations]
        if g_out.explicit_covariances is not None:
            tensors.append(g_out.explicit_covariances)
        assert_on(dev.device, *tensors)
        sum(t.sum() for t in tensors).backward()
        assert_on(dev.device, leaves["depths"].grad, leaves["raw"].grad)


# ---------------------------------------------------------------------------------------------- model
# The tiny preset with the official adapter runs in test_training_step_on_the_device; the released
# sizes take seconds each (hundreds of millions of parameters on two CPU cores), hence `slow`.
MODELS = [
    pytest.param("tiny", "paper", id="tiny-paper"),
    pytest.param("small", "official", id="small-official", marks=pytest.mark.slow),
    pytest.param("base", "paper", id="base-paper", marks=pytest.mark.slow),
    pytest.param("large", "official", id="large-official", marks=pytest.mark.slow),
]


@pytest.mark.parametrize("kind", DEVICES)
@pytest.mark.parametrize(("preset", "adapter"), MODELS)
def test_model_forward_backward_on_the_device(kind: str, preset: str, adapter: str) -> None:
    """Every preset, moved to the device as a user does (a tensor kept as a plain attribute instead
    of a buffer would stay behind). The adapter's code does not depend on the preset, so each size
    runs with one adapter: the released sizes mostly with the official one of their checkpoints.
    Two-scale presets (base, large) also build the cascade's coarse surfels, as training does."""
    torch.manual_seed(0)
    model = SurfSplat.from_preset(preset, adapter=adapter).train()
    images = torch.rand(1, 2, 3, SIZE, SIZE)
    cams = cameras(2, SIZE)
    cascade = num_intermediate_depths(model) > 0
    with on_device(kind) as dev:
        model = model.to(dev.device)
        assert_module_on(model, dev.device, grads=False)
        x, c = images.to(dev.device), cams.to(dev.device)
        near = torch.full((1, 2), 0.5, device=dev.device)
        prediction = model(x, c, near, 100.0, return_intermediates=cascade)
        gaussians = [prediction.gaussians]
        if cascade:
            gaussians += intermediate_gaussians(model, prediction, x, c, near, torch.full_like(near, 100.0))
        loss = prediction.depths.mean()
        for g in gaussians:
            assert_on(dev.device, g.means, g.quats, g.scales, g.opacities, g.sh)
            loss = loss + g.means.square().mean() + g.scales.mean() + g.opacities.mean() + g.sh.mean()
        loss.backward()
        assert_module_on(model, dev.device, grads=True)


# ---------------------------------------------------------------------------------------------- losses
@pytest.mark.parametrize("kind", DEVICES)
def test_losses_forward_backward_on_the_device(kind: str) -> None:
    b, v, h, w = 1, 2, 16, 16
    g = torch.Generator().manual_seed(2)
    truth = torch.rand(b, v, 3, h, w, generator=g)
    renders = [torch.rand(b, v, 3, h, w, generator=g) for _ in range(2)]
    K = cameras(b * v, w).K.reshape(b, v, 3, 3)
    K_hr = K * torch.tensor([2.0, 2.0, 1.0])[:, None]
    depth = 1 + torch.rand(b, v, h, w, generator=g)
    true_depth = (1 + torch.rand(b, v, 1, h, w, generator=g)) * (torch.rand(b, v, 1, h, w, generator=g) > 0.2)
    alpha_hr = torch.rand(b, v, 1, 2 * h, 2 * w, generator=g)
    config = LossConfig(depth_weight=0.5, normal_weight=0.25, highres_weight=1.0, closure_weight=0.5)
    loss = ImageLoss(config, lpips=host_syncs.random_lpips())
    with on_device(kind) as dev:
        d = dev.device
        loss = loss.to(d)
        assert_module_on(loss, d, grads=False)
        leaves = [r.to(d).requires_grad_() for r in renders]
        pred_depth = depth.to(d).requires_grad_()
        pred_alpha = alpha_hr.to(d).requires_grad_()
        total, terms = cascade_loss(loss, leaves, truth.to(d))
        geometry = geometry_loss(config, pred_depth, true_depth.to(d), K.to(d))
        window = alpha_at_window(torch.rand(b, v, 1, h, w).to(d), K.to(d), K_hr.to(d), (2 * h, 2 * w))
        color_hr = F.interpolate(leaves[-1].flatten(0, 1), scale_factor=2.0).reshape(b, v, 3, 2 * h, 2 * w)
        close_up = highres_loss(config, color_hr, pred_alpha, torch.rand(b, v, 3, 2 * h, 2 * w).to(d), window)
        scalars = [total, geometry.total, close_up.total, *(t.lpips for t in terms), *(t.mse for t in terms)]
        assert_on(d, window, *scalars)
        (total + geometry.total + close_up.total).backward()
        assert_on(d, pred_depth.grad, pred_alpha.grad, *(r.grad for r in leaves))


# ---------------------------------------------------------------------------------------------- training
STEPS = {
    # The paper's loss plus every optional term (depth, normal, close-up, closure): surfel renders.
    "paper-all-terms": {
        "adapter": "paper",
        "overrides": {
            "loss.depth_weight": 0.1,
            "loss.normal_weight": 0.1,
            "loss.highres_weight": 0.5,
            "loss.closure_weight": 0.5,
        },
        "highres_factor": 2,
    },
    # The release's adapter: EWA renders of explicit covariances.
    "official": {"adapter": "official", "lpips": False},
}


@pytest.mark.parametrize("kind", DEVICES)
@pytest.mark.parametrize("name", sorted(STEPS))
def test_training_step_on_the_device(kind: str, name: str) -> None:
    """`training_step` as `fit` runs it: forward, render, losses, backward, clipping, AdamW."""
    model, make_optimizer, loss_fn, batch, config = host_syncs.build_step("tiny", **STEPS[name])
    before = [p.detach().clone() for p in model.parameters()]
    with on_device(kind) as dev:
        model, loss_fn, batch = model.to(dev.device), loss_fn.to(dev.device), batch.to(dev.device)
        out = host_syncs.run_step(model, make_optimizer, loss_fn, batch, config)
        assert out.nonfinite is None
        assert_on(dev.device, out.loss, out.grad_norm, *out.renders)
        assert_module_on(model, dev.device, grads=False)
        after = [p.detach().elem if isinstance(p, StandinTensor) else p.detach().cpu() for p in model.parameters()]
    assert any(not torch.equal(a, b) for a, b in zip(after, before)), "AdamW changed no parameter"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="autocast is not emulated on the stand-in device")
def test_bf16_training_step_on_cuda() -> None:
    model, make_optimizer, loss_fn, batch, config = host_syncs.build_step("tiny", "paper", size=64, targets=2)
    d = _Cuda().device
    model, loss_fn, batch = model.to(d), loss_fn.to(d), batch.to(d)
    out = host_syncs.run_step(model, make_optimizer, loss_fn, batch, config, amp_dtype=torch.bfloat16)
    assert out.nonfinite is None and math.isfinite(float(out.loss))
    assert_module_on(model, d, grads=False)


# ---------------------------------------------------------------------------------------------- host syncs
# Host synchronisations of one training step (benchmarks/host_syncs.py defaults: tiny preset, paper
# adapter, 32x32, one target view, MSE + 0.05 LPIPS, torch renderer), per (file (function), kind).
# Lines are left out so that edits elsewhere in a file do not matter; the benchmark prints them.
SCALAR = "scalar read (.item/bool/float/int)"
EXPECTED_SYNCS = {
    # The training step skips the value checks of the public forward (finite images in [0, 1], near <
    # far, pinhole K, rigid c2w: 18 host reads), made where its batches are read; inverses through
    # inv_ex read no error flag; the SH mask, the partner-view table and the Swin mask are made on
    # the device. What is left outside the renderer: the SH fit operators uploaded (2) and the one
    # finite-step flag.
    ("geometry/sh_rotation.py (sh_rotation_matrix)", UPLOAD): 2,
    # The torch renderer, once per target view: culling (nonzero), tile binning (repeat_interleave's
    # total and sign check, bincount's min and max), busy tiles and their sorted counts (boolean
    # mask, tolist), then per block of depth slots "any pair left?" and "all pixels saturated?".
    ("render/torch_backend.py (_cull_and_sort)", "nonzero (data-dependent size)"): 1,
    ("render/torch_backend.py (bin_tiles)", "repeat_interleave without output_size"): 2,
    ("render/torch_backend.py (bin_tiles)", "bincount (output size from the values)"): 2,
    ("render/torch_backend.py (composite)", "boolean-mask indexing (data-dependent size)"): 1,
    ("render/torch_backend.py (composite)", "copy to the CPU"): 1,
    ("render/torch_backend.py (composite)", SCALAR): 2,
    # The step's one decision, one flag: are the loss and the gradient norm finite (skip the update if not).
    ("train/loop.py (_nonfinite_reason)", SCALAR): 1,
}


def _without_line(where: str) -> str:
    path, function = where.split(" ", 1)
    return f"{path.rsplit(':', 1)[0]} {function}"


def test_host_syncs_of_a_training_step_are_the_expected_ones() -> None:
    """Every device-to-host wait of one step, by place: a new one (a `.item()` for logging, a
    boolean mask) fails here. The losses themselves (MSE, LPIPS), backward, clipping and AdamW
    wait for nothing."""
    report = host_syncs.measure()
    found = Counter()
    for row in report["rows"]:
        found[(_without_line(row["where"]), row["kind"])] += row["waits"]
    assert dict(found) == EXPECTED_SYNCS
    assert report["total"] == sum(EXPECTED_SYNCS.values()) and math.isfinite(report["loss"])
