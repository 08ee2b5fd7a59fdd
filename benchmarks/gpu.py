"""The GPU path in one run: training on both render backends, the gsplat glue against gsplat's own
rasterizer, a whole reconstruction stage by stage, and training throughput.

    python benchmarks/gpu.py                                   # CUDA; every part, under 8 minutes
    python benchmarks/gpu.py --parts render --device cpu --quick   # the same code on a CPU, small (tests)

Parts (each recorded in the JSON as soon as it ends, with its seconds or the error that stopped it):
- train: `--train-steps` (300) tiny-preset training steps at 128x128, batch 4, from one seed, with the
  torch and the gsplat render backends: the losses every 10 steps, skipped (non-finite) updates,
  seconds a step, and the mean loss of the last 50 steps of each with their ratio.
- render: one forward and backward of the procedural surfel scene (`make_scene`) through
  `render(..., backend="gsplat")`, `backend="torch"` and gsplat's own `rasterization_2dgs` on the same
  surfels and cameras: 393,216 surfels to 7 cameras at 288x400 and 1,048,576 surfels to 8 cameras at
  512x512 (median of `--repeats`), with the ratios to gsplat's.
- reconstruct: `surfsplat reconstruct` of DTU scan 24's views 14, 16, ..., 26 (cameras given, 288x400,
  every default output) and of a 10-second 1080p video, each in a fresh process on DEVICE: wall
  seconds and the stage times of `reconstruction.json`. Needs the sample data (`--data`). With the
  optimizer on by default, the DTU run includes its 3,000 steps.
- optimize: the per-scene optimizer on the card: `surfsplat reconstruct` of LLFF fern (17 context views
  at 368x496, 3 held out), the shipped defaults: held-out PSNR before and after, the optimizer's start,
  steps, surfels and seconds (the CPU figures are benchmarks/optimize.py's fern-cli).
- throughput: bf16 autocast training steps of the small preset (2 context + 4 target views, 256x256
  procedural rooms) at batch 1 and at the paper's batch 16 on one batch made once: median step time,
  samples per second, peak memory (the train part measures the loop's wait for data).

gsplat compiles its CUDA kernels on first use (67-85 s on 16 cores for sm_90 with MAX_JOBS=16
TORCH_CUDA_ARCH_LIST=9.0): the build starts in a background process at once and the parts that do
not need it run first.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

import torch

from common import RESULTS, machine, sample_data

DTU_VIEWS = list(range(14, 27, 2))  # seven neighbouring views of DTU scan 24 (the reconstruction)


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def start_gsplat_build(device: torch.device) -> subprocess.Popen | None:
    """gsplat's JIT build in a background process (its build folder is shared with this process)."""
    if device.type != "cuda":
        return None
    env = {"MAX_JOBS": str(os.cpu_count() or 8), "TORCH_CUDA_ARCH_LIST": _arch(), **os.environ}
    return subprocess.Popen([sys.executable, "-c", "from gsplat.cuda._backend import _C"], env=env)


def _arch() -> str:
    major, minor = torch.cuda.get_device_capability()
    return f"{major}.{minor}"


def wait_for_build(build: subprocess.Popen | None, report: dict) -> None:
    if build is None or "gsplat_build_wait_s" in report:
        return
    start = time.perf_counter()
    code = build.wait()
    report["gsplat_build_wait_s"] = time.perf_counter() - start
    report["gsplat_build_exit_code"] = code


