"""Typed training configuration and presets.

One root `TrainConfig` composes the model choice, optimizer, loss, data, precision, checkpointing,
logging and validation settings. Presets are data (`TRAIN_PRESETS`); the command line and JSON
files only override fields of a preset:

    config = train_preset("tiny", out_dir="runs/tiny", steps=200)
    config = config_from_dict(json.load(open("run.json")))   # unknown keys are errors

Paper / release values (SPEC Sec. 8, the release's config/main.yaml and training script): AdamW,
lr 2e-4, pretrained ViT lr 2e-6, weight decay 0.01, one-cycle cosine schedule with 1% warm-up,
gradient clipping 0.5, 256x256 images, near 0.5 / far 100 (RealEstate10K), horizontal flips.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from typing import Any, Literal

from ..data.view_sampler import BoundedViewSamplerConfig
from ..model.adapter import AdapterConfig
from ..model.surfsplat import PRESETS
from ..render.types import BACKENDS, Backend
from ..utils.checks import SurfSplatInputError
from ..utils.configio import dataclass_from_dict
from .losses import LossConfig

Precision = Literal["auto", "fp32", "bf16", "fp16"]
DatasetKind = Literal["synthetic", "chunks"]
RenderModeChoice = Literal["auto", "surfel", "ewa"]


@dataclass(frozen=True)
class InitConfig:
    """Pretrained weights the branches start from: the paper trains from Depth Anything V2 (monocular)
    and UniMatch (multi-view). Each is a registry name (`surfsplat weights list`) or a file path."""

    monodepth: str | None = None  # monocular ViT: depth-anything-v2-vit{s,b,l} or a depth_anything_v2_*.pth
    mvdepth: str | None = None  # multi-view CNN + transformer: unimatch-gmflow-scale1 or a gmflow-*.pth


@dataclass(frozen=True)
class ModelConfig:
    """Which network to train and what it starts from."""

    preset: str = "small"  # encoder preset of surfsplat.model.surfsplat.PRESETS (tiny, small, base, large)
    adapter: AdapterConfig = field(default_factory=AdapterConfig)  # surfel adapter (paper mode, ablations)
    init_checkpoint: str | None = None  # our own model checkpoint (.safetensors + .json, or its name) to start from
    release_weights: str | None = None  # a released SurfSplat .ckpt/.pth (or its name) to fine-tune from
    init: InitConfig = field(default_factory=InitConfig)  # pretrained branches (the paper's initialisation)
    render_mode: RenderModeChoice = "auto"  # auto: surfel for the paper adapter, ewa for official / 3D Gaussians
    render_backend: Backend = "auto"  # surfsplat.render backend: auto = gsplat on CUDA, compiled on CPU


@dataclass(frozen=True)
class OptimConfig:
    """AdamW with a one-cycle cosine schedule (the release's OneCycleLR, written as a pure function)."""

    lr: float = 2e-4  # peak learning rate of every parameter outside the ViT
    vit_lr: float = 2e-6  # peak learning rate of the pretrained ViT (monocular backbone)
    weight_decay: float = 0.01  # AdamW decoupled weight decay (the release's value)
    betas: tuple[float, float] = (0.9, 0.999)  # AdamW moment decay rates (torch defaults, as the release)
    eps: float = 1e-8  # AdamW denominator epsilon
    grad_clip: float = 0.5  # maximum global gradient L2 norm; 0 turns clipping off
    warmup_fraction: float = 0.01  # share of the run spent warming up (OneCycleLR's pct_start)
    initial_div: float = 25.0  # the schedule starts at peak / initial_div (OneCycleLR's div_factor)
    final_div: float = 1e4  # and ends at peak / (initial_div * final_div) (final_div_factor)


@dataclass(frozen=True)
class DataConfig:
    """Where samples come from and how they are shaped."""

    dataset: DatasetKind = "synthetic"  # synthetic: procedural rooms; chunks: RealEstate10K-style folders
    roots: tuple[str, ...] = ()  # chunk folders for training (RE10K, ACID, or `surfsplat convert` output)
    val_roots: tuple[str, ...] = ()  # held-out chunk folders for validation (none: no validation)
    val_index: str | None = None  # evaluation index JSON fixing the validation views (none: bounded sampler)
    image_shape: tuple[int, int] = (256, 256)  # (H, W) of every view; multiples of 16
    num_context_views: int = 2  # views the model sees
    num_target_views: int = 4  # views rendered and supervised per sample
    near: float = 0.5  # depth bounds of chunk datasets (RealEstate10K values); synthetic rooms bring their own
    far: float = 100.0
    flip_probability: float = 0.5  # horizontal flip of images and cameras together (the release's augmentation)
    view_sampler: BoundedViewSamplerConfig = field(default_factory=BoundedViewSamplerConfig)  # chunk frame gaps
    synthetic_length: int = 100_000  # number of distinct synthetic training rooms
    synthetic_seed: int = 0  # seed of the synthetic training rooms (validation uses a disjoint seed)
    synthetic_supersample: int = 2  # rays per pixel per axis for synthetic images (anti-aliasing)
    # Truth of the targets at s times the resolution, for loss.highres_weight: procedural rooms ray-cast
    # it; chunks take it from frames at least s times image_shape (samples with smaller ones are skipped
    # and counted). 0 = none; a random highres_crop-pixel square of the s-times image per target (0: all).
    highres_factor: int = 0
    highres_crop: int = 0
    cache_samples: bool = False  # keep generated samples in memory (small synthetic pools on CPU)
    val_samples: int = 16  # validation samples per evaluation (split across ranks)
    num_workers: int = 0  # data-loader worker processes per rank


@dataclass(frozen=True)
class TrainConfig:
    """Everything one training run needs; stored in every checkpoint."""

    model: ModelConfig = field(default_factory=ModelConfig)  # network and initial weights
    optim: OptimConfig = field(default_factory=OptimConfig)  # AdamW, schedule, clipping
    loss: LossConfig = field(default_factory=LossConfig)  # MSE + lambda LPIPS, cascade weights
    data: DataConfig = field(default_factory=DataConfig)  # datasets and shapes
    steps: int = 600_000  # optimizer steps (the release trains 600k steps)
    batch_size: int = 16  # global batch (scenes per step), split evenly across ranks
    seed: int = 111123  # model initialisation and every random choice of the run (the release's seed)
    precision: Precision = "auto"  # auto: bf16 autocast on CUDA when supported, fp32 on CPU
    device: Literal["auto", "cpu", "cuda"] = "auto"  # auto: CUDA when available
    cpu_threads: int = 0  # CPU threads per rank for torch and the compiled renderer; 0 keeps their defaults
    out_dir: str = "runs/surfsplat"  # checkpoints, TensorBoard events, metrics.jsonl
    checkpoint_every: int = 5000  # steps between checkpoints (and one at the end)
    keep_checkpoints: int = 3  # newest checkpoints kept on disk (0 keeps all)
    log_every: int = 50  # steps between scalar logs
    image_every: int = 1000  # steps between image grids in TensorBoard (0: never)
    val_every: int = 5000  # steps between validations (0: never; also run at the end when > 0)
    val_factors: tuple[int, ...] = (1, 2, 4)  # render scales of validation: 1 = standard, 2 and 4 = HRRC
    progress: bool = True  # rank 0 shows progress: a bar on a terminal, a log line every few seconds elsewhere
    max_nonfinite_steps: int = 5  # steps in a row skipped for a NaN/inf loss or gradient before training stops

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _validate(config: TrainConfig) -> TrainConfig:
    """Range checks with one error naming the field; returns the config."""

    def need(ok: bool, name: str, expected: str, value: object) -> None:
        if not ok:
            raise SurfSplatInputError(f"{name}: expected {expected}, got {value!r}")

    m, o, d = config.model, config.optim, config.data
    need(m.preset in PRESETS, "model.preset", f"one of {sorted(PRESETS)}", m.preset)
    need(m.render_mode in ("auto", "surfel", "ewa"), "model.render_mode", "auto, surfel or ewa", m.render_mode)
    need(m.render_backend in BACKENDS, "model.render_backend", ", ".join(BACKENDS), m.render_backend)
    for name in ("lr", "vit_lr"):
        value = getattr(o, name)
        need(value >= 0, f"optim.{name}", "a learning rate >= 0", value)
    need(o.weight_decay >= 0, "optim.weight_decay", "a value >= 0", o.weight_decay)
    need(o.grad_clip >= 0, "optim.grad_clip", "a norm >= 0 (0 = off)", o.grad_clip)
    need(0 <= o.warmup_fraction < 1, "optim.warmup_fraction", "a value in [0, 1)", o.warmup_fraction)
    need(
        o.initial_div >= 1 and o.final_div >= 1,
        "optim.initial_div/final_div",
        "values >= 1",
        (o.initial_div, o.final_div),
    )
    need(d.dataset in ("synthetic", "chunks"), "data.dataset", "synthetic or chunks", d.dataset)
    h, w = d.image_shape
    need(h > 0 and w > 0 and h % 16 == 0 and w % 16 == 0, "data.image_shape", "(H, W) multiples of 16", d.image_shape)
    need(d.num_context_views >= 2, "data.num_context_views", "at least 2", d.num_context_views)
    need(d.num_target_views >= 1, "data.num_target_views", "at least 1", d.num_target_views)
    need(0 < d.near < d.far, "data.near/far", "0 < near < far", (d.near, d.far))
    need(0 <= d.flip_probability <= 1, "data.flip_probability", "a probability", d.flip_probability)
    need(d.synthetic_length >= 1, "data.synthetic_length", "at least 1", d.synthetic_length)
    need(d.synthetic_supersample >= 1, "data.synthetic_supersample", "at least 1", d.synthetic_supersample)
    need(d.highres_factor == 0 or d.highres_factor >= 2, "data.highres_factor", "0 (off) or >= 2", d.highres_factor)
    need(d.highres_crop >= 0, "data.highres_crop", "0 (whole image) or a size in pixels", d.highres_crop)
    need(
        (config.loss.highres_weight > 0 or config.loss.closure_weight > 0) <= (d.highres_factor > 0),
        "loss.highres_weight/closure_weight",
        "data.highres_factor >= 2 (they compare renders with the high-resolution truth)",
        (config.loss.highres_weight, config.loss.closure_weight),
    )
    need(d.val_samples >= 0, "data.val_samples", "a count >= 0", d.val_samples)
    need(d.num_workers >= 0, "data.num_workers", "a count >= 0", d.num_workers)
    need(config.steps >= 1, "steps", "at least 1", config.steps)
    need(config.batch_size >= 1, "batch_size", "at least 1", config.batch_size)
    need(
        config.precision in ("auto", "fp32", "bf16", "fp16"), "precision", "auto, fp32, bf16 or fp16", config.precision
    )
    need(config.device in ("auto", "cpu", "cuda"), "device", "auto, cpu or cuda", config.device)
    for name in (
        "cpu_threads",
        "checkpoint_every",
        "keep_checkpoints",
        "log_every",
        "image_every",
        "val_every",
        "max_nonfinite_steps",
    ):
        value = getattr(config, name)
        need(value >= 0, name, "a count >= 0", value)
    need(config.checkpoint_every > 0, "checkpoint_every", "at least 1", config.checkpoint_every)
    need(config.log_every > 0, "log_every", "at least 1", config.log_every)
    need(
        len(config.val_factors) > 0 and all(s >= 1 for s in config.val_factors),
        "val_factors",
        "positive integers",
        config.val_factors,
    )
    return config


# ----------------------------------------------------------------------------------------- presets
def _tiny() -> TrainConfig:
    # CPU smoke training: the ~1M-parameter `tiny` encoder on 64x64 synthetic rooms.
    # Its ViT starts random (no pretrained weights), so it takes the full learning rate; the LPIPS
    # term is off so the preset runs without the VGG files; a fixed pool of cached rooms keeps the
    # procedural ray caster out of the step time. One CPU thread: tensors this small gain little
    # from more, and a shared machine loses a lot to oversubscription (0.57 s vs 4.5 s per step
    # measured on a loaded 2-core box). Runs are bit-reproducible with any fixed thread count.
    return TrainConfig(
        model=ModelConfig(preset="tiny"),
        optim=OptimConfig(lr=1e-3, vit_lr=1e-3, warmup_fraction=0.05),
        loss=LossConfig(lpips_weight=0.0),
        data=DataConfig(
            dataset="synthetic",
            image_shape=(64, 64),
            num_target_views=2,
            synthetic_length=48,
            synthetic_supersample=1,
            cache_samples=True,
            val_samples=4,
        ),
        steps=200,
        batch_size=1,
        cpu_threads=1,
        checkpoint_every=100,
        log_every=10,
        image_every=100,
        val_every=100,
        out_dir="runs/tiny",
    )


def _release(preset: str, batch_size: int) -> TrainConfig:
    # RealEstate10K training as SPEC Sec. 8 states it; roots must be given (chunk folders).
    return TrainConfig(
        model=ModelConfig(preset=preset),
        data=DataConfig(dataset="chunks"),
        batch_size=batch_size,
        out_dir=f"runs/re10k-{preset}",
    )


TRAIN_PRESETS: dict[str, typing.Callable[[], TrainConfig]] = {
    "tiny": _tiny,
    "small": lambda: _release("small", 16),
    "base": lambda: _release("base", 8),
    "large": lambda: _release("large", 8),
}


def train_preset(name: str, **overrides: Any) -> TrainConfig:
    """The preset `name` with top-level fields replaced (nested sections: pass a whole dataclass or
    use `override`)."""
    if name not in TRAIN_PRESETS:
        raise SurfSplatInputError(f"preset: expected one of {sorted(TRAIN_PRESETS)}, got {name!r}")
    config = TRAIN_PRESETS[name]()
    try:
        config = dataclasses.replace(config, **overrides)
    except TypeError as err:
        raise SurfSplatInputError(f"preset overrides: {err}") from None
    return _validate(config)


def override(config: TrainConfig, dotted: dict[str, Any]) -> TrainConfig:
    """Replace fields by dotted path, e.g. {"optim.lr": 1e-3, "data.image_shape": (96, 96)}."""
    data = config.to_dict()
    for path, value in dotted.items():
        node = data
        parts = path.split(".")
        for part in parts[:-1]:
            if not isinstance(node.get(part), dict):
                raise SurfSplatInputError(f"{path}: no configuration section {part!r}")
            node = node[part]
        if parts[-1] not in node:
            raise SurfSplatInputError(f"{path}: unknown configuration field")
        node[parts[-1]] = value
    return config_from_dict(data)


def config_from_dict(data: object) -> TrainConfig:
    """A TrainConfig from JSON-style data (lists for tuples); unknown keys and wrong types are errors."""
    return _validate(dataclass_from_dict(TrainConfig, _upgrade(data), "config"))


def _upgrade(data: object) -> object:
    """Configurations of earlier runs named the Depth Anything V2 file `model.depth_anything`; it is
    `model.init.monodepth` now. Rewritten here so those runs still resume."""
    if not isinstance(data, dict) or not isinstance(data.get("model"), dict) or "depth_anything" not in data["model"]:
        return data
    model = dict(data["model"])
    legacy = model.pop("depth_anything")
    init = dict(model.get("init") or {})
    if legacy is not None and init.get("monodepth") is None:
        init["monodepth"] = legacy
    model["init"] = init
    return {**data, "model": model}


def paper_init(preset: str) -> dict[str, str]:
    """Dotted config fields of the paper's initialisation for `preset`: the Depth Anything V2 ViT of
    the preset's size and UniMatch's GMFlow weights (the release's pretrained_monodepth / _mvdepth)."""
    from ..model.registry import known_names, lookup

    mono = [name for name in known_names("monodepth") if lookup(name).preset == preset]
    if not mono:
        raise SurfSplatInputError(
            f"--paper-init: preset {preset!r} has no pretrained initialisation (small, base and large have)"
        )
    return {"model.init.monodepth": mono[0], "model.init.mvdepth": "unimatch-gmflow-scale1"}
