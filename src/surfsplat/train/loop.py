"""The training loop: `fit(config)` trains SurfSplat and returns what happened.

    result = fit(train_preset("tiny", out_dir="runs/tiny"))       # one process
    torchrun --nproc_per_node 2 -m surfsplat train --preset tiny   # the same loop on two ranks

Read top to bottom, one step is: learning rate from the step (pure function), the batch of the
step (a function of seed and step), forward under autocast, render the target views (surfel or
EWA, training tau_alpha), MSE + lambda LPIPS (+ the cascade's coarse renders), backward (DDP
averages gradients over ranks), clip, AdamW. Rank 0 alone writes checkpoints, TensorBoard events,
metrics.jsonl and the progress; every number it reports is first reduced over all ranks.

TensorBoard (`tensorboard --logdir <out_dir>/tensorboard`), written with torch's SummaryWriter:
- scalars: loss/total, loss/mse, loss/lpips (and loss/depth, loss/normal when the loss supervises
  geometry); train/grad_norm, train/lr (the main group's rate),
  train/lr_vit (the pretrained ViT's), train/seconds_per_step, train/samples_per_second; at each
  validation val/x{s}/{psnr,ssim,lpips}, val/depth/{abs_rel,delta1}, val/closure/{closure,alpha_x{s},
  undersized,multiplier_at_low} (`surfsplat.metrics.closure`), val/num_images; loss/highres and
  loss/closure when the loss supervises close-ups. metrics.jsonl
  holds the same values, one JSON line per logged step.
- images: train/context_target_render (context, target and render rows of one training sample)
  every image_every steps; val/x{s} (a held-out view's truth, upsampled as the metric compares it,
  beside the render at s times the resolution) at each validation.
- text: config, the run's full configuration as JSON (also config.json).
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import logging
import math
import random
import time
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn.parallel import DistributedDataParallel

from ..data.dataset import mix_seed
from ..export.figures import image_grid
from ..metrics.lpips import Lpips, LpipsUnavailable, try_load_lpips
from ..model.checkpoint import (
    describe_init,
    load_checkpoint,
    load_depth_anything_v2,
    load_release_weights,
    load_unimatch,
)
from ..model.decoder import decoder_mode, render_views
from ..model.pretrained import resolve, resolve_checkpoint, with_adapter
from ..model.surfsplat import PRESETS, SurfSplat, SurfSplatConfig
from ..render.types import Backend, RenderMode
from ..utils.atomic import write_text
from ..utils.checks import SurfSplatInputError, read_json
from ..utils.heap import reuse_freed_memory
from ..utils.log import progress
from ..utils.precision import autocast_dtype
from ..utils.precision import resolve_precision as resolve_device_precision
from .cascade import intermediate_gaussians, num_intermediate_depths
from .checkpoint import (
    TrainingState,
    capture_environment,
    capture_rng,
    changed_entries,
    latest_checkpoint,
    load_training_checkpoint,
    read_environment,
    restore_rng,
    save_training_checkpoint,
    software_identity,
)
from .config import TrainConfig, config_from_dict
from .data import TrainBatch, augment, build_train_batches, build_validation_samples
from .distributed import (
    DistributedContext,
    all_gather_objects,
    all_reduce_mean,
    all_reduce_sum,
    barrier,
    init_distributed,
    shutdown,
)
from .losses import (
    GeometryTerms,
    HighresTerms,
    ImageLoss,
    LossTerms,
    alpha_at_window,
    cascade_loss,
    geometry_loss,
    highres_loss,
    supervises_geometry,
    supervises_highres,
)
from .schedule import learning_rate
from .validation import validate

logger = logging.getLogger("surfsplat.train")

VIT_PREFIX = "encoder.vit."  # parameters of the pretrained monocular ViT (their own learning rate)


@dataclass
class TrainResult:
    """What a run did (the same on every rank but `rank` and `checkpoint`, which rank 0 alone writes)."""

    out_dir: Path
    rank: int  # this process's rank (0 reports)
    start_step: int  # 0, or the step the run resumed from
    step: int  # optimizer steps completed
    losses: list[tuple[int, float]] = field(default_factory=list)  # (step, loss averaged over ranks)
    validation: dict[int, dict[str, float]] = field(default_factory=dict)  # step -> metrics
    checkpoint: Path | None = None  # the newest checkpoint of the run (written, or resumed from)
    seconds: float = 0.0  # wall time of the loop
    data_seconds: float = 0.0  # of which waiting for the next batch: the loader and the copy to the device
    nonfinite_steps: list[tuple[int, str]] = field(default_factory=list)  # (step, reason) of skipped updates
    precision: str = "fp32"  # what the forward passes ran in: fp32, or autocast bf16 / fp16 (float32 weights)


# ------------------------------------------------------------------------------------------ setup
# Adapter fields that decide the head's channel layout or what its channels mean as a whole: an
# initial checkpoint must agree on these; the others may change between the runs.
_ADAPTER_LAYOUT = ("mode", "prior", "primitive", "sh_degree")


def build_model(config: TrainConfig) -> SurfSplat:
    """The network of `config.model`, with its initial weights (random, ours, released, pretrained
    branches). Names are resolved through the weights registry (fetched once when missing)."""
    m = config.model
    if m.init_checkpoint is not None:
        model = load_checkpoint(resolve_checkpoint(resolve(m.init_checkpoint, role="model")[0]))
        layout = [f for f in _ADAPTER_LAYOUT if getattr(model.cfg.adapter, f) != getattr(m.adapter, f)]
        if model.cfg.encoder != PRESETS[m.preset] or layout:
            raise SurfSplatInputError(
                f"model.init_checkpoint: {m.init_checkpoint} holds a different network than preset {m.preset!r} "
                f"with the configured adapter" + (f" (adapter {', '.join(layout)} differ)" if layout else "")
            )
        # Fields that only change how the head's channels are read (bounds, clamps, thresholds)
        # follow the run's configuration: fine-tuning under a new rule is the point of setting them.
        changed = {
            f.name: getattr(m.adapter, f.name)
            for f in dataclasses.fields(m.adapter)
            if getattr(model.cfg.adapter, f.name) != getattr(m.adapter, f.name)
        }
        if changed:
            before = model.cfg.adapter
            model = with_adapter(model, changed)
            shown = ", ".join(f"{k} {getattr(before, k)!r} -> {v!r}" for k, v in changed.items())
            model.init_report = [f"adapter of {m.init_checkpoint} changed: {shown}"]
        return model
    model = SurfSplat(SurfSplatConfig(encoder=PRESETS[m.preset], adapter=m.adapter))
    reports = {}
    if m.release_weights is not None:
        reports[f"release {m.release_weights}"] = load_release_weights(model, resolve(m.release_weights, "model")[0])
    if m.init.monodepth is not None:
        path = resolve(m.init.monodepth, role="monodepth")[0]
        reports[f"monodepth {m.init.monodepth}"] = load_depth_anything_v2(model, path)
    if m.init.mvdepth is not None:
        path = resolve(m.init.mvdepth, role="mvdepth")[0]
        reports[f"mvdepth {m.init.mvdepth}"] = load_unimatch(model, path)
    # The release loads these with strict=False and never says what was filled; `fit` prints this.
    model.init_report = describe_init(model, reports) if reports else []
    return model


def build_optimizer(model: nn.Module, config: TrainConfig) -> torch.optim.AdamW:
    """AdamW with two groups: the pretrained ViT (vit_lr) and everything else (lr), as the release."""
    vit, rest = [], []
    for name, param in model.named_parameters():
        if param.requires_grad:
            (vit if name.startswith(VIT_PREFIX) else rest).append(param)
    o = config.optim
    groups = [
        {"params": vit, "lr": o.vit_lr, "peak_lr": o.vit_lr, "name": "vit"},
        {"params": rest, "lr": o.lr, "peak_lr": o.lr, "name": "rest"},
    ]
    return torch.optim.AdamW(
        [g for g in groups if g["params"]], lr=o.lr, betas=o.betas, eps=o.eps, weight_decay=o.weight_decay
    )


def set_learning_rate(optimizer: torch.optim.Optimizer, step: int, config: TrainConfig) -> float:
    """Every group at its peak times the schedule of `step`; returns the main group's rate."""
    o = config.optim
    for group in optimizer.param_groups:
        group["lr"] = learning_rate(step, group["peak_lr"], config.steps, o.warmup_fraction, o.initial_div, o.final_div)
    return optimizer.param_groups[-1]["lr"]


