"""The demo's phases: data, training under a deadline, evaluation (HRRC, native truth, geometry),
export of one scene and its pictures; `run_demo` runs them in order and writes the report."""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..utils import log
from ..utils.checks import SurfSplatInputError
from ..utils.log import progress
from ..utils.precision import Precision, parse_precision

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
    precision: Precision = (
        "fp32"  # training and evaluation forward passes: auto, fp32, bf16 (surfsplat.utils.precision)
    )

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
    from .report import write_demo_report

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
    from ..evaluation import iter_index_samples, predict_sample
    from ..evaluation.geometry import GeometryConfig, GeometryEvaluator, format_geometry_table
    from ..metrics.closure import ClosureAccumulator
    from ..metrics.hrrc import HrrcConfig, HrrcEvaluator, format_hrrc_table
    from ..metrics.lpips import try_load_lpips
    from ..model.loading import ModelSpec, load_model
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
    from ..export.flow import ExportOptions, export_reconstruction

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
    from ..geometry.cameras import look_at

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