# ----------------------------------------------------------------------------------------- train
def train_run(backend: str, steps: int, size: int, batch: int, device: torch.device, out: Path) -> dict:
    from surfsplat.train import fit, train_preset
    from surfsplat.train.config import override

    workers = min(8, os.cpu_count() or 1) if device.type == "cuda" else 0  # the GPU must not wait for rooms

    config = override(
        train_preset("tiny"),
        {
            "data.image_shape": [size, size],
            "batch_size": batch,
            "steps": steps,
            "val_every": 0,
            "log_every": 10,
            "image_every": 0,
            "checkpoint_every": steps,
            "progress": False,
            "device": device.type,
            "model.render_backend": backend,
            "out_dir": str(out),
            "data.num_workers": workers,
        },
    )
    result = fit(config)
    losses = [loss for _, loss in result.losses]
    last = [loss for step, loss in result.losses if step > steps - 50]
    return {
        "backend": backend,
        "steps": result.step,
        "seconds": result.seconds,
        "seconds_per_step": result.seconds / max(result.step, 1),
        "data_wait_seconds": result.data_seconds,
        "loader_workers": workers,
        "losses": result.losses,
        "all_finite": all(math.isfinite(x) for x in losses) and not result.nonfinite_steps,
        "nonfinite_steps": result.nonfinite_steps,
        "mean_loss_last_50": statistics.fmean(last) if last else None,
        "precision": result.precision,
    }


def train_part(args, device: torch.device, build, report: dict) -> dict:
    runs = {}
    steps, size, batch = (3, 32, 1) if args.quick else (args.train_steps, args.train_size, 4)
    with tempfile.TemporaryDirectory() as tmp:
        runs["torch"] = train_run("torch", steps, size, batch, device, Path(tmp) / "torch")
        wait_for_build(build, report)
        if device.type == "cuda":
            runs["gsplat"] = train_run("gsplat", steps, size, batch, device, Path(tmp) / "gsplat")
    if "gsplat" in runs and runs["torch"]["mean_loss_last_50"]:
        runs["last_50_ratio_gsplat_to_torch"] = runs["gsplat"]["mean_loss_last_50"] / runs["torch"]["mean_loss_last_50"]
    return runs


# ----------------------------------------------------------------------------------------- render
def ring_cameras(scene, count: int, width: int, height: int):
    """`count` cameras on a small arc in front of the scene, looking at its centre (K for width x height)."""
    from surfsplat import Cameras
    from surfsplat.data.synthetic.surfel_scene import SPHERE_CENTER
    from surfsplat.geometry.cameras import look_at

    focal = 1.1 * min(width, height)
    K = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    target = torch.tensor([0.0, 0.0, SPHERE_CENTER[2]])
    eyes = torch.tensor([[0.3 * (i / max(count - 1, 1) - 0.5), 0.05 * math.sin(i), 0.0] for i in range(count)])
    return Cameras(look_at(eyes, target.expand(count, 3)), K.expand(count, 3, 3).clone())


def time_pass(fn, leaves: dict, repeats: int, device: torch.device) -> dict:
    """Median seconds of forward + backward of fn(leaves) -> a scalar loss (after one warm-up)."""
    times = []
    for i in range(repeats + 1):
        for leaf in leaves.values():
            leaf.grad = None
        sync(device)
        start = time.perf_counter()
        fn(leaves).backward()
        sync(device)
        if i:
            times.append(time.perf_counter() - start)
    return {"median_s": statistics.median(times), "min_s": min(times), "max_s": max(times)}