def resolve_precision(config: TrainConfig, device: torch.device) -> torch.dtype | None:
    """The autocast dtype (None: full float32). `auto` and `bf16` follow `surfsplat.utils.precision`
    (auto: bf16 where the device computes it natively, AMX / AVX512-BF16 CPUs included); fp16
    (with loss scaling) needs a GPU. Weights and optimizer state stay float32 in every case."""
    if config.precision == "fp16":
        if device.type != "cuda":
            raise SurfSplatInputError("precision: 'fp16' mixed precision needs a CUDA device (use bf16 or fp32 on CPU)")
        return torch.float16
    return autocast_dtype(resolve_device_precision(config.precision, device))


class _Reporter:
    """Rank 0's outputs: TensorBoard events, metrics.jsonl and progress (a bar on a terminal, log
    lines elsewhere). Other ranks hold an inactive reporter."""

    def __init__(self, config: TrainConfig, ctx: DistributedContext, start_step: int) -> None:
        self.active = ctx.is_main
        self.out = Path(config.out_dir)
        self.writer: Any = None
        self.bar: Any = None
        if not self.active:
            return
        # Imported here: only rank 0 writes events, and the command line's start-up stays fast.
        from torch.utils.tensorboard import SummaryWriter

        self.out.mkdir(parents=True, exist_ok=True)
        config_json = json.dumps(config.to_dict(), indent=1)
        write_text(self.out / "config.json", config_json)
        self.writer = SummaryWriter(log_dir=str(self.out / "tensorboard"))
        # Fenced so that TensorBoard's markdown keeps the JSON's layout.
        self.writer.add_text("config", f"```json\n{config_json}\n```", global_step=start_step)
        self.jsonl = open(self.out / "metrics.jsonl", "a")
        self.bar = progress(total=config.steps, initial=start_step, desc="train", unit="step", enabled=config.progress)

    def scalars(self, step: int, values: dict[str, float]) -> None:
        if not self.active:
            return
        for tag, value in values.items():
            # NaN and inf are written as they are: TensorBoard shows them, so a diverging run is visible.
            self.writer.add_scalar(tag, value, global_step=step)
        self.jsonl.write(json.dumps({"step": step, **values}) + "\n")
        self.jsonl.flush()
        self.writer.flush()

    def image(self, step: int, tag: str, picture: Tensor) -> None:
        """picture: [3, H, W] in [0, 1]."""
        if self.active:
            self.writer.add_image(tag, picture.detach().float().clamp(0, 1).cpu(), global_step=step)

    def progress(self, **postfix: str) -> None:
        """One step done; new postfix values (loss, rate) when given."""
        if self.bar is not None:
            if postfix:
                self.bar.set_postfix(postfix, refresh=False)
            self.bar.update(1)

    def message(self, text: str) -> None:
        if self.active:
            logger.info(text)

    def close(self) -> None:
        if not self.active:
            return
        if self.bar is not None:
            self.bar.close()
        self.writer.close()
        self.jsonl.close()


