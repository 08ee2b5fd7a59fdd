"""Evaluation over an evaluation index: standard metrics and HRRC (paper Sec. 3.6) per scene.

    model, name = load_model(ModelSpec("runs/tiny/checkpoints/step-00000200"))
    samples = iter_index_samples(["data/re10k/test"], EvaluationIndex.load("evaluation_index_re10k.json"))
    result = evaluate(model, samples, EvalConfig(), lpips=try_load_lpips(), name=name)
    print(format_results({name: result}))       # the paper's table: standard / x2 / x4 / average

For every index entry the model sees the context views once; the target views are rendered at the
input resolution (standard metrics) and at 2x and 4x with K scaled by s, and scored against the
ground truth upsampled bicubically (`surfsplat.metrics.hrrc`). Where chunks carry true depth
(synthetic rooms, ScanNet) the predicted context depth is scored as well. Wall time of the forward
pass and of each render scale, and peak memory, are measured per run.

Checkpoints: our own (`model.safetensors` + `model.json`, a training checkpoint folder or a run
folder, whose newest checkpoint is taken) and the release's Lightning `.ckpt` / `.pth` files (loaded
through the key mapping into the official-compatible adapter). Ablations of a checkpoint are adapter
overrides (`opacity_max=1.0` is "w/o FAB" at inference), so `--compare` puts them side by side.
"""

from __future__ import annotations

import csv
import io
import json
import math
import resource
import sys
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import torch
from torch import Tensor

from ..data.chunks import decode_depths, decode_views, example_cameras, image_size, list_chunks, read_chunk
from ..data.eval_index import EvaluationIndex
from ..data.transforms import rescale_and_crop
from ..geometry.cameras import Cameras
from ..metrics.closure import ClosureAccumulator, ClosureMetrics, format_closure_table
from ..metrics.depth import depth_metrics
from ..metrics.hrrc import METRICS, UPSAMPLE_MODES, HrrcConfig, HrrcEvaluator, HrrcReport, format_hrrc_table
from ..metrics.lpips import Lpips, LpipsUnavailable
from ..model.decoder import decoder_mode
from ..model.pretrained import check_resolution
from ..model.surfsplat import SurfSplat
from ..render import RenderOutput, render
from ..utils.checks import SurfSplatInputError
from ..utils.log import progress
from ..utils.precision import Precision, Resolved, autocast, parse_precision, resolve_precision
from .geometry import COLUMNS as GEOMETRY_COLUMNS
from .geometry import GeometryConfig, GeometryEvaluator, GeometryReport, format_geometry_table

DEPTH_METRICS = ("abs_rel", "sq_rel", "rmse", "delta1")


# ----------------------------------------------------------------------------------------- samples
@dataclass
class EvalSample:
    """One evaluation index entry with its decoded views."""

    key: str  # index entry key
    scene: str  # chunk example key
    context_images: Tensor  # [Vc, 3, H, W]
    context_cameras: Cameras
    target_images: Tensor  # [Vt, 3, H, W]
    target_cameras: Cameras
    near: float
    far: float
    context_depths: Tensor | None = None  # [Vc, 1, H, W] true depth where the chunk has it
    context_views: tuple[int, ...] = ()
    target_views: tuple[int, ...] = ()


@dataclass
class SampleCounts:
    """What happened to the index entries (nothing is skipped silently)."""

    evaluated: int = 0
    excluded: int = 0  # null entries of the index (the benchmark leaves those scenes out)
    not_in_index: int = 0  # chunk scenes the index does not mention
    missing: list[str] = field(default_factory=list)  # index entries whose scene is in no chunk


