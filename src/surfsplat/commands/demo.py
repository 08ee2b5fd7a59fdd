"""`surfsplat demo [--out DIR]`: the whole product on a fresh machine, nothing downloaded.

    surfsplat demo --out outputs/demo            # about 5-9 minutes on a shared 2-core CPU
    surfsplat demo --out outputs/quick --quick   # a reduced budget (tests, smoke runs)

1. data:     procedural synthetic rooms (exact images and depth at any resolution); held-out
             evaluation scenes are written as chunks with an evaluation index, the same files
             `surfsplat eval` reads;
2. train:    the `tiny` preset (MSE only: lambda_lpips = 0, no VGG files needed) for 150 steps
             (--steps), stopped at a hard time limit on a slow or busy machine (--train-minutes);
3. evaluate: the shipped model (`tiny-synthetic`, trained on procedural rooms: its metadata says how), the
             model just trained and the untrained network: renders at x1, x2, x4 (K scaled) scored
             against the ground truth upsampled bicubically (the paper's HRRC) and against native
             high-resolution truth, which the synthetic scenes provide exactly; geometry (depth and
             normals at the target views, surfels and TSDF mesh against the true surfaces);
4. export:   surfels (PLY), a turntable and a camera-path MP4, a TSDF mesh of one scene (shipped
             model), pictured from a viewpoint no input saw;
5. report:   report.html (tables, image and error-map grids at the three resolutions, the mesh,
             a paragraph reading the numbers, training curve) and metrics.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch
from torch import Tensor

from .. import log
from ..checks import SurfSplatInputError, check_output_dir
from ..geometry.cameras import Cameras
from ..log import progress
from ..precision import PRECISIONS, Precision, parse_precision

logger = logging.getLogger(__name__)

SHIPPED_MODEL = "tiny-synthetic"  # surfsplat.model.registry: the model trained on procedural rooms, in the package
SHIPPED_LABEL = "tiny-synthetic (shipped)"
DEPTH_ERROR_MAX = 0.25  # relative depth error shown as full yellow in the error maps
NORMAL_ERROR_MAX = 45.0  # degrees of normal error shown as full yellow
EVAL_SEED = 90210  # held-out evaluation rooms (training rooms are drawn from the preset's seed)
CHECKPOINT_EVERY = 10  # training steps between checkpoints (what a deadline stop can lose)
START_SECONDS = 30.0  # allowance for starting the training process (imports) before its time limit counts
# Rays per pixel per axis of the native high-resolution truth: at x4 one ray per pixel already samples
# the scene 4x finer per axis than the x1 images, and ray casting is the evaluation's main cost.
NATIVE_SUPERSAMPLE = 1


@dataclass(frozen=True)
class DemoConfig:
    """The demo's budget; `quick()` is the reduced one."""

    image_size: int = 64  # square training and evaluation images (a multiple of 16)
    train_scenes: int = 24  # distinct procedural training rooms (each ray-cast once, then cached)
    steps: int = 150  # optimizer steps (the learning-rate schedule's length)
    train_seconds: float = 240.0  # hard time limit of training: stopped there, with the newest checkpoint
    eval_scenes: int = 3  # held-out rooms
    eval_frames: int = 6  # frames per held-out room (context: first and last; targets: between them)
    eval_targets: int = 3  # target views scored per room
    factors: tuple[int, ...] = (1, 2, 4)  # render scales; 1 = standard, 2 and 4 = HRRC
    figure_scenes: int = 2  # rooms shown in the image grids
    video_frames: int = 36  # frames of each video
    mesh_resolution: int = 96  # TSDF voxels along the longest side
    seed: int = 111123  # training seed (the preset's)
    precision: Precision = "fp32"  # training and evaluation forward passes: auto, fp32, bf16 (surfsplat.precision)

    @staticmethod
    def quick() -> DemoConfig:
        return DemoConfig(
            image_size=32,
            train_scenes=4,
            steps=6,
            eval_scenes=1,
            eval_frames=4,
            eval_targets=2,
            figure_scenes=1,
            video_frames=8,
            mesh_resolution=40,
        )

    def __post_init__(self) -> None:
        if self.image_size < 16 or self.image_size % 16:
            raise SurfSplatInputError(f"--image-size: expected a multiple of 16, got {self.image_size}")
        if self.steps < 1:
            raise SurfSplatInputError(f"--steps: expected at least 1, got {self.steps}")
        if self.eval_frames < 3 or not 1 <= self.eval_targets <= self.eval_frames - 2:
            raise SurfSplatInputError("eval_frames >= 3 and 1 <= eval_targets <= eval_frames - 2 expected")
        if self.eval_scenes < 1 or self.train_scenes < 1:
            raise SurfSplatInputError("--eval-scenes and train_scenes: expected at least 1")
        parse_precision(self.precision)
        if self.train_seconds <= 0:
            raise SurfSplatInputError(f"--train-minutes: expected a positive limit, got {self.train_seconds / 60}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("outputs/demo"), help="output folder")
    parser.add_argument("--quick", action="store_true", help="a reduced budget (32 px, a few steps; for tests)")
    parser.add_argument("--steps", type=int, default=None, help="training steps (default 150)")
    parser.add_argument(
        "--train-minutes",
        type=float,
        default=None,
        help="hard limit of training (default 4): stopped there, the newest checkpoint is used",
    )
    parser.add_argument("--image-size", type=int, default=None, help="square image size, a multiple of 16 (default 64)")
    parser.add_argument("--eval-scenes", type=int, default=None, help="held-out rooms (default 3)")
    parser.add_argument(
        "--precision",
        choices=PRECISIONS,
        default="auto",
        help="training and evaluation precision (auto: bf16 where the device has fast bf16, else fp32)",
    )


def run(args: argparse.Namespace) -> int:
    config = DemoConfig.quick() if args.quick else DemoConfig()
    changes = {
        k: v
        for k, v in (("steps", args.steps), ("image_size", args.image_size), ("eval_scenes", args.eval_scenes))
        if v is not None
    }
    changes["precision"] = args.precision
    if args.train_minutes is not None:
        changes["train_seconds"] = args.train_minutes * 60
    config = replace(config, **changes)
    check_output_dir(args.out, "--out")
    for stale in ("train", "data"):
        if (args.out / stale).exists() and any((args.out / stale).iterdir()):
            raise SurfSplatInputError(
                f"--out {args.out}: already holds a demo run ({stale}/ is not empty); choose an empty folder"
            )
    run_demo(config, args.out)
    return 0


# ----------------------------------------------------------------------------------------------- phases
@dataclass
class Phase:
    name: str
    seconds: float


@dataclass
class DemoResult:
    out: Path
    files: dict[str, Path] = field(default_factory=dict)
    phases: list[Phase] = field(default_factory=list)
    metrics: dict = field(default_factory=dict)


def _say(text: str) -> None:
    logger.info(text)


def run_demo(config: DemoConfig, out: Path) -> DemoResult:
    """Every phase of the demo; returns what it wrote and measured."""
    from ..export.video import video_unavailable

    reason = video_unavailable()
    if reason is not None:
        raise SurfSplatInputError(f"demo: cannot write the videos: {reason}")
    out.mkdir(parents=True, exist_ok=True)
    result = DemoResult(out=out)
    started = time.perf_counter()

    def phase(name: str, t0: float) -> None:
        result.phases.append(Phase(name, time.perf_counter() - t0))

    t0 = time.perf_counter()
    index_path, data_dir = write_eval_data(config, out / "data")
    phase("data", t0)
    _say(f"wrote {config.eval_scenes} held-out rooms as chunks in {data_dir} with evaluation index {index_path}")

    t0 = time.perf_counter()
    train = train_tiny(config, out / "train")
    phase("train", t0)

    t0 = time.perf_counter()
    evaluation = evaluate_demo(config, train["checkpoint"], data_dir, index_path, out)
    phase("evaluate", t0)

    t0 = time.perf_counter()
    scene0 = evaluation.pop("scene0")
    exports = export_demo_scene(config, scene0, out / "scene")
    novel = picture_mesh(config, scene0, exports["mesh (TSDF fusion)"], out / "figures")
    novel["viewer"] = picture_viewer_export(config, scene0, exports, out / "figures")
    phase("export", t0)

    t0 = time.perf_counter()
    result.metrics = {
        "config": asdict(config),
        "train": {k: v for k, v in train.items() if k != "losses"} | {"checkpoint": str(train["checkpoint"])},
        "evaluation": evaluation["metrics"],
        "lpips": evaluation["lpips"],
        "files": {k: str(v) for k, v in exports.items()},
    }
    curve = write_training_curve(train["losses"], out / "figures" / "training_curve.svg")
    result.files.update(exports)
    result.files["training curve"] = curve
    report = write_demo_report(config, out, train, evaluation, exports, novel, curve, result.phases)
    phase("report", t0)
    total = time.perf_counter() - started
    result.metrics["wall_seconds"] = {p.name: round(p.seconds, 2) for p in result.phases} | {"total": round(total, 2)}
    from ..export.figures import write_text

    metrics_path = write_text(out / "metrics.json", json.dumps(result.metrics, indent=1) + "\n")
    result.files["report"] = report
    result.files["metrics"] = metrics_path

    print()
    print(evaluation["table"])
    print()
    print(evaluation["geometry_table"])
    print()
    _say(f"finished in {total / 60:.1f} min (" + ", ".join(f"{p.name} {p.seconds:.0f} s" for p in result.phases) + ")")
    print("outputs:")
    for key, path in [
        ("report", report),
        ("metrics", metrics_path),
        ("checkpoint", train["checkpoint"]),
        ("evaluation data", data_dir),
        ("evaluation index", index_path),
        *exports.items(),
    ]:
        print(f"  {key:22s} {path}")
    print(f"  next: surfsplat eval --checkpoint {SHIPPED_MODEL} --data {data_dir} --index {index_path} --geometry")
    print(f"        surfsplat view {exports['surfels (2DGS PLY)']}")
    return result


# ----------------------------------------------------------------------------------------------- data
def write_eval_data(config: DemoConfig, folder: Path) -> tuple[Path, Path]:
    """Held-out rooms as chunks (F frames along each camera path) plus an evaluation index whose
    context views are the path's ends and whose targets are evenly spaced frames between them."""
    from ..data.synthetic import write_synthetic_chunks
    from ..export.figures import write_text

    chunks = folder / "eval"
    keys = write_synthetic_chunks(
        chunks,
        config.eval_scenes,
        seed=EVAL_SEED,
        image_shape=(config.image_size,) * 2,
        num_frames=config.eval_frames,
        supersample=2,
    )
    index = {key: {"context": [0, config.eval_frames - 1], "target": eval_targets(config)} for key in sorted(keys)}
    path = write_text(folder / "evaluation_index.json", json.dumps(index, indent=1) + "\n")
    return path, chunks


def eval_targets(config: DemoConfig) -> list[int]:
    inner = torch.linspace(1, config.eval_frames - 2, config.eval_targets).round().long().unique()
    return inner.tolist()


# ----------------------------------------------------------------------------------------------- training
def train_tiny(config: DemoConfig, folder: Path) -> dict:
    """fit() on the tiny preset for config.steps, in a child process with a hard time limit.

    A shared machine can be many times slower than a quiet one, and the demo promises minutes, so
    the training process is stopped at config.train_seconds (plus its start-up allowance) when it
    has not finished. Training checkpoints are published atomically every few steps, so the newest
    one is then a complete model; the demo goes on with it and says at which step it stopped (the
    learning-rate schedule was then not finished).
    """
    from ..train import latest_checkpoint, override, train_preset

    size = config.image_size
    base = train_preset(
        "tiny",
        out_dir=str(folder),
        seed=config.seed,
        val_every=0,
        image_every=0,
        steps=config.steps,
        precision=config.precision,
        log_every=1,
        keep_checkpoints=2,
        checkpoint_every=max(1, min(CHECKPOINT_EVERY, config.steps)),
    )
    train_config = override(
        base, {"data.image_shape": [size, size], "data.synthetic_length": config.train_scenes, "loss.lpips_weight": 0.0}
    )
    limit = config.train_seconds + START_SECONDS
    _say(
        f"training the tiny preset for {config.steps} steps on {config.train_scenes} synthetic rooms at {size}x{size} "
        f"(MSE loss; lambda_lpips = 0, LPIPS weights are not needed; stopped after {limit / 60:.1f} min at the latest) -> {folder}"
    )
    t0 = time.perf_counter()
    stopped_early = _fit_with_deadline(train_config, limit)
    seconds = time.perf_counter() - t0
    checkpoint = latest_checkpoint(folder)
    if checkpoint is None:
        raise SurfSplatInputError(
            f"{folder}: training wrote no checkpoint within {limit:.0f} s; give a larger --train-minutes"
        )
    done = int(checkpoint.name.split("-")[1])
    losses = read_losses(folder / "metrics.jsonl", done)
    if stopped_early:
        _say(
            f"the time limit stopped training after {seconds:.0f} s; continuing with the checkpoint of step {done} of {config.steps}"
        )
    return {
        "steps": done,
        "planned_steps": config.steps,
        "stopped_by_deadline": stopped_early,
        "seconds": seconds,
        "first_loss": losses[0][1] if losses else None,
        "final_loss": losses[-1][1] if losses else None,
        "losses": losses,
        "checkpoint": checkpoint,
        "image_size": size,
        "scenes": config.train_scenes,
    }


def _fit_with_deadline(train_config, deadline: float) -> bool:
    """Run fit(train_config) in a spawned process; True when the deadline stopped it."""
    import multiprocessing

    process = multiprocessing.get_context("spawn").Process(
        target=_fit_child, args=(train_config, log.configured_level()), daemon=True
    )
    process.start()
    try:
        process.join(timeout=deadline)
        stopped = process.is_alive()
        if stopped:
            process.terminate()
            process.join()
    finally:
        if process.is_alive():  # interrupted while waiting: take the child down too
            process.terminate()
            process.join()
    if not stopped and process.exitcode != 0:
        raise SurfSplatInputError(f"training failed (exit code {process.exitcode}); its error is printed above")
    return stopped


def _fit_child(train_config, log_level: int) -> None:
    from ..train import fit

    if log_level:  # a spawned process starts without the parent's logging setup
        log.configure(log_level)
    fit(train_config)


def read_losses(path: Path, last_step: int) -> list[tuple[int, float]]:
    """(step index, loss) of every logged step up to the checkpoint's step, from metrics.jsonl."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the training run wrote no metrics")
    losses = []
    lines = path.read_text().splitlines()
    for k, line in enumerate(lines):
        try:
            record = json.loads(line)
        except ValueError:
            if k == len(lines) - 1:
                break  # a run stopped at its deadline may have been writing its last line
            raise SurfSplatInputError(f"{path}: line {k + 1} is not JSON") from None
        if "loss/total" in record and record["step"] <= last_step:
            losses.append((record["step"] - 1, float(record["loss/total"])))
    return losses


def write_training_curve(losses: list[tuple[int, float]], path: Path) -> Path:
    from ..export.figures import line_chart, smooth, write_text

    points = [(s + 1, v) for s, v in losses]
    window = max(1, len(points) // 20)
    svg = line_chart(
        {"loss (MSE)": points, f"moving average ({window} steps)": smooth(points, window)},
        title="Training loss",
        y_label="loss",
        log_y=True,
    )
    return write_text(path, svg)


# ----------------------------------------------------------------------------------------------- evaluation
def evaluate_demo(config: DemoConfig, checkpoint: Path, data_dir: Path, index_path: Path, out: Path) -> dict:
    """Score the shipped, the just-trained and the untrained network: HRRC against bicubic-upsampled
    and against native high-resolution truth, coverage at each scale, geometry against the exact
    truth; write figures (with error maps) of the shipped model on the first rooms."""
    from ..data.eval_index import EvaluationIndex
    from ..evaluation import ModelSpec, iter_index_samples, load_model, predict_sample
    from ..evaluation.geometry import GeometryConfig, GeometryEvaluator, format_geometry_table
    from ..metrics.closure import ClosureAccumulator
    from ..metrics.hrrc import HrrcConfig, HrrcEvaluator, format_hrrc_table
    from ..metrics.lpips import try_load_lpips
    from ..train import build_model, train_preset

    lpips = try_load_lpips()
    trained, _ = load_model(ModelSpec(str(checkpoint)))
    torch.manual_seed(config.seed)
    untrained = build_model(train_preset("tiny", seed=config.seed)).eval()  # the weights training started from
    shipped, _ = load_model(ModelSpec(SHIPPED_MODEL))
    models = {
        SHIPPED_LABEL: shipped,
        f"tiny, {config.steps} steps here": trained,
        "tiny, untrained": untrained,
    }
    index = EvaluationIndex.load(index_path)
    factors = config.factors
    samples = list(iter_index_samples([data_dir], index, near=0.5, far=15.0))
    if not samples:
        raise SurfSplatInputError(f"{index_path}: no evaluation entry found in {data_dir}")
    native = native_truth(config, samples, factors)

    _say(
        f"evaluating {len(samples)} rooms x {len(samples[0].target_views)} target views at x{', x'.join(map(str, factors))}"
    )
    metrics, tables, geometry, keep = {}, {}, {}, {}
    geometry_config = GeometryConfig(mesh_resolution=config.mesh_resolution)
    for name, model in models.items():
        shapes = GeometryEvaluator(geometry_config)
        upsampled = HrrcEvaluator(lpips, HrrcConfig(factors=factors, upsample="bicubic"))
        natives = {s: HrrcEvaluator(lpips, HrrcConfig(factors=(1,))) for s in factors}
        coverage = {s: [] for s in factors}
        closure = ClosureAccumulator()
        for k, sample in enumerate(progress(samples, desc=f"score {name}", unit="room", leave=False)):
            pred = predict_sample(model, sample, factors, precision=config.precision)
            closure.add_alpha({s: r.alpha for s, r in pred.renders.items()})
            closure.add_surfels(pred.gaussians, *pred.closure_surfels())
            shapes.add(sample, pred)
            upsampled.add_scene(sample.key, sample.target_images, {s: r.color for s, r in pred.renders.items()})
            for s in factors:
                natives[s].add_scene(sample.key, native[k][s]["image"], {1: pred.renders[s].color})
                coverage[s].append(float((pred.renders[s].alpha > 0.5).float().mean()))
            if name == SHIPPED_LABEL and k < config.figure_scenes:
                keep[k] = pred
        report = upsampled.report()
        tables[name] = report
        geometry[name] = shapes.report()
        metrics[name] = {
            "geometry": geometry[name].to_json(),
            "vs_bicubic_upsampled_truth": report.to_json(),
            "vs_native_truth": {f"x{s}": natives[s].report().mean[1] for s in factors},
            "coverage": {f"x{s}": sum(v) / len(v) for s, v in coverage.items()},
            "closure": closure.report().to_json(),
            "precision": pred.precision,
        }
    figures = write_figures(config, samples, keep, native, out / "figures")
    table = format_hrrc_table(tables)
    return {
        "metrics": metrics,
        "table": table,
        "geometry_table": format_geometry_table(geometry),
        "figures": figures,
        "samples": samples,
        "lpips": None if not isinstance(lpips, Exception) else str(lpips),
        "scene0": (keep[0], shipped),
    }


def native_truth(config: DemoConfig, samples, factors) -> list[dict[int, dict[str, Tensor]]]:
    """Ray-cast images, depth and normals of every sample's target views at s times the
    resolution (K scaled by s): exact high-resolution truth, not an upsampling (pixel-centre rays)."""
    from ..data.synthetic import SyntheticDataset, SyntheticDatasetConfig, render_synthetic

    size = config.image_size
    dataset = SyntheticDataset(
        SyntheticDatasetConfig(length=config.eval_scenes, seed=EVAL_SEED, image_shape=(size, size))
    )
    positions = torch.linspace(0, 1, config.eval_frames, dtype=torch.float64)
    out = []
    for sample in progress(samples, desc="ray-cast native truth", unit="room", leave=False):
        i = int(sample.scene.rsplit("-", 1)[1])
        scene = dataset.scene(i)
        cams = dataset.trajectory(i, scene).cameras(positions[list(sample.target_views)], size, size)
        truth = {}
        for s in factors:
            r = render_synthetic(scene, cams.scaled(float(s)), size * s, size * s, supersample=NATIVE_SUPERSAMPLE)
            truth[s] = {"image": r.image, "depth": r.depth, "normal": r.normal}
        out.append(truth)
    return out


def write_figures(config: DemoConfig, samples, predictions: dict, native, folder: Path) -> list[dict]:
    """Per shown room: PNGs of truth, renders, depth and normal maps at every scale, plus a grid."""
    from ..export.figures import image_grid
    from ..export.images import colorize_depth, colorize_error, normal_to_rgb, write_png
    from ..metrics.geometry import angular_error_deg

    figures = []
    for k, pred in predictions.items():
        sample = samples[k]
        tag = f"room{k}"
        entry: dict = {"key": sample.key, "context": [], "rows": []}
        for c in range(sample.context_images.shape[0]):
            entry["context"].append(
                str(write_png(folder / f"{tag}_context{c}.png", sample.context_images[c]).relative_to(folder.parent))
            )
        # One depth colour scale for every resolution: the true depth range of the x1 view.
        true_depth = native[k][1]["depth"][0]
        d_lo, d_hi = float(true_depth[true_depth > 0].min()), float(true_depth.max())
        grid_rows = []
        v = 0  # first target view
        # Depth is shown wherever forced alpha blending normalised it (alpha >= tau), not only where
        # alpha > 0.5: the coverage column of the table reports the gaps separately.
        tau = pred.alpha_threshold if pred.alpha_threshold is not None else 0.5
        shown = {s: (pred.renders[s].alpha >= tau)[v].float() for s in config.factors}
        for s in config.factors:
            r = pred.renders[s]
            truth_depth, truth_normal = native[k][s]["depth"][v], native[k][s]["normal"][v]
            scored = shown[s].bool() & (truth_depth > 0)
            depth_error = colorize_error(
                (r.depth[v] - truth_depth).abs() / truth_depth.clamp_min(1e-6), scored, vmax=DEPTH_ERROR_MAX
            )
            normal_error = colorize_error(
                angular_error_deg(r.normal[v].movedim(0, -1), truth_normal.movedim(0, -1))[None],
                scored,
                vmax=NORMAL_ERROR_MAX,
            )
            files = {
                "truth": write_png(folder / f"{tag}_x{s}_truth.png", native[k][s]["image"][v]),
                "render": write_png(folder / f"{tag}_x{s}_render.png", r.color[v]),
                "depth": write_png(
                    folder / f"{tag}_x{s}_depth.png", colorize_depth(r.depth[v], shown[s], near=d_lo, far=d_hi)
                ),
                "normal": write_png(folder / f"{tag}_x{s}_normal.png", normal_to_rgb(r.normal[v])),
                "truth depth": write_png(
                    folder / f"{tag}_x{s}_truth_depth.png",
                    colorize_depth(native[k][s]["depth"][v], None, near=d_lo, far=d_hi),
                ),
                "truth normal": write_png(
                    folder / f"{tag}_x{s}_truth_normal.png", normal_to_rgb(native[k][s]["normal"][v])
                ),
                "depth error": write_png(folder / f"{tag}_x{s}_depth_error.png", depth_error),
                "normal error": write_png(folder / f"{tag}_x{s}_normal_error.png", normal_error),
            }
            entry["rows"].append(
                {
                    "factor": s,
                    "size": r.color.shape[-1],
                    **{key: str(p.relative_to(folder.parent)) for key, p in files.items()},
                }
            )
            grid_rows.append(
                [
                    native[k][s]["image"][v],
                    r.color[v],
                    colorize_depth(r.depth[v], shown[s], near=d_lo, far=d_hi),
                    normal_to_rgb(r.normal[v]),
                    depth_error,
                    normal_error,
                ]
            )
        top = config.image_size * max(config.factors)
        entry["grid"] = str(
            write_png(folder / f"{tag}_grid.png", image_grid(grid_rows, size=(top, top))).relative_to(folder.parent)
        )
        figures.append(entry)
    return figures


# ----------------------------------------------------------------------------------------------- export
def export_demo_scene(config: DemoConfig, scene, folder: Path) -> dict[str, Path]:
    """PLY, turntable and camera-path videos and a TSDF mesh of the first held-out room."""
    from .export import ExportOptions, export_reconstruction

    pred, model = scene
    sample = pred.sample
    options = ExportOptions(
        scale=2.0,
        path_frames=config.video_frames,
        turntable_frames=config.video_frames,
        turntable_degrees=24.0,
        fps=12.0,
        mesh_resolution=config.mesh_resolution,
        mode="surfel",
        alpha_threshold=model.adapter.alpha_threshold(),
    )
    _say(f"exporting room {sample.scene}: surfels, videos ({config.video_frames} frames), mesh -> {folder}")
    size = config.image_size
    return export_reconstruction(
        pred.gaussians,
        sample.context_cameras,
        size,
        size,
        folder,
        options,
        names=[f"context{i}" for i in range(len(sample.context_cameras))],
        near=0.5,
        far=15.0,
    )


def novel_viewpoint(pred, orbit_degrees: float = 25.0, lift: float = 0.35) -> Cameras:
    """A camera no input saw: the first target camera orbited about the vertical axis (the rooms
    are z-up) through the point it looks at (median rendered depth along its optical axis), raised
    by `lift` metres and aimed back at that point. Same intrinsics and image size as the inputs."""
    from ..scenes import look_at

    r = pred.renders[1]
    c2w = pred.sample.target_cameras.c2w[0].double()
    tau = pred.alpha_threshold if pred.alpha_threshold is not None else 0.5
    depth = r.depth[0, 0][r.alpha[0, 0] >= tau]
    distance = float(depth.median()) if depth.numel() else 2.0
    pivot = c2w[:3, 3] + distance * c2w[:3, 2]
    c, s = math.cos(math.radians(orbit_degrees)), math.sin(math.radians(orbit_degrees))
    rot = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)  # about world z
    eye = pivot + rot @ (c2w[:3, 3] - pivot) + torch.tensor([0.0, 0.0, lift], dtype=torch.float64)
    pose = look_at(eye, pivot, down=(0.0, 0.0, -1.0))
    return Cameras(pose[None].float(), pred.sample.target_cameras.K[:1].clone())


def picture_mesh(config: DemoConfig, scene, mesh_path: Path, folder: Path) -> dict[str, str]:
    """The exported mesh, the surfels and the true room from `novel_viewpoint`, at x4 of the input
    size: truth | surfels (exact 2DGS render) | mesh with its colours | mesh shape (grey)."""
    from ..data.synthetic import render_synthetic
    from ..data.synthetic.truth import scene_from_key
    from ..export.figures import image_grid
    from ..export.images import write_png
    from ..export.mesh import load_mesh
    from ..export.mesh_render import render_mesh
    from ..render import render

    pred, model = scene
    camera = novel_viewpoint(pred)
    s = max(config.factors)
    size = config.image_size * s
    big = camera.scaled(float(s))
    room = scene_from_key(pred.sample.scene)
    truth = render_synthetic(room, big, size, size, supersample=NATIVE_SUPERSAMPLE).image[0]
    surfels = render(
        pred.gaussians, big, size, size, mode="surfel", alpha_threshold=model.adapter.alpha_threshold()
    ).color[0]
    mesh = load_mesh(mesh_path)
    picture = render_mesh(mesh, big, size, size)
    pictures = {"truth": truth, "surfels": surfels, "mesh": picture.shaded, "mesh shape": picture.shape}
    files = {k: write_png(folder / f"novel_{k.replace(' ', '_')}.png", v) for k, v in pictures.items()}
    files["grid"] = write_png(folder / "novel_view_grid.png", image_grid([list(pictures.values())], size=(size, size)))
    return {k: str(p) for k, p in files.items()}


def picture_viewer_export(config: DemoConfig, scene, exports: dict[str, Path], folder: Path) -> dict:
    """The exported surfels_3dgs.ply as a standard 3DGS viewer composites it (EWA, no alpha
    normalisation, on black) beside our render, from the first context view and from
    `novel_viewpoint`, at x4 of the input size; with the bake's figures (surfels_3dgs.json)."""
    from ..export.figures import image_grid
    from ..export.images import write_png
    from ..export.ply import load_ply
    from ..render import render

    pred, model = scene
    s = max(config.factors)
    size = config.image_size * s
    viewer = load_ply(exports["surfels (3DGS PLY, baked for viewers)"])
    tau = model.adapter.alpha_threshold()
    pictures = []
    for camera in (pred.sample.context_cameras[:1], novel_viewpoint(pred)):
        big = camera.scaled(float(s))
        pictures.append(render(pred.gaussians, big, size, size, mode="surfel", alpha_threshold=tau).color[0])
        pictures.append(render(viewer, big, size, size, mode="ewa", alpha_threshold=None).color[0])
    grid = write_png(folder / "viewer_export_grid.png", image_grid([pictures], size=(size, size)))
    figures = json.loads(exports["viewer bake figures"].read_text())
    return {"grid": str(grid), "before": figures["before"], "after": figures["after"], "seconds": figures["seconds"]}


# ----------------------------------------------------------------------------------------------- report
def read_numbers(metrics: dict, train: dict) -> str:
    """A short paragraph that reads the table: geometry of each network, then sharpness at x4."""
    names = list(metrics)

    def geo(name: str) -> dict | None:
        return metrics[name]["geometry"]["mean"]

    def views(name: str) -> str:
        g = geo(name)
        if g is None:
            return "no geometry"
        return (
            f"depth AbsRel {g['abs_rel']:.3f} ({g['delta1']:.0%} of pixels within 1.25x), "
            f"median normal error {g['median_deg']:.1f} deg, surfel Chamfer {g['surfels_chamfer']:.2f} m "
            f"(F-score {g['surfels_fscore']:.2f} at 5 cm)"
        )

    shipped, here, untrained = names[0], names[1], names[2]
    text = [
        f"At the target views the shipped model reaches {views(shipped)}; the model trained here for "
        f"{train['steps']} steps reaches {views(here)}, and the untrained network {views(untrained)}."
    ]
    g_ship, g_here = geo(shipped), geo(here)
    if g_ship and g_here:
        better = g_ship["median_deg"] < g_here["median_deg"] and g_ship["abs_rel"] < g_here["abs_rel"]
        text.append(
            "Long training is what turns the network's depth into a surface: "
            if better
            else "Here the brief run is not behind the shipped model on every geometry column: "
        )
        text[-1] += (
            f"its normals are off by {g_ship['median_deg']:.1f} instead of {g_here['median_deg']:.1f} degrees "
            f"(median) and its depth by {g_ship['abs_rel']:.1%} instead of {g_here['abs_rel']:.1%}."
        )
    native = {n: metrics[n]["vs_native_truth"] for n in names}
    x1, x4 = native[shipped]["x1"]["psnr"], native[shipped]["x4"]["psnr"]
    cover = metrics[shipped]["coverage"]
    closure = metrics[shipped]["closure"]
    holes = not closure["closed"]
    text.append(
        f"Against natively ray-cast truth the shipped model scores {x1:.2f} dB PSNR at x1 and {x4:.2f} dB at x4, "
        f"with {cover['x1']:.0%} of pixels covered by alpha > 0.5 at x1 and {cover['x4']:.0%} at x4; its mean "
        f"alpha at x4 is {closure['closure']:.2f} of that at x1 (closure) and "
        f"{closure['undersized_share']:.0%} of its surfels are under half their pixel footprint: "
        + (
            "at four times the resolution its surfels leave gaps that forced alpha blending fills by "
            "normalising what little alpha remains, which the x4 renders and the novel view show as texture "
            "broken into discs."
            if holes
            else "at four times the resolution its surfels still close into a surface."
        )
        + " A low-resolution input cannot supply the detail the native x4 image holds in any case."
    )
    return " ".join(text)


def shipped_summary() -> str:
    """How the shipped model was trained, as its metadata records it (`scripts/ship_model.py --summary`)."""
    from ..model.pretrained import describe

    return str(describe(SHIPPED_MODEL)["summary"])


def write_demo_report(
    config: DemoConfig,
    out: Path,
    train: dict,
    evaluation: dict,
    exports: dict[str, Path],
    novel: dict[str, str],
    curve: Path,
    phases: list[Phase],
) -> Path:
    from ..export.report import HtmlReport

    rel = lambda p: str(Path(p).resolve().relative_to(out.resolve()))  # noqa: E731 - a one-line path helper
    report = HtmlReport("SurfSplat demo: a learned surface, measured at x1/x2/x4")
    size = config.image_size
    report.paragraph(
        f"Three networks are scored on {config.eval_scenes} held-out procedural rooms at {size}x{size}: "
        f"{SHIPPED_LABEL}, {shipped_summary()}, shipped with the "
        f"package (--checkpoint {SHIPPED_MODEL}); the same preset trained here for {train['steps']} "
        f"steps ({train['seconds']:.0f} s) on {train['scenes']} rooms with the MSE loss, to show training; and the "
        "untrained network. Renders at x2 and x4 use K scaled by the factor (HRRC, paper Sec. 3.6). Two ground "
        "truths: the x1 image upsampled bicubically (the paper's HRRC) and the scene ray-cast natively at the "
        "higher resolution; geometry is scored against the rooms' exact depth, normals and surfaces."
    )
    report.heading("What the numbers say")
    report.paragraph(read_numbers(evaluation["metrics"], train))
    if train["stopped_by_deadline"]:
        report.paragraph(
            f"Training was stopped by its time limit at step {train['steps']} of the {train['planned_steps']} "
            "planned (a slow or busy machine); the learning-rate schedule did not finish.",
            note=True,
        )
    if evaluation["lpips"] is not None:
        report.paragraph(evaluation["lpips"], note=True)
    report.heading("Metrics")
    factors = config.factors
    header = [
        "Model",
        "Resolution",
        "PSNR (bicubic GT)",
        "SSIM (bicubic GT)",
        "LPIPS (bicubic GT)",
        "PSNR (native GT)",
        "SSIM (native GT)",
        "Coverage (alpha > 0.5)",
    ]
    rows = []
    for name, m in evaluation["metrics"].items():
        up = m["vs_bicubic_upsampled_truth"]
        for s in factors:
            label = f"{size * s}x{size * s} (" + ("standard" if s == 1 else f"HRRC x{s}") + ")"
            u, n = up["mean"][f"x{s}"], m["vs_native_truth"][f"x{s}"]
            rows.append([name, label, u["psnr"], u["ssim"], u["lpips"], n["psnr"], n["ssim"], m["coverage"][f"x{s}"]])
        avg = up["average"]
        rows.append([name, "average", avg["psnr"], avg["ssim"], avg["lpips"], None, None, None])
    report.table("Standard and HRRC metrics (means over target views)", header, rows)
    report.paragraph(
        "Coverage is the share of pixels whose accumulated alpha exceeds 0.5. Forced alpha blending "
        "divides colour, depth and normals by alpha wherever alpha >= 0.001 (paper Sec. 3.4), so a "
        "render can look complete while its surfels leave gaps between them at higher resolutions."
    )
    report.paragraph("The same numbers in the paper's table layout:")
    report.preformatted(evaluation["table"])

    report.heading("Closure: does the surface stay closed at x2 and x4?")
    closure_rows = []
    for name, m in evaluation["metrics"].items():
        c = m["closure"]
        q = c["opacity_quantiles"]
        closure_rows.append(
            [name, c["closure"]]
            + [c["mean_alpha"][f"x{s}"] for s in factors]
            + [c["coverage"][f"x{s}"]["alpha>=0.9"] for s in factors]
            + [c["undersized_share"], c["multiplier_at_low"], q["p50"], "yes" if c["closed"] else "no"]
        )
    report.table(
        "Closure of the target views (means over every rendered pixel; surfel shares over every surfel)",
        ["Model", "Closure (alpha x4 / x1)"]
        + [f"Mean alpha x{s}" for s in factors]
        + [f"Coverage alpha >= 0.9, x{s}" for s in factors]
        + ["Surfels under half their footprint", "Scale multipliers at 1/3", "Median opacity", "Closed"],
        closure_rows,
    )
    report.paragraph(
        "A continuous surface keeps its alpha at any resolution: closure is the mean alpha at x4 over the mean "
        "alpha at x1, and counts as closed at 0.9 or more with at most 15% of surfels smaller than half the "
        "surface one pixel spans at their depth (z / f). The screen-space low-pass widens every surfel to about "
        "a pixel at x1, so surfels of a third of a pixel look whole there and part at x4."
    )

    report.heading("Geometry against the exact truth")
    report.paragraph(
        "Target views at x1: rendered depth (AbsRel, RMSE in metres, share within 1.25x) and normals (angular "
        "error) over the pixels whose true surface a context view sees and where alpha >= 0.1. Surfaces: surfel "
        "centres weighted by opacity, and points sampled on the TSDF mesh, against area-uniform samples of the "
        "true surfaces the context views see: accuracy and completeness (mean distances, metres), Chamfer "
        "distance and F-score at 5 cm. Silhouette pixels blend foreground and background depth, so even surfels "
        "placed exactly on the true surfaces score an AbsRel of a few percent here."
    )
    report.preformatted(evaluation["geometry_table"])

    report.heading("Renders at x1, x2, x4")
    report.paragraph(
        "Each row: native ground truth, render, rendered depth, rendered normals; all shown at the "
        "same size, so the x1 row shows its pixels and the x4 row the detail a continuous surface keeps."
    )
    for fig in evaluation["figures"]:
        report.paragraph(f"Held-out room {fig['key']}; context views:")
        report.figure_row([(p, f"context {i}") for i, p in enumerate(fig["context"])], width=160, pixelated=True)
        for row in fig["rows"]:
            s = row["factor"]
            report.figure_row(
                [
                    (row["truth"], f"truth {row['size']} px (x{s})"),
                    (row["render"], f"render x{s}"),
                    (row["depth"], f"depth x{s}"),
                    (row["normal"], f"normal x{s}"),
                    (row["truth depth"], f"true depth x{s}"),
                    (row["truth normal"], f"true normal x{s}"),
                    (row["depth error"], f"depth error x{s} (0-{DEPTH_ERROR_MAX:.0%})"),
                    (row["normal error"], f"normal error x{s} (0-{NORMAL_ERROR_MAX:.0f} deg)"),
                ],
                width=104,
                pixelated=True,
            )
        report.figure(
            fig["grid"],
            "grid: truth | render | depth | normal | depth error | normal error, rows x1, x2, x4 "
            "(error maps: black = exact, yellow = at or above the scale; grey = not scored)",
            width=960,
            pixelated=True,
        )

    report.heading("Training curve")
    report.figure(rel(curve), f"MSE loss per step ({train['steps']} steps)", width=640)

    report.heading("Exports of the first held-out room (shipped model)")
    report.paragraph(
        f"From a viewpoint no input saw (orbited and raised from the first target view), at {size * max(config.factors)} "
        "px: the true room, the shipped model's surfels (exact 2DGS render), the TSDF mesh fused from their depth "
        "with its colours, and the mesh's shape alone."
    )
    report.figure(rel(novel["grid"]), "truth | surfels | mesh | mesh shape", width=960)
    bake = novel["viewer"]
    report.paragraph(
        "The exported surfels_3dgs.ply as standard 3DGS viewers (SuperSplat, gsplat's) composite it: EWA splatting "
        "without forced alpha blending, on black. The export bakes it so that this reproduces our render: "
        + "; ".join(
            f"from the context views at {k.split()[-1]}, mean alpha {bake['before'][k]['alpha']:.2f} -> "
            f"{bake['after'][k]['alpha']:.2f} and colour PSNR {bake['before'][k]['psnr']:.1f} -> "
            f"{bake['after'][k]['psnr']:.1f} dB against our render over the pixels it covers"
            for k in bake["after"]
        )
        + f" (raw thin surfels -> baked; {bake['seconds']:.0f} s)."
    )
    report.figure(
        rel(bake["grid"]),
        "context view: ours | exported PLY in a standard viewer; novel view: ours | exported PLY in a standard viewer",
        width=960,
    )
    videos = [(k, p) for k, p in exports.items() if str(p).endswith(".mp4")]
    for key, path in videos:
        report.video(rel(path), key, width=320)
    report.links("Files:", [(rel(p), k) for k, p in exports.items()])
    report.heading("Time")
    report.table("Wall time per phase", ["Phase", "Seconds"], [[p.name, p.seconds] for p in phases])
    return report.write(out / "report.html")