def _resume_path(config: TrainConfig, resume: bool | str | Path) -> Path | None:
    if resume is False:
        return None
    if resume is True or resume == "auto":
        found = latest_checkpoint(config.out_dir)
        if found is None and resume is True:
            raise SurfSplatInputError(f"resume: no checkpoint in {Path(config.out_dir) / 'checkpoints'}")
        return found
    return Path(resume)


def _first_nonfinite_parameter(model: nn.Module) -> str | None:
    """The name of the first parameter holding NaN or inf, or None."""
    for name, param in model.named_parameters():
        if not bool(torch.isfinite(param.detach()).all()):
            return name
    return None


# ------------------------------------------------------------------------------------------ one step
@dataclass
class StepOutput:
    loss: Tensor  # the optimised scalar (cascade-weighted sum)
    terms: list[LossTerms]  # per render, coarse to final
    grad_norm: Tensor  # global gradient norm before clipping
    renders: list[Tensor]  # [B, V, 3, H, W] per render, coarse to final
    geometry: GeometryTerms | None = None  # depth / normal supervision when the loss has it
    highres: HighresTerms | None = None  # close-up supervision when the loss has it
    nonfinite: str | None = None  # why the update was skipped (a NaN/inf loss or gradient, named), else None


def training_step(
    net: nn.Module,
    model: SurfSplat,
    batch: TrainBatch,
    loss_fn: ImageLoss,
    optimizer: torch.optim.Optimizer,
    *,
    mode: RenderMode,
    backend: Backend = "auto",
    amp_dtype: torch.dtype | None = None,
    scaler: torch.amp.GradScaler | None = None,
    grad_clip: float = 0.5,
    cascade: bool = False,
) -> StepOutput:
    """One optimizer step on `batch` (already on the device). `net` is `model` or its DDP wrapper."""
    context, target = batch.context, batch.target
    _, _, h, w = target.shape
    device_type = context.images.device.type
    with torch.autocast(device_type, dtype=amp_dtype or torch.float32, enabled=amp_dtype is not None):
        # validate=False: the batch's values were checked where they were read (each check is a host wait)
        prediction = net(
            context.images,
            context.cameras(),
            context.near,
            context.far,
            return_intermediates=cascade,
            validate=False,
        )
    # Coarse cascade surfels first, the final ones last (the order cascade_loss weights); the
    # renderer always works in float32, at the training tau_alpha the adapter reports.
    coarse = intermediate_gaussians(model, prediction, context.images, context.cameras(), context.near, context.far)
    decoded = [
        render_views(
            g.to(torch.float32),
            target.cameras(),
            w,
            h,
            mode=mode,
            alpha_threshold=prediction.alpha_threshold,
            backend=backend,
        )
        for g in [*coarse, prediction.gaussians]
    ]
    renders = [d.color for d in decoded]
    loss, terms = cascade_loss(loss_fn, renders, target.images)
    highres = None
    if supervises_highres(loss_fn.config):
        if target.images_hr is None:
            raise SurfSplatInputError(
                "loss.highres_weight / loss.closure_weight need high-resolution truth, and this batch has none "
                "(set data.highres_factor; procedural rooms have it)"
            )
        hh, ww = target.images_hr.shape[-2:]
        close_up = render_views(
            prediction.gaussians.to(torch.float32),
            target.highres_cameras(),
            ww,
            hh,
            mode=mode,
            alpha_threshold=prediction.alpha_threshold,
            backend=backend,
        )
        window = alpha_at_window(decoded[-1].alpha.detach(), target.K, target.K_hr, (hh, ww))
        highres = highres_loss(loss_fn.config, close_up.color, close_up.alpha, target.images_hr, window)
        loss = loss + highres.total
    geometry = None
    if supervises_geometry(loss_fn.config):
        if context.depths is None:
            raise SurfSplatInputError(
                "loss.depth_weight / loss.normal_weight need true depth, and this batch has none "
                "(procedural rooms and chunks that store depth have it)"
            )
        geometry = geometry_loss(loss_fn.config, prediction.depths.float(), context.depths, context.K)
        loss = loss + geometry.total
    if scaler is not None:
        scaler.scale(loss).backward()
        scaler.unscale_(optimizer)  # clip the true gradients, not the scaled ones
    else:
        loss.backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    grad_norm = nn.utils.get_total_norm(grads)
    # Every rank must take the same decision: the gradients are already the same on every rank
    # (DDP's all-reduce), the losses are shared in _nonfinite_reason.
    nonfinite = _nonfinite_reason(model, loss, grad_norm, fp16_overflow_is_normal=scaler is not None)
    if nonfinite is None:
        nn.utils.clip_grads_with_norm_(grads, grad_clip if grad_clip > 0 else math.inf, grad_norm)
    if scaler is not None:
        # GradScaler skips a step with inf/NaN gradients itself (and lowers its scale): fp16 overflow.
        scaler.step(optimizer)
        scaler.update()
    elif nonfinite is None:
        optimizer.step()
    optimizer.zero_grad(set_to_none=True)
    return StepOutput(
        loss=loss,
        terms=terms,
        grad_norm=grad_norm,
        renders=renders,
        geometry=geometry,
        highres=highres,
        nonfinite=nonfinite,
    )