def iter_index_samples(
    roots: Sequence[str | Path],
    index: EvaluationIndex,
    image_shape: tuple[int, int] | None = None,
    near: float = 0.5,
    far: float = 100.0,
    max_entries: int | None = None,
    counts: SampleCounts | None = None,
) -> Iterator[EvalSample]:
    """Samples for every non-null index entry whose scene is in the chunk folders, in chunk order.

    image_shape: rescale and centre-crop every view to (H, W) first (the release evaluates RE10K at
    256x256 this way), with K following exactly; None keeps the stored size.
    `counts` (optional) is filled in as the iteration proceeds.
    """
    # Inputs are checked here, eagerly; the generator below only reads.
    if not roots:
        raise SurfSplatInputError("data: expected at least one chunk folder")
    if not 0 < near < far:
        raise SurfSplatInputError(f"near/far: expected 0 < near < far, got {near}, {far}")
    folders = []
    for root in roots:
        chunks = list_chunks(root)
        if not chunks:
            raise SurfSplatInputError(f"{root}: no .torch chunks in this folder")
        folders.append(chunks)
    return _samples(
        folders, index, image_shape, near, far, max_entries, counts if counts is not None else SampleCounts()
    )


def _samples(
    folders: list[list[Path]],
    index: EvaluationIndex,
    image_shape: tuple[int, int] | None,
    near: float,
    far: float,
    max_entries: int | None,
    counts: SampleCounts,
) -> Iterator[EvalSample]:
    found: set[str] = set()
    produced = 0
    for chunks in folders:
        for chunk in chunks:
            for example in read_chunk(chunk):
                entries = index.lookup(example["key"])
                if not entries:
                    counts.not_in_index += 1
                    continue
                for entry_key, entry in entries:
                    found.add(entry_key)
                    if entry is None:
                        counts.excluded += 1
                        continue
                    if max_entries is not None and produced >= max_entries:
                        return
                    yield _decode_entry(
                        example, entry_key, entry.context, entry.target, str(chunk), image_shape, near, far
                    )
                    produced += 1
                    counts.evaluated += 1
    counts.missing = sorted(k for k, v in index.entries.items() if v is not None and k not in found)


def _decode_entry(
    example: dict,
    entry_key: str,
    context: tuple[int, ...],
    target: tuple[int, ...],
    source: str,
    image_shape: tuple[int, int] | None,
    near: float,
    far: float,
) -> EvalSample:
    num_views = example["cameras"].shape[0]
    largest = max(context + target)
    if largest >= num_views:
        raise SurfSplatInputError(
            f"{source}: index entry '{entry_key}' uses view {largest} but the scene has {num_views} views"
        )
    views = list(context) + list(target)
    images = decode_views(example, views, source)
    width, height = image_size(example, views[0], source)
    cameras = example_cameras(example, width, height, source)[torch.tensor(views)]
    depths = decode_depths(example, list(context), source)
    K = cameras.K
    c = len(context)
    if image_shape is not None and tuple(images.shape[-2:]) != tuple(image_shape):
        if depths is not None:
            _, _, depths = rescale_and_crop(images[:c], K[:c], image_shape, depths=depths)
        images, K, _ = rescale_and_crop(images, K, image_shape)
    elif depths is not None and depths.shape[-2:] != images.shape[-2:]:
        depths = torch.nn.functional.interpolate(depths, size=images.shape[-2:], mode="nearest-exact")
    cams = Cameras(cameras.c2w, K, validate=False)
    return EvalSample(
        key=entry_key,
        scene=example["key"],
        context_images=images[:c],
        context_cameras=cams[:c],
        target_images=images[c:],
        target_cameras=cams[c:],
        near=near,
        far=far,
        context_depths=depths,
        context_views=tuple(context),
        target_views=tuple(target),
    )