def render_case(resolution: int, views: int, cameras: int, width: int, height: int, args, device) -> dict:
    from surfsplat import Gaussians
    from surfsplat.data.synthetic.surfel_scene import make_scene
    from surfsplat.render import gsplat_available, render

    scene = make_scene(resolution=resolution, views=views)
    g = scene.gaussians
    cams = ring_cameras(scene, cameras, width, height).to(device)
    leaves = {
        k: getattr(g, k).detach().to(device, torch.float32).requires_grad_(True)
        for k in ("means", "quats", "scales", "opacities", "sh")
    }
    weights = torch.rand(cameras, 3, height, width, generator=torch.Generator().manual_seed(0)).to(device)

    def ours(backend: str):
        def fn(p: dict):
            out = render(Gaussians(**p), cams, width, height, backend=backend, alpha_threshold=None)
            return (out.color * weights).sum()

        return fn

    row = {"surfels": len(g), "cameras": cameras, "width": width, "height": height}
    backends = ["torch"] + (["gsplat"] if gsplat_available(device) else [])
    for backend in backends:
        row[backend] = time_pass(ours(backend), leaves, args.repeats, device)
    if "gsplat" in backends:
        from gsplat import rasterization_2dgs

        degree = math.isqrt(g.sh.shape[-1]) - 1

        def theirs(p: dict):
            scales = torch.cat((p["scales"], torch.zeros_like(p["scales"][:, :1])), -1)
            colors, *_ = rasterization_2dgs(
                p["means"],
                p["quats"],
                scales,
                p["opacities"],
                p["sh"].transpose(1, 2),
                cams.w2c,
                cams.K,
                width,
                height,
                sh_degree=degree,
            )
            return (colors.permute(0, 3, 1, 2) * weights).sum()

        row["gsplat_rasterization_2dgs"] = time_pass(theirs, leaves, args.repeats, device)
        reference = row["gsplat_rasterization_2dgs"]["median_s"]
        row["ratio_ours_gsplat"] = row["gsplat"]["median_s"] / reference
        row["ratio_ours_torch"] = row["torch"]["median_s"] / reference
    if device.type == "cuda":
        row["peak_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
        torch.cuda.reset_peak_memory_stats(device)
    return row


def render_part(args, device: torch.device, build, report: dict) -> dict:
    wait_for_build(build, report)
    if args.quick:
        cases = [(32, 2, 3, 40, 32)]
    else:
        cases = [(256, 6, 7, 400, 288), (512, 4, 8, 512, 512)]
    return {f"{c[2]}x{c[3]}x{c[4]}": render_case(*c, args, device) for c in cases}


# ----------------------------------------------------------------------------------------- reconstruct
def reconstruct_part(args, device: torch.device, build, report: dict) -> dict:
    from capture import run_cli, write_1080p_video
    from surfsplat.data.images import list_images

    wait_for_build(build, report)
    data = sample_data(args.data)
    dtu = data / "dtu_scan24"
    photos = list_images(dtu / "images_4")
    results = {"data": str(data)}
    # MP4s need imageio-ffmpeg's ffmpeg binary; a machine without it reconstructs every other output
    # and says what it left out.
    has_ffmpeg = importlib.util.find_spec("imageio_ffmpeg") is not None
    if not has_ffmpeg:
        results["left_out"] = "video output and the 1080p video: imageio-ffmpeg is not installed"
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        common = ["--device", device.type, "--checkpoint", "tiny-synthetic"]
        views = [str(photos[i]) for i in DTU_VIEWS]
        size = ["96", "128", "--formats", "ply"] if args.quick else ["288", "400"]
        if not has_ffmpeg and not args.quick:
            size += ["--formats", "ply", "renders", "mesh"]
        results["dtu_7_views"] = run_cli(
            ["--images", *views, "--cameras", str(dtu), "--size", *size, *common], tmp / "dtu"
        )
        print(f"reconstruct dtu: {json.dumps(results['dtu_7_views'])}", flush=True)
        if has_ffmpeg and not args.quick:
            video = tmp / "phone.mp4"
            write_1080p_video(video, 300)
            results["video_1080p_10s"] = run_cli(["--video", str(video), *common], tmp / "video")
            print(f"reconstruct video: {json.dumps(results['video_1080p_10s'])}", flush=True)
    return results


# ----------------------------------------------------------------------------------------- optimizer
def optimize_part(args, device: torch.device, build, report: dict) -> dict:
    """The per-scene optimizer on the card (gsplat backend): `surfsplat reconstruct` of LLFF fern with its
    held-out views, the shipped defaults (3,000 steps from COLMAP's points, densification, distortion
    off), as benchmarks/optimize.py's fern-cli runs it on the CPU: held-out PSNR before and after, the
    stages' seconds, the start, the surfels."""
    from capture import run_cli

    wait_for_build(build, report)
    fern = sample_data(args.data) / "llff_fern"
    extra = ["--size", "96", "128", "--optimize-steps", "20"] if args.quick else []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "fern"
        record = run_cli(
            ["--images", str(fern / "images_8"), "--cameras", str(fern), "--images-folder", "images_8"]
            + ["--holdout-every", "8", "--formats", "ply", "--raw-3dgs", "--device", device.type, *extra],
            out,
        )
        summary = out / "reconstruction.json"
        if summary.is_file():
            document = json.loads(summary.read_text())
            held = document.get("capture", {}).get("held_out") or {}
            optimize = document.get("optimize", {})
            record["held_out_psnr"] = held.get("mean_psnr")
            record["held_out_psnr_before"] = (held.get("before_optimization") or {}).get("mean_psnr")
            record["optimize"] = {k: optimize.get(k) for k in ("start", "points", "steps", "surfels_after", "seconds")}
    print(f"optimize fern: {json.dumps(record)}", flush=True)
    return {"fern": record}


# ----------------------------------------------------------------------------------------- throughput
def throughput_run(preset: str, size: int, batch: int, steps: int, device: torch.device) -> dict:
    """The training step's own speed: one batch of procedural rooms made once (its making timed apart;
    the training loop's wait for data is the train part's `data_wait_seconds`) and stepped on `steps`
    times, after one warm-up step."""
    from torch.utils.data import DataLoader, default_collate

    from surfsplat.data.synthetic import SyntheticDataset, SyntheticDatasetConfig
    from surfsplat.model.decoder import decoder_mode
    from surfsplat.train import build_model, build_optimizer, train_preset
    from surfsplat.train.config import override
    from surfsplat.train.data import to_train_batch
    from surfsplat.train.loop import training_step
    from surfsplat.train.losses import ImageLoss

    config = override(
        train_preset(preset),
        {"data.image_shape": [size, size], "data.num_target_views": 4, "loss.lpips_weight": 0.0, "batch_size": batch},
    )
    torch.manual_seed(0)
    model = build_model(config).to(device).train()
    optimizer = build_optimizer(model, config)
    loss_fn = ImageLoss(config.loss).to(device)
    dataset = SyntheticDataset(
        SyntheticDatasetConfig(length=batch, image_shape=(size, size), num_target_views=4, supersample=1)
    )
    workers = min(8, os.cpu_count() or 1) if device.type == "cuda" else 0
    start = time.perf_counter()
    samples = next(iter(DataLoader(dataset, batch_size=batch, num_workers=workers, collate_fn=default_collate)))
    batch_on_device = to_train_batch(samples, list(range(batch))).to(device)
    making = time.perf_counter() - start
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    mode = decoder_mode(model.cfg.adapter)
    amp = torch.bfloat16 if device.type == "cuda" else None
    times, skipped = [], 0
    for step in range(steps + 1):
        sync(device)
        start = time.perf_counter()
        out = training_step(
            model,
            model,
            batch_on_device,
            loss_fn,
            optimizer,
            mode=mode,
            amp_dtype=amp,
            grad_clip=config.optim.grad_clip,
        )
        sync(device)
        if step:  # the first step selects kernels and warms the allocator
            times.append(time.perf_counter() - start)
        skipped += out.nonfinite is not None
    median = statistics.median(times)
    peak = torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else None
    return {
        "preset": preset,
        "size": size,
        "batch": batch,
        "steps": steps,
        "precision": "bf16 autocast" if amp is not None else "fp32",
        "step_median_s": median,
        "step_min_s": min(times),
        "samples_per_s": batch / median,
        "seconds_making_the_batch": making,
        "skipped_updates": skipped,
        "peak_mb": peak,
    }


def throughput_part(args, device: torch.device, build, report: dict) -> dict:
    wait_for_build(build, report)
    preset, size, steps, batches = (
        ("tiny", 32, 1, [1]) if args.quick else ("small", 256, args.throughput_steps, args.batches)
    )
    return {f"batch_{b}": throughput_run(preset, size, b, steps, device) for b in batches}


# ----------------------------------------------------------------------------------------- main
PARTS = {
    "train": train_part,
    "render": render_part,
    "reconstruct": reconstruct_part,
    "optimize": optimize_part,
    "throughput": throughput_part,
}


def print_table(results: dict) -> None:
    parts = results["parts"]
    train = parts.get("train", {})
    for backend in ("torch", "gsplat"):
        if backend in train and "backend" in train[backend]:
            r = train[backend]
            print(
                f"train {backend:6s}  {r['steps']} steps  {r['seconds_per_step'] * 1000:7.1f} ms/step  "
                f"last-50 loss {r['mean_loss_last_50']}  finite {r['all_finite']}  data wait {r['data_wait_seconds']:.1f} s"
            )
    for name, row in parts.get("render", {}).items():
        if isinstance(row, dict) and "surfels" in row:
            cells = [
                f"{k} {row[k]['median_s'] * 1000:.1f} ms"
                for k in ("gsplat", "torch", "gsplat_rasterization_2dgs")
                if k in row
            ]
            ratio = f"  ours/gsplat {row['ratio_ours_gsplat']:.2f}x" if "ratio_ours_gsplat" in row else ""
            print(f"render {row['surfels']:,} surfels, {name}: " + ", ".join(cells) + ratio)
    for name, run in parts.get("reconstruct", {}).items():
        if isinstance(run, dict) and "seconds" in run:
            print(f"reconstruct {name}: {run['seconds']:.1f} s, stages {run.get('stages', run.get('error'))}")
    for name, run in parts.get("optimize", {}).items():
        if isinstance(run, dict):
            print(
                f"optimize {name}: {run['seconds']:.1f} s, held-out PSNR {run.get('held_out_psnr_before')} -> "
                f"{run.get('held_out_psnr')}, {run.get('optimize', run.get('error'))}"
            )
    for name, run in parts.get("throughput", {}).items():
        if isinstance(run, dict) and "samples_per_s" in run:
            print(
                f"throughput {run['preset']} {name}: {run['step_median_s'] * 1000:.0f} ms/step, "
                f"{run['samples_per_s']:.1f} samples/s, peak {run['peak_mb']} MB"
            )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--parts", nargs="+", default=list(PARTS), choices=list(PARTS))
    parser.add_argument("--out", type=Path, default=RESULTS / "gpu.json")
    parser.add_argument("--data", type=Path, default=None, help="the sample captures (default: ../shared/data)")
    parser.add_argument("--quick", action="store_true", help="tiny sizes (the CPU test of this script)")
    parser.add_argument("--train-steps", type=int, default=300)
    parser.add_argument("--train-size", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--throughput-steps", type=int, default=10)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    args = parser.parse_args()
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print("--device cuda: no CUDA device is available", file=sys.stderr)
        return 2
    start = time.perf_counter()
    build = start_gsplat_build(device)
    results = {
        "machine": machine(),
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "torch": torch.__version__,
        "parts": {},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    order = [
        p for p in ("train", "render", "reconstruct", "optimize", "throughput") if p in args.parts
    ]  # gsplat-free first
    for part in order:
        tick = time.perf_counter()
        try:
            results["parts"][part] = PARTS[part](args, device, build, results)
        except Exception as err:  # recorded in the JSON: one part's failure does not stop the others
            results["parts"][part] = {"error": repr(err), "traceback": traceback.format_exc()}
        results["parts"][part]["seconds_total"] = time.perf_counter() - tick
        results["seconds"] = time.perf_counter() - start
        args.out.write_text(json.dumps(results, indent=1, default=str))  # after every part
        print(f"{part}: {results['parts'][part]['seconds_total']:.1f} s", flush=True)
    print_table(results)
    print(f"wrote {args.out}")
    return 0 if all("error" not in p for p in results["parts"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