def _nonfinite_reason(model: nn.Module, loss: Tensor, grad_norm: Tensor, fp16_overflow_is_normal: bool) -> str | None:
    """None when the step may be applied; else what is not finite, named (the loss, or the first
    parameter whose gradient holds NaN/inf). Under fp16 loss scaling an inf gradient with a finite
    loss is the scaler's routine overflow, not a fault."""
    finite_loss = torch.isfinite(loss.detach())
    distributed = torch.distributed.is_available() and torch.distributed.is_initialized()
    if not distributed and bool(finite_loss & torch.isfinite(grad_norm)):
        return None  # the healthy step reads one flag on the host, not two
    loss_ok = bool(finite_loss)
    if distributed:
        flags = torch.tensor([0 if loss_ok else 1], device=loss.device)
        torch.distributed.all_reduce(flags, op=torch.distributed.ReduceOp.MAX)
        if loss_ok and int(flags[0]):
            return "loss is not finite on another rank"
    if not loss_ok:
        return f"loss is {float(loss.detach())}"
    if bool(torch.isfinite(grad_norm)) or fp16_overflow_is_normal:
        return None
    for name, param in model.named_parameters():
        if param.grad is not None and not bool(torch.isfinite(param.grad).all()):
            return f"gradient of {name} holds NaN or inf"
    return f"gradient norm is {float(grad_norm)}"