# ----------------------------------------------------------------------------------------- prediction
@dataclass
class ScenePrediction:
    sample: EvalSample
    gaussians: object  # unbatched surfsplat.Gaussians of the scene
    depths: Tensor  # [Vc, H, W] predicted context depth
    renders: dict[int, RenderOutput]  # factor -> target renders at s times the resolution
    seconds_forward: float
    seconds_render: dict[int, float]
    alpha_threshold: float | None = None  # tau the renders were normalised with (None: plain compositing)
    render_mode: str = "surfel"  # rasterization the renders used ("surfel" or "ewa")
    surfels: int = 0  # surfels rendered (after compaction when asked for)
    precision: Resolved = "fp32"  # what the forward pass ran in (rendering is always float32)
    scale_multipliers: Tensor | None = None  # [N, 2] the adapter's Eq. 9 multipliers (None once compacted)
    multiplier_range: float | None = None  # the clamp's r of those multipliers

    def closure_surfels(self) -> tuple[Tensor, Tensor | None, float | None]:
        """(pixel footprints [N], multipliers, r) of the rendered surfels, for `ClosureAccumulator`:
        as predicted, each surfel's own context view judges its size; compacted, the finest view."""
        from ..geometry.pixels import pixel_footprints, views_of_pixels

        cams = self.sample.context_cameras
        h, w = self.sample.context_images.shape[-2:]
        predicted = self.scale_multipliers is not None
        views = views_of_pixels(len(cams), h, w) if predicted else None
        footprints = pixel_footprints(self.gaussians, cams.to(self.gaussians.means.device), w, h, views)
        return footprints, self.scale_multipliers, self.multiplier_range


@torch.no_grad()
def predict_sample(
    model: SurfSplat,
    sample: EvalSample,
    factors: Sequence[int] = (1, 2, 4),
    mode: Literal["auto", "surfel", "ewa"] = "auto",
    alpha_threshold: float | None | Literal["model"] = "model",
    compact: int | None = None,
    precision: Precision = "fp32",
) -> ScenePrediction:
    """Reconstruct a sample's scene from its context views and render its targets at every factor
    (compacted first at level `compact`, see `surfsplat.compact`, when given). `precision` is the
    forward pass's (auto, fp32, bf16; `surfsplat.utils.precision`)."""
    device = next(model.parameters()).device
    h, w = sample.target_images.shape[-2:]
    images = sample.context_images[None].to(device)
    cams = sample.context_cameras.to(device=device, dtype=torch.float32)
    _sync(device)
    start = time.perf_counter()
    with torch.inference_mode(), autocast(precision, device) as ran:
        prediction = model(images, cams, sample.near, sample.far)
    _sync(device)
    forward = time.perf_counter() - start
    # copied out of inference mode: the compaction's refit differentiates them
    gaussians = prediction.gaussians.select(0).to(torch.float32).clone()
    multipliers = prediction.adapter_output.scales_mul[0].float().clone()
    rmode = decoder_mode(model.cfg.adapter, mode)
    tau = prediction.alpha_threshold if alpha_threshold == "model" else alpha_threshold
    if compact is not None:
        from ..compaction import compact as compact_gaussians

        ch, cw = sample.context_images.shape[-2:]
        gaussians = compact_gaussians(gaussians, cams, ch, cw, compact, mode=rmode, alpha_threshold=tau)
        multipliers = None  # compacted surfels no longer stand one per pixel
    targets = sample.target_cameras.to(device=device, dtype=torch.float32)
    renders, seconds = {}, {}
    for s in factors:
        start = time.perf_counter()
        renders[s] = render(gaussians, targets.scaled(float(s)), w * s, h * s, mode=rmode, alpha_threshold=tau)
        _sync(device)
        seconds[s] = time.perf_counter() - start
    fixed = model.cfg.adapter.prior != "surface"  # regressed scales have no multiplier
    return ScenePrediction(
        sample,
        gaussians,
        prediction.depths[0].clone(),
        renders,
        forward,
        seconds,
        tau,
        rmode,
        len(gaussians),
        scale_multipliers=None if fixed else multipliers,
        multiplier_range=None if fixed or multipliers is None else model.cfg.adapter.scale_multiplier_range,
        precision=ran,
    )


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


