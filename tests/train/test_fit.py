"""fit(): reports, checkpoints, the LPIPS term, start-up errors, and learning on synthetic rooms."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from surfsplat import Cameras
from surfsplat.metrics import LpipsUnavailable, try_load_lpips
from surfsplat.model.checkpoint import load_checkpoint
from surfsplat.model.surfsplat import SurfSplat
from surfsplat.train import build_model, fit, train_preset
from surfsplat.train.checkpoint import latest_checkpoint, verify_checkpoint
from surfsplat.train.config import override
from surfsplat.train.data import build_validation_samples
from surfsplat.train.distributed import DistributedContext
from surfsplat.train.loop import resolve_precision
from surfsplat.train.validation import validate
from surfsplat.utils.checks import SurfSplatInputError
from tests.helpers.training import validated_quick_config


def test_fit_reports_checkpoints_and_lpips_term(tmp_path: Path, lpips_files) -> None:
    vgg, lin = lpips_files
    lpips_settings = {"loss.lpips_weight": 0.05, "loss.lpips_vgg_path": str(vgg), "loss.lpips_lin_path": str(lin)}
    config = validated_quick_config(tmp_path / "run", **lpips_settings)
    result = fit(config)
    assert (result.start_step, result.step, [s for s, _ in result.losses]) == (0, 2, [0, 1])

    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    train_rows = [r for r in rows if "loss/total" in r]
    assert [r["step"] for r in train_rows] == [1, 2]
    for r in train_rows:  # Eq. 12: MSE + 0.05 LPIPS, both logged
        assert r["loss/total"] == pytest.approx(r["loss/mse"] + 0.05 * r["loss/lpips"], rel=1e-5)
        assert r["loss/lpips"] > 0
    assert [r["loss/total"] for r in train_rows] == pytest.approx([v for _, v in result.losses], rel=1e-6)
    val = result.validation[2]
    assert {"x1/psnr", "x1/ssim", "x1/lpips", "x2/psnr", "x2/ssim", "x2/lpips"} <= val.keys()
    assert val["num_images"] == 1 and 5 < val["x1/psnr"] < 50 and 0 < val["x1/ssim"] < 1
    assert any("val/x2/psnr" in r for r in rows)

    checkpoint = latest_checkpoint(tmp_path / "run")
    assert checkpoint == result.checkpoint and checkpoint.name == "step-00000002"
    verify_checkpoint(checkpoint)
    model = load_checkpoint(checkpoint / "model")  # the model part loads without the training code
    assert model.cfg.encoder == build_model(config).cfg.encoder
    assert (tmp_path / "run" / "config.json").is_file()
    assert len(list((tmp_path / "run" / "tensorboard").glob("events.out.tfevents.*"))) == 1

    with pytest.raises(SurfSplatInputError, match="nothing left"):
        fit(config, resume=True)
    more = fit(override(config, {"steps": 3}), resume=True)  # extending a finished run
    assert (more.start_step, more.step) == (2, 3)


def test_missing_lpips_weights_stop_before_anything_is_written(tmp_path: Path) -> None:
    config = validated_quick_config(
        tmp_path / "run", **{"loss.lpips_weight": 0.05, "loss.lpips_vgg_path": str(tmp_path / "none.pth")}
    )
    with pytest.raises(LpipsUnavailable, match="or set lpips_weight to 0"):
        fit(config)
    assert not (tmp_path / "run").exists()


def test_geometry_terms_join_the_loss_where_the_data_has_depth(tmp_path: Path) -> None:
    config = validated_quick_config(
        tmp_path / "run", **{"loss.depth_weight": 0.1, "loss.normal_weight": 0.2, "val_every": 0}
    )
    fit(config)
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    train_rows = [r for r in rows if "loss/total" in r]
    assert len(train_rows) == 2
    for r in train_rows:
        assert r["loss/depth"] > 0 and r["loss/normal"] > 0 and "loss/lpips" not in r
        assert r["loss/total"] == pytest.approx(
            r["loss/mse"] + 0.1 * r["loss/depth"] + 0.2 * r["loss/normal"], rel=1e-5
        )

    from surfsplat.model.decoder import decoder_mode
    from surfsplat.train import build_optimizer
    from surfsplat.train.loop import training_step
    from surfsplat.train.losses import ImageLoss

    sample = _one_sample()
    without_depth = replace(sample, context=replace(sample.context, depths=None))
    model = build_model(config)
    with pytest.raises(SurfSplatInputError, match="need true depth, and this batch has none"):
        training_step(
            model,
            model,
            without_depth,
            ImageLoss(config.loss),
            build_optimizer(model, config),
            mode=decoder_mode(model.cfg.adapter),
        )


def test_bf16_resume_is_exact(tmp_path: Path) -> None:
    """bf16 autocast keeps float32 master weights and AdamW state, so a run resumed from its step-2
    checkpoint reaches step 4 bit for bit as the run that never stopped."""
    from safetensors.torch import load_file

    def tensors(checkpoint: Path) -> dict[str, torch.Tensor]:
        return {
            **load_file(str(checkpoint / "model.safetensors")),
            **load_file(str(checkpoint / "train_state.safetensors")),
        }

    settings = {"steps": 4, "checkpoint_every": 2, "val_every": 0, "image_every": 0, "precision": "bf16"}
    straight = fit(validated_quick_config(tmp_path / "straight", **settings))
    assert straight.precision == "bf16"
    model_dtypes = {t.dtype for t in load_file(str(straight.checkpoint / "model.safetensors")).values()}
    assert model_dtypes == {torch.float32}  # master weights stay float32
    resumed_dir = tmp_path / "resumed" / "checkpoints"
    resumed_dir.mkdir(parents=True)
    shutil.copytree(tmp_path / "straight" / "checkpoints" / "step-00000002", resumed_dir / "step-00000002")
    resumed = fit(validated_quick_config(tmp_path / "resumed", **settings), resume=True)
    assert (resumed.start_step, resumed.step, resumed.precision) == (2, 4, "bf16")
    a, b = tensors(straight.checkpoint), tensors(resumed.checkpoint)
    assert a.keys() == b.keys()
    for key in a:  # weights, AdamW moments and step counts, RNG states
        assert torch.equal(a[key], b[key]), key
    assert [loss for s, loss in straight.losses if s >= 2] == [loss for _, loss in resumed.losses]


def test_resume_needs_a_checkpoint(tmp_path: Path) -> None:
    with pytest.raises(SurfSplatInputError, match="resume: no checkpoint"):
        fit(validated_quick_config(tmp_path / "empty"), resume=True)


def test_command_errors_are_one_line(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "surfsplat.train", "--preset", "tiny", "--out", str(tmp_path), "--set", "optim.lr=-1"],
        capture_output=True,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        timeout=300,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip() == "surfsplat train: error: optim.lr: expected a learning rate >= 0, got -1.0"


# Held-out PSNR of the tiny preset (64x64 synthetic rooms, 8 target views) measured on this
# project's 2-core CPU: 19.89 dB untrained, 21.99 dB after the 60 steps below (+2.10 dB), 22.28 dB
# after the preset's 200 steps. The test asks for most of the 60-step gain.
MIN_PSNR_GAIN_DB = 1.5


@pytest.mark.slow
def test_tiny_training_beats_the_untrained_model_on_held_out_rooms(tmp_path: Path) -> None:
    config = train_preset(
        "tiny", out_dir=str(tmp_path), steps=60, val_every=60, checkpoint_every=60, val_factors=(1,), progress=False
    )
    torch.manual_seed(config.seed)  # fit() initialises the model from the same seed
    untrained = build_model(config)
    ctx = DistributedContext(rank=0, world_size=1, local_rank=0, device=torch.device("cpu"))
    samples = build_validation_samples(config.data, 0, 1, config.seed)
    before = validate(untrained, samples, ctx, mode="surfel", lpips=try_load_lpips(), factors=(1,))
    after = fit(config).validation[60]
    assert after["num_images"] == before["num_images"] == 2 * config.data.val_samples
    assert after["x1/psnr"] > before["x1/psnr"] + MIN_PSNR_GAIN_DB, (before, after)
    assert after["x1/ssim"] > before["x1/ssim"]


# Held-out context-depth AbsRel after the 60 steps below (64x64 rooms), measured on this project's
# 2-core CPU: 0.382 with the paper's image loss alone, 0.320 with depth and normal supervision added
# (PSNR 22.00 and 22.31 dB). The test asks for half of that gain, at no loss of PSNR beyond 0.3 dB.
MIN_ABS_REL_GAIN = 0.03


@pytest.mark.slow
def test_geometry_supervision_gives_better_depth_on_held_out_rooms(tmp_path: Path) -> None:
    results = {}
    for name, weights in (("image", {}), ("geometry", {"loss.depth_weight": 0.1, "loss.normal_weight": 0.1})):
        config = override(
            train_preset("tiny", out_dir=str(tmp_path / name), steps=60, val_every=60, checkpoint_every=60),
            {"val_factors": [1], "progress": False, **weights},
        )
        results[name] = fit(config).validation[60]
    image, geometry = results["image"], results["geometry"]
    assert geometry["depth/abs_rel"] < image["depth/abs_rel"] - MIN_ABS_REL_GAIN, results
    assert geometry["x1/psnr"] > image["x1/psnr"] - 0.3, results


def test_precision_rules_and_float32_adapter_under_autocast(monkeypatch) -> None:
    import surfsplat.utils.precision

    cpu = torch.device("cpu")
    monkeypatch.setattr(surfsplat.utils.precision, "cpu_bf16_flags", lambda: frozenset())
    assert resolve_precision(train_preset("tiny"), cpu) is None  # auto: float32 on a CPU without native bf16
    monkeypatch.setattr(surfsplat.utils.precision, "cpu_bf16_flags", lambda: frozenset({"amx_bf16"}))
    assert resolve_precision(train_preset("tiny"), cpu) == torch.bfloat16  # auto: bf16 on an AMX CPU
    assert resolve_precision(train_preset("tiny", precision="fp32"), cpu) is None
    assert resolve_precision(train_preset("tiny", precision="bf16"), cpu) == torch.bfloat16
    with pytest.raises(SurfSplatInputError, match="'fp16' mixed precision needs a CUDA device"):
        resolve_precision(train_preset("tiny", precision="fp16"), cpu)

    torch.manual_seed(0)
    model = SurfSplat.from_preset("tiny")
    seen: list[tuple[bool, torch.dtype]] = []
    model.adapter.register_forward_pre_hook(
        lambda m, args: seen.append((torch.is_autocast_enabled("cpu"), args[0].dtype))
    )
    images = torch.rand(1, 2, 3, 32, 32)
    c2w = torch.eye(4).repeat(2, 1, 1)
    c2w[1, 0, 3] = 0.2
    cams = Cameras(c2w, torch.tensor([[30.0, 0, 16], [0, 30.0, 16], [0, 0, 1]]).repeat(2, 1, 1))
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        prediction = model(images, cams, 0.5, 20.0)
        assert torch.is_autocast_enabled("cpu")  # restored after the adapter
    # The model runs its geometry in float32 with autocast off, on the encoder's depths.
    assert seen == [(False, torch.float32)]
    assert prediction.gaussians.means.dtype == torch.float32


@pytest.mark.slow
def test_base_preset_adds_the_coarse_cascade_render_to_the_loss(tmp_path: Path) -> None:
    """base/large refine depth in two scales; the release also renders the coarse depth's surfels
    and adds 0.9 x their loss, so the logged total exceeds the final render's MSE."""
    config = override(
        train_preset("base"),
        {
            "out_dir": str(tmp_path),
            "steps": 1,
            "log_every": 1,
            "val_every": 0,
            "progress": False,
            "batch_size": 1,
            "cpu_threads": 1,
            "loss.lpips_weight": 0.0,
            "data.dataset": "synthetic",
            "data.image_shape": [32, 32],
            "data.num_target_views": 1,
            "data.synthetic_length": 1,
            "data.synthetic_supersample": 1,
        },
    )
    fit(config)
    (row,) = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    # total = 0.9 * MSE(coarse render) + MSE(final render), both MSEs of the same images in (0, 1).
    assert row["loss/mse"] < row["loss/total"] < row["loss/mse"] + 0.9 * 1.0
    assert row["loss/total"] - row["loss/mse"] > 0.1 * row["loss/mse"]