# ------------------------------------------------------------------------------------------ the loop
def fit(config: TrainConfig, *, resume: bool | str | Path = False) -> TrainResult:
    """Train per `config`; `resume` = True (newest checkpoint of out_dir), "auto" (newest if any),
    or a checkpoint folder. Works alone or under torchrun (one process per device)."""
    if not isinstance(config, TrainConfig):
        raise SurfSplatInputError(f"config: expected a TrainConfig, got {type(config).__name__}")
    config = config_from_dict(config.to_dict())  # validates every field
    software_identity()  # digest the sources now, as this process imported them, not at the first checkpoint
    ctx = init_distributed(config.device)
    try:
        resume_from = _resume_path(config, resume)
        # on the CPU each step's large buffers reuse the last step's freed pages (utils.heap)
        heap = reuse_freed_memory() if ctx.device.type == "cpu" else nullcontext()
        with cpu_threads(config.cpu_threads or _recorded_cpu_threads(resume_from, ctx)), heap:
            return _fit(config, ctx, resume_from)
    finally:
        shutdown(ctx)


def _recorded_cpu_threads(resume_from: Path | None, ctx: DistributedContext) -> int:
    """The CPU thread count of the run that wrote `resume_from`, for this rank; 0 when there is none
    or the run trains on a GPU (where the count does not decide the gradients).

    A run left to the default thread count (cpu_threads 0) gets whatever the environment gives the
    process (OMP_NUM_THREADS, the cores), and float32 reductions on the CPU split their sums per
    thread: a resume in a shell or on a machine with another count would continue with other
    gradients. So the resumed process takes the recorded count; setting cpu_threads chooses another.
    """
    if resume_from is None or ctx.device.type != "cpu":
        return 0
    recorded = read_environment(resume_from)
    if len(recorded) != ctx.world_size:
        return 0
    threads = recorded[ctx.rank].get("cpu_threads")
    if not isinstance(threads, int) or threads <= 0:
        return 0
    if threads != torch.get_num_threads() and ctx.is_main:
        logger.info("resuming with %d CPU threads per rank, as the run that wrote %s", threads, resume_from)
    return threads


@contextmanager
def cpu_threads(threads: int) -> Iterator[None]:
    """Use `threads` CPU threads in torch and in the compiled (numba) renderer while inside;
    0 changes nothing. The previous counts come back on exit."""
    if threads <= 0:
        yield
        return
    numba = importlib.import_module("numba") if importlib.util.find_spec("numba") is not None else None
    before = (torch.get_num_threads(), numba.get_num_threads() if numba is not None else 0)
    torch.set_num_threads(threads)
    if numba is not None:
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        yield
    finally:
        torch.set_num_threads(before[0])
        if numba is not None:
            numba.set_num_threads(before[1])