# ----------------------------------------------------------------------------------------- evaluation
@dataclass(frozen=True)
class EvalConfig:
    """How an evaluation runs."""

    factors: tuple[int, ...] = (1, 2, 4)  # 1 = standard metrics, 2 and 4 = HRRC
    upsample: Literal["bicubic", "bilinear"] = "bicubic"  # HRRC ground truth: the paper; bilinear = the release's code
    mode: Literal["auto", "surfel", "ewa"] = "auto"  # rasterization; auto follows the adapter
    max_entries: int | None = None  # stop after this many index entries (smoke runs)
    progress: bool = True  # progress over the entries (a bar on a terminal, log lines elsewhere)
    geometry: GeometryConfig | None = None  # also score geometry against exact truth (procedural scenes)
    compact: int | None = None  # score the reconstruction compacted at this level (surfsplat.compact)
    precision: Precision = "fp32"  # forward pass: auto, fp32 or bf16 (surfsplat.utils.precision)

    def __post_init__(self) -> None:
        parse_precision(self.precision, "precision")
        if self.upsample not in UPSAMPLE_MODES:
            raise SurfSplatInputError(f"upsample: expected one of {UPSAMPLE_MODES}, got {self.upsample!r}")
        if not self.factors or any(not isinstance(s, int) or s < 1 for s in self.factors):
            raise SurfSplatInputError(f"factors: expected positive integers, got {self.factors!r}")


@dataclass
class EvaluationResult:
    """One model's evaluation: the HRRC report, depth errors, timing and memory."""

    name: str
    report: HrrcReport
    depth: dict[str, float] | None  # mean context-depth errors where true depth exists
    seconds_forward: float  # mean wall time of one forward pass (context views -> surfels)
    seconds_render: dict[int, float]  # mean wall time to render one entry's targets at each factor
    seconds_total: float
    peak_memory_bytes: int
    peak_memory_kind: str  # what the peak counts: CUDA allocations of the run, or the process's peak RSS
    num_entries: int
    per_scene_depth: dict[str, dict[str, float]] = field(default_factory=dict)
    geometry: GeometryReport | None = None  # with EvalConfig.geometry: geometry against exact truth
    surfels_mean: float = 0.0  # surfels rendered per entry (after compaction when asked for)
    compact: int | None = None  # the compaction level, None: as predicted
    closure: ClosureMetrics | None = None  # does the surface stay closed at every factor (target views)
    precision: Resolved = "fp32"  # what the forward passes ran in

    def to_json(self) -> dict:
        return {
            "name": self.name,
            **self.report.to_json(),
            "depth": self.depth,
            "per_scene_depth": self.per_scene_depth,
            **({"geometry": self.geometry.to_json()} if self.geometry is not None else {}),
            "timing": {
                "seconds_forward_mean": self.seconds_forward,
                "seconds_render_mean": {f"x{s}": v for s, v in self.seconds_render.items()},
                "seconds_total": self.seconds_total,
            },
            "peak_memory": {"bytes": self.peak_memory_bytes, "kind": self.peak_memory_kind},
            "num_entries": self.num_entries,
            "surfels_mean": self.surfels_mean,
            "compact_level": self.compact,
            **({"closure": self.closure.to_json()} if self.closure is not None else {}),
            "precision": self.precision,
        }