def _one_sample(size: int = 32):
    from torch.utils.data import default_collate

    from surfsplat.data.synthetic import SyntheticDataset, SyntheticDatasetConfig
    from surfsplat.train.data import to_train_batch

    dataset = SyntheticDataset(
        SyntheticDatasetConfig(length=1, image_shape=(size, size), num_target_views=2, supersample=1)
    )
    return to_train_batch(default_collate([dataset[0]]), [0])


def _first_step(sample, amp_dtype, scaler=None, backend: str = "auto"):
    from surfsplat.model.decoder import decoder_mode
    from surfsplat.train import build_optimizer
    from surfsplat.train.loop import training_step
    from surfsplat.train.losses import ImageLoss

    config = train_preset("tiny")
    torch.manual_seed(0)
    model = build_model(config).train()
    before = {k: v.detach().clone() for k, v in model.state_dict().items()}
    # the dtypes the encoder's convolutions and linear layers computed in
    computed = set()
    hooks = [
        m.register_forward_hook(lambda _m, _i, o: computed.add(o.dtype))
        for m in model.encoder.modules()
        if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear))
    ]
    out = training_step(
        model,
        model,
        sample,
        ImageLoss(config.loss),
        build_optimizer(model, config),
        mode=decoder_mode(model.cfg.adapter),
        backend=backend,
        amp_dtype=amp_dtype,
        scaler=scaler,
    )
    for hook in hooks:
        hook.remove()
    out.encoder_dtypes = computed
    moved = sum(not torch.equal(before[k], v) for k, v in model.state_dict().items())
    return out, moved


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_mixed_precision_step_on_cpu_autocast(dtype) -> None:
    # The GPU recipe (autocast, float32 adapter and renderer, GradScaler for fp16), run on CPU
    # autocast: the same loss as full precision to low-precision rounding, and a real update.
    sample = _one_sample()
    reference, _ = _first_step(sample, None)
    scaler = torch.amp.GradScaler("cpu", init_scale=2.0**10) if dtype == torch.float16 else None
    out, moved = _first_step(sample, dtype, scaler)
    assert all(r.dtype == torch.float32 for r in out.renders)  # the renderer always runs in float32
    assert torch.isfinite(out.grad_norm) and float(out.grad_norm) > 0
    assert moved > 10  # parameters took the step (a scaler skipping it on inf would leave them)
    assert float(out.loss.detach()) == pytest.approx(float(reference.loss.detach()), rel=0.01)
    # the encoder really ran in low precision (its loss can round to the float32 one on some CPUs' fp16
    # kernels: an AVX512-FP16 Xeon gave the same loss to the last bit, so the layers' outputs are checked)
    assert dtype in out.encoder_dtypes and reference.encoder_dtypes == {torch.float32}
    if scaler is not None:
        assert scaler.get_scale() == 2.0**10  # no overflow: the step was not skipped


def test_render_backend_choice_reaches_the_renderer(monkeypatch) -> None:
    import surfsplat.model.decoder as decoder

    seen = []
    real = decoder.render

    def spy(*args, **kwargs):
        seen.append(kwargs["backend"])
        return real(*args, **kwargs)

    monkeypatch.setattr(decoder, "render", spy)
    sample = _one_sample()
    ours, _ = _first_step(sample, None, backend="cpu")
    ref, _ = _first_step(sample, None, backend="torch")
    assert seen == ["cpu", "torch"]
    # The compiled renderer and the torch reference give the same training loss and gradient norm.
    assert float(ours.loss.detach()) == pytest.approx(float(ref.loss.detach()), rel=1e-5)
    assert float(ours.grad_norm) == pytest.approx(float(ref.grad_norm), rel=1e-4)
    with pytest.raises(SurfSplatInputError, match="model.render_backend"):
        override(train_preset("tiny"), {"model.render_backend": "vulkan"})