def _fit(config: TrainConfig, ctx: DistributedContext, resume_from: Path | None) -> TrainResult:
    device = ctx.device
    if config.batch_size % ctx.world_size:
        raise SurfSplatInputError(f"batch_size: {config.batch_size} does not split evenly over {ctx.world_size} ranks")

    # Same initial weights on every rank (DDP also broadcasts rank 0's), then per-rank randomness.
    torch.manual_seed(config.seed)
    model = build_model(config).to(device)
    model.train()
    loss_fn = ImageLoss(config.loss).to(device)  # fails here, at start-up, without LPIPS weights
    optimizer = build_optimizer(model, config)
    amp_dtype = resolve_precision(config, device)
    precision = {None: "fp32", torch.bfloat16: "bf16", torch.float16: "fp16"}[amp_dtype]
    scaler = torch.amp.GradScaler(device.type) if amp_dtype == torch.float16 else None
    mode = decoder_mode(model.cfg.adapter, config.model.render_mode)
    cascade = num_intermediate_depths(model) > 0
    if ctx.is_main:
        logger.debug(
            "model %s: %s parameters on %s (%d ranks), autocast %s, %s rendering (%s backend)%s",
            config.model.preset,
            f"{sum(p.numel() for p in model.parameters()):,}",
            device,
            ctx.world_size,
            amp_dtype or "off",
            mode,
            config.model.render_backend,
            ", cascade loss" if cascade else "",
        )

    start_step, data_state, rng_state, extra = 0, None, None, {}
    rank_seed = mix_seed(config.seed, ctx.rank)
    torch.manual_seed(rank_seed)
    np.random.seed(rank_seed & 0xFFFF_FFFF)
    random.seed(rank_seed)
    if resume_from is not None:
        state = load_training_checkpoint(resume_from, model, map_location=device)
        changes = changed_entries(state.config, json.loads(json.dumps(config.to_dict())))
        if changes and ctx.is_main:
            logger.warning("resuming %s with changed settings: %s", resume_from, "; ".join(changes))
        optimizer.load_state_dict(state.optimizer)
        if scaler is not None and state.grad_scaler is not None:
            scaler.load_state_dict(state.grad_scaler)
        start_step = state.step
        if len(state.rng) == ctx.world_size:
            rng_state = state.rng[ctx.rank]
            data_state = state.data[ctx.rank]
            if state.environment and len(state.environment) == ctx.world_size:
                # Same state, other code, libraries, threads or precision: other bits from here on.
                saved, current = dict(state.environment[ctx.rank]), capture_environment(precision)
                if device.type != "cpu":  # the CPU thread count does not decide a GPU run's gradients
                    saved.pop("cpu_threads", None)
                    current.pop("cpu_threads", None)
                differences = changed_entries(saved, current)
                if differences:
                    logger.warning(
                        "resuming %s in another environment (%s): the run continues, but not bit-identical "
                        "to an uninterrupted one",
                        resume_from,
                        "; ".join(differences),
                    )
        elif ctx.is_main:
            logger.warning(
                "resuming %d ranks from a checkpoint of %d: random generators reseeded, streams restart their epoch; "
                "the run continues but is not bit-identical to an uninterrupted one",
                ctx.world_size,
                len(state.rng),
            )
        extra = state.extra or {}
    if start_step >= config.steps:
        raise SurfSplatInputError(
            f"steps: the checkpoint is at step {start_step}, nothing left of {config.steps} steps"
        )

    net: nn.Module = model
    if ctx.is_distributed:
        net = DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)

    stream_state = data_state if data_state and data_state.get("kind") == "stream" else None
    source = build_train_batches(
        config.data,
        config.batch_size,
        ctx.rank,
        ctx.world_size,
        config.seed,
        start_step,
        stream_state,
        with_depth=supervises_geometry(config.loss),
    )
    val_samples = (
        build_validation_samples(config.data, ctx.rank, ctx.world_size, config.seed) if config.val_every else []
    )
    val_lpips: Lpips | LpipsUnavailable = LpipsUnavailable("no validation scenes")
    if val_samples:
        # The loss's LPIPS when it has one (loaded once), else whatever the standard locations hold.
        lpips_model = loss_fn.lpips
        if lpips_model is not None:
            val_lpips = lpips_model
        else:
            val_lpips = try_load_lpips(config.loss.lpips_vgg_path, config.loss.lpips_lin_path)
    reporter = _Reporter(config, ctx, start_step)
    if resume_from is None:
        for line in getattr(model, "init_report", []):
            reporter.message(line)
    validating = config.val_every > 0 and float(all_reduce_sum(torch.tensor([len(val_samples)]), ctx)[0]) > 0
    if config.val_every and not validating:
        reporter.message("validation off: no held-out scenes (chunk datasets need data.val_roots)")
    elif validating and isinstance(val_lpips, LpipsUnavailable):
        reporter.message(f"validation without LPIPS: {val_lpips}")

    if rng_state is not None:
        # Last thing before the loop: whatever start-up drew from the generators is overwritten.
        restore_rng(rng_state)
    result = TrainResult(
        out_dir=Path(config.out_dir),
        rank=ctx.rank,
        start_step=start_step,
        step=start_step,
        checkpoint=resume_from,
        precision=precision,
    )
    pending: list[Tensor] = []  # per-step [total, mse, lpips, depth, normal, highres, closure, grad norm] not reduced
    pending_steps: list[int] = []  # the (0-based) steps of `pending`; skipped steps have no row
    consecutive = 0  # steps in a row skipped for a non-finite loss or gradient
    started = time.perf_counter()
    window_start, window_steps = started, 0
    try:
        for step in range(start_step, config.steps):
            lr = set_learning_rate(optimizer, step, config)
            tick = time.perf_counter()
            batch: TrainBatch = augment(source.next(step), config.data.flip_probability, config.seed).to(device)
            result.data_seconds += time.perf_counter() - tick  # a starved device shows here (data.num_workers)
            context, target = batch.context, batch.target

            out = training_step(
                net,
                model,
                batch,
                loss_fn,
                optimizer,
                mode=mode,
                backend=config.model.render_backend,
                amp_dtype=amp_dtype,
                scaler=scaler,
                grad_clip=config.optim.grad_clip,
                cascade=cascade,
            )
            loss, terms, grad_norm, renders = out.loss, out.terms, out.grad_norm, out.renders
            done = step + 1
            if out.nonfinite is not None:
                # The weights were not updated: count the step, show it, and stop after too many in a row.
                result.nonfinite_steps.append((done, out.nonfinite))
                consecutive += 1
                reporter.scalars(done, {"train/nonfinite_steps": float(len(result.nonfinite_steps))})
                if consecutive > config.max_nonfinite_steps:
                    raise FloatingPointError(
                        f"training stopped at step {done}: {consecutive} steps in a row not finite "
                        f"(max_nonfinite_steps {config.max_nonfinite_steps}), the last: {out.nonfinite}; "
                        f"last good checkpoint: {result.checkpoint or 'none'} (lower optim.lr, or check the data)"
                    )
                if ctx.is_main:
                    logger.warning("step %d: skipped, %s (%d in a row)", done, out.nonfinite, consecutive)
            else:
                consecutive = 0
                final, geometry, highres = terms[-1], out.geometry, out.highres
                zero = torch.zeros((), device=device)
                parts = [final.lpips] + ([geometry.depth, geometry.normal] if geometry is not None else [None, None])
                parts += [highres.highres, highres.closure] if highres is not None else [None, None]
                pending.append(
                    torch.stack(
                        [
                            loss.detach().float(),
                            final.mse.detach().float(),
                            *(zero if t is None else t.detach().float() for t in parts),
                            grad_norm.detach().float(),
                        ]
                    )
                )
                pending_steps.append(step)
            window_steps += 1
            is_last = done == config.steps

            if (done % config.log_every == 0 or is_last) and pending:
                # One reduction for the whole window: per-step values, averaged over ranks (every
                # rank skipped the same steps, so the windows agree).
                reduced = all_reduce_mean(torch.stack(pending).cpu(), ctx)
                result.losses += [(s, float(r[0])) for s, r in zip(pending_steps, reduced)]
                now = time.perf_counter()
                seconds_per_step = (now - window_start) / window_steps
                last = reduced[-1]
                values = {
                    "loss/total": float(last[0]),
                    "loss/mse": float(last[1]),
                    "train/grad_norm": float(last[-1]),
                    "train/lr": lr,
                    **{f"train/lr_{g['name']}": g["lr"] for g in optimizer.param_groups if g["name"] == "vit"},
                    "train/samples_per_second": config.batch_size / seconds_per_step,
                    "train/seconds_per_step": seconds_per_step,
                }
                names = ("lpips", "depth", "normal", "highres", "closure")
                for column, (name, term) in enumerate(zip(names, parts), start=2):
                    if term is not None:
                        values[f"loss/{name}"] = float(last[column])
                reporter.scalars(done, values)
                reporter.progress(
                    loss=f"{float(last[0]):.4f}",
                    lr=f"{lr:.2e}",
                    rate=f"{config.batch_size / seconds_per_step:.2f} samples/s",
                )
                pending.clear()
                pending_steps.clear()
                window_start, window_steps = now, 0
            else:
                reporter.progress()

            if config.image_every and (done % config.image_every == 0 or is_last) and ctx.is_main:
                picture = image_grid([list(context.images[0]), list(target.images[0]), list(renders[-1][0])])
                reporter.image(done, "train/context_target_render", picture)

            if validating and (done % config.val_every == 0 or is_last):
                grids: dict[int, Tensor] = {}  # a held-out view per factor (rank 0 writes its own)
                metrics = validate(
                    net.module if isinstance(net, DistributedDataParallel) else net,
                    val_samples,
                    ctx,
                    mode=mode,
                    backend=config.model.render_backend,
                    lpips=val_lpips,
                    factors=config.val_factors,
                    grids=grids,
                    multiplier_range=(
                        model.cfg.adapter.scale_multiplier_range if model.cfg.adapter.prior == "surface" else None
                    ),
                )
                result.validation[done] = metrics
                reporter.scalars(done, {f"val/{k}": v for k, v in metrics.items()})
                for s, picture in grids.items():
                    reporter.image(done, f"val/x{s}", picture)
                shown = ", ".join(f"{k} {v:.4f}" for k, v in metrics.items() if k.startswith(("x", "closure/closure")))
                reporter.message(f"step {done}: validation {shown}")

            if done % config.checkpoint_every == 0 or is_last:
                broken = _first_nonfinite_parameter(model)
                if broken is not None:  # never publish weights holding NaN/inf; the last good one stays
                    raise FloatingPointError(
                        f"training stopped at step {done}: parameter {broken} holds NaN or inf; "
                        f"last good checkpoint: {result.checkpoint or 'none'}"
                    )
                rng = all_gather_objects(capture_rng(), ctx)
                environments = all_gather_objects(capture_environment(precision), ctx)
                positions = all_gather_objects(source.state(), ctx)
                if ctx.is_main:
                    extra["validation"] = {str(k): v for k, v in result.validation.items()}
                    state = TrainingState(
                        step=done,
                        config=config.to_dict(),
                        optimizer=optimizer.state_dict(),
                        rng=rng,
                        environment=environments,
                        data=positions,
                        grad_scaler=scaler.state_dict() if scaler is not None else None,
                        extra=extra,
                    )
                    result.checkpoint = save_training_checkpoint(
                        config.out_dir, model, state, keep=config.keep_checkpoints
                    )
                    logger.debug("checkpoint %s", result.checkpoint)
                barrier(ctx)
            result.step = done
    finally:
        reporter.close()
    result.seconds = time.perf_counter() - started
    return result


def read_checkpoint_config(path: str | Path) -> TrainConfig:
    """The TrainConfig stored in a checkpoint folder (e.g. to resume without repeating options)."""
    document_path = Path(path) / "train_state.json"
    if not document_path.is_file():
        raise FileNotFoundError(f"{document_path}: not a training checkpoint folder")
    document = read_json(document_path)
    if not isinstance(document, dict):
        raise SurfSplatInputError(f"{document_path}: expected a JSON object with the run's 'config'")
    return config_from_dict(document.get("config"))