def evaluate(
    model: SurfSplat,
    samples: Iterable[EvalSample],
    config: EvalConfig = EvalConfig(),
    *,
    lpips: Lpips | LpipsUnavailable,
    name: str = "model",
    total: int | None = None,
) -> EvaluationResult:
    """Standard and HRRC metrics (plus context depth errors where true depth exists) over samples."""
    device = next(model.parameters()).device
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    model.eval()
    warned = False  # about a resolution other than the weights were trained at, once
    evaluator = HrrcEvaluator(lpips, HrrcConfig(factors=config.factors, upsample=config.upsample))
    forward, surfels, renders = [], [], {s: [] for s in config.factors}
    depth_rows: dict[str, dict[str, float]] = {}
    geometry = GeometryEvaluator(config.geometry) if config.geometry is not None else None
    closure = ClosureAccumulator()
    started = time.perf_counter()
    bar = progress(samples, total=total, enabled=config.progress, desc=f"eval {name}", unit="scene")
    for sample in bar:
        if not warned:
            warned = check_resolution(model, *sample.context_images.shape[-2:]) is not None
        pred = predict_sample(
            model, sample, config.factors, config.mode, compact=config.compact, precision=config.precision
        )
        surfels.append(pred.surfels)
        closure.add_alpha({s: r.alpha for s, r in pred.renders.items()})
        closure.add_surfels(pred.gaussians, *pred.closure_surfels())
        evaluator.add_scene(sample.key, sample.target_images.to(device), {s: r.color for s, r in pred.renders.items()})
        forward.append(pred.seconds_forward)
        for s, t in pred.seconds_render.items():
            renders[s].append(t)
        if geometry is not None:
            geometry.add(sample, pred)
        if sample.context_depths is not None:
            errors = depth_metrics(pred.depths.float().cpu(), sample.context_depths[:, 0].float())
            keep = errors.num_valid > 0
            if bool(keep.any()):
                depth_rows[sample.key] = {m: float(getattr(errors, m)[keep].double().mean()) for m in DEPTH_METRICS}
    if not forward:
        raise SurfSplatInputError("evaluation: no index entry had its scene in the data (check --data and --index)")
    report = evaluator.report()
    n = len(forward)
    if device.type == "cuda":
        peak, kind = int(torch.cuda.max_memory_allocated(device)), "CUDA memory allocated (peak of this evaluation)"
    else:
        peak, kind = peak_rss_bytes(), "process peak resident memory (RSS, since start)"
    depth = {m: sum(r[m] for r in depth_rows.values()) / len(depth_rows) for m in DEPTH_METRICS} if depth_rows else None
    return EvaluationResult(
        name=name,
        report=report,
        depth=depth,
        seconds_forward=sum(forward) / n,
        seconds_render={s: sum(v) / n for s, v in renders.items()},
        seconds_total=time.perf_counter() - started,
        peak_memory_bytes=peak,
        peak_memory_kind=kind,
        num_entries=n,
        per_scene_depth=depth_rows,
        geometry=geometry.report() if geometry is not None else None,
        surfels_mean=sum(surfels) / n,
        compact=config.compact,
        closure=closure.report(),
        precision=resolve_precision(config.precision, device),
    )


def peak_memory(device: torch.device) -> tuple[int, str]:
    """This process's peak memory on `device` in bytes and what it counts: CUDA's peak allocation
    (since the last torch.cuda.reset_peak_memory_stats) or the peak resident set (`peak_rss_bytes`)."""
    if device.type == "cuda":
        return int(torch.cuda.max_memory_allocated(device)), "cuda_max_allocated"
    return peak_rss_bytes(), "process_peak_rss"


def peak_rss_bytes() -> int:
    """This process's peak resident set size.

    On Linux the high-water mark of /proc/self/status (VmHWM): getrusage's ru_maxrss survives
    fork + exec, so a fresh child started by a large parent would report the parent's peak.
    Elsewhere ru_maxrss (kilobytes on Linux, bytes on macOS).
    """
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)


# ----------------------------------------------------------------------------------------- reporting
def format_results(results: dict[str, EvaluationResult]) -> str:
    """The paper's table (standard / x2 / x4 / average) for every model, then timing and memory."""
    lines = [format_hrrc_table({name: r.report for name, r in results.items()}), ""]
    name_w = max(len("Method"), *(len(n) for n in results))
    factors = next(iter(results.values())).report.factors
    head = "Method".ljust(name_w) + " | forward s | " + " | ".join(f"render x{s} s" for s in factors) + " | peak memory"
    lines += [head, "-" * len(head)]
    for name, r in results.items():
        cells = " | ".join(f"{r.seconds_render[s]:>11.3f}" for s in factors)
        lines.append(
            f"{name.ljust(name_w)} | {r.seconds_forward:>9.3f} | {cells} | {r.peak_memory_bytes / 2**20:,.0f} MiB"
        )
    for name, r in results.items():
        if r.compact is not None:
            lines.append(f"{name}: compacted at level {r.compact}, {r.surfels_mean:,.0f} surfels per entry on average")
    kinds = sorted({r.peak_memory_kind for r in results.values()})
    lines.append("peak memory: " + "; ".join(kinds))
    depth = {n: r.depth for n, r in results.items() if r.depth is not None}
    if depth:
        lines.append("")
        lines.append("Context depth (true depth in the chunks): " + ", ".join(DEPTH_METRICS))
        for name, d in depth.items():
            lines.append(f"{name.ljust(name_w)} | " + " | ".join(f"{d[m]:.4f}" for m in DEPTH_METRICS))
    geometry = {n: r.geometry for n, r in results.items() if r.geometry is not None}
    if geometry:
        lines += ["", format_geometry_table(geometry)]
    closure = {n: r.closure for n, r in results.items() if r.closure is not None}
    if closure:
        lines += ["", "Closure (target views; a closed surface keeps its alpha at every factor):"]
        lines += [format_closure_table(closure)]
    return "\n".join(lines)


def per_scene_csv(results: dict[str, EvaluationResult]) -> str:
    """One row per (model, entry, factor): PSNR, SSIM, LPIPS (empty where unavailable)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["model", "entry", "factor", *METRICS, *DEPTH_METRICS])
    for name, r in results.items():
        for entry, per_factor in r.report.per_scene.items():
            depth = r.per_scene_depth.get(entry, {})
            for s, metrics in per_factor.items():
                values = ["" if metrics[m] is None else f"{metrics[m]:.6f}" for m in METRICS]
                writer.writerow(
                    [name, entry, s, *values, *(f"{depth[m]:.6f}" if m in depth else "" for m in DEPTH_METRICS)]
                )
    return buffer.getvalue()


def geometry_csv(results: dict[str, EvaluationResult]) -> str:
    """One row per (model, entry) with every geometry column (empty where undefined)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["model", "entry", *GEOMETRY_COLUMNS])
    for name, r in results.items():
        for entry, row in (r.geometry.per_scene if r.geometry is not None else {}).items():
            writer.writerow(
                [name, entry, *("" if not math.isfinite(row[c]) else f"{row[c]:.6f}" for c in GEOMETRY_COLUMNS)]
            )
    return buffer.getvalue()


RESULT_FILES = ("per_scene.csv", "table.txt", "geometry_per_scene.csv", "metrics.json")  # what write_results writes


def write_results(
    results: dict[str, EvaluationResult], out_dir: str | Path, counts: SampleCounts | None = None
) -> dict[str, Path]:
    """metrics.json (every number), per_scene.csv and table.txt in out_dir; each written atomically.
    `counts`: what happened to the index entries for one model (every model sees the same entries)."""
    from ..export.figures import write_text

    out = Path(out_dir)
    document = {"models": {n: r.to_json() for n, r in results.items()}}
    if counts is not None:
        document["entries"] = {
            "evaluated_per_model": counts.evaluated,
            "excluded_null": counts.excluded,
            "scenes_not_in_index": counts.not_in_index,
            "missing_from_data": len(counts.missing),
        }
    # Every text first, then the files: an error (e.g. reports of different factors) writes nothing.
    texts = {
        "per_scene": ("per_scene.csv", per_scene_csv(results)),
        "table": ("table.txt", format_results(results) + "\n"),
    }
    if any(r.geometry is not None and r.geometry.per_scene for r in results.values()):
        texts["geometry"] = ("geometry_per_scene.csv", geometry_csv(results))
    # metrics.json last: a folder holding it is a finished evaluation, one without it was interrupted.
    texts["metrics"] = ("metrics.json", json.dumps(_finite(document), indent=2))
    return {key: write_text(out / name, text) for key, (name, text) in texts.items()}


def _finite(value: object) -> object:
    """JSON cannot hold inf/NaN: such values become strings ("inf"), visibly not numbers."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value
