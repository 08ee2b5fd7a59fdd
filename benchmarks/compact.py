"""Compact surfels: surfels against PSNR at x1 and x4, render time and PLY size, per compaction level.

    python benchmarks/compact.py --checkpoint runs/tiny
    python benchmarks/compact.py --checkpoint runs/tiny --data ../data --levels 1 2 3 4
    python benchmarks/compact.py --checkpoint tiny-synthetic --data ../data \
        --capture-checkpoint fern=runs/capture-fern dtu_scan24=runs/capture-dtu_scan24

For each scene the model reconstructs the context views once; the reconstruction is then compacted
at every level (0 = as predicted, one surfel per pixel per view) and its target views are rendered at
x1 and x4. Held-out procedural rooms are scored against native ray-cast truth at both scales; the
real captures (`--data` folder holding llff_fern and dtu_scan24) against their photos at x1 and the
bicubic-upsampled photos at x4 (HRRC). Every loss is against the uncompacted reconstruction of the
same scene; "fidelity" is the PSNR of the compacted render against the uncompacted one (the same
picture: higher is closer). `--capture-checkpoint NAME=CKPT` reconstructs a capture with its own
model (scripts/capture_models.sh fine-tunes one per capture with the benchmark's target views held
out), since a model trained on synthetic rooms reconstructs photos too poorly for a loss against
them to mean much. Writes benchmarks/results/compact.json, prints a table and, when matplotlib is
installed (`pip install 'surfsplat[bench]'`), draws benchmarks/results/compact.png.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import tempfile
import time
from pathlib import Path

import torch

from common import REAL
from surfsplat.compaction import LEVELS, compact_surfels
from surfsplat.export.figures import write_text
from surfsplat.export.ply import save_ply
from surfsplat.geometry.cameras import Cameras
from surfsplat.metrics.hrrc import upsample_ground_truth
from surfsplat.metrics.image import psnr
from surfsplat.model.decoder import decoder_mode
from surfsplat.model.loading import ModelSpec, load_model
from surfsplat.render import render
from surfsplat.render.cpu.backend import contributing_pairs

ROOT = Path(__file__).resolve().parents[1]
FACTORS = (1, 4)
REPEATS = 3  # renders timed per factor (the median is reported)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True, help="our checkpoint (run folder, checkpoint folder, file)")
    parser.add_argument("--levels", nargs="+", type=int, default=sorted(LEVELS), help="compaction levels")
    parser.add_argument("--scenes", type=int, default=4, help="held-out procedural rooms")
    parser.add_argument("--image-size", type=int, default=64, help="procedural room size (the tiny preset's)")
    parser.add_argument("--data", type=Path, default=None, help="folder with llff_fern and dtu_scan24 (optional)")
    parser.add_argument(
        "--capture-checkpoint",
        nargs="+",
        default=[],
        metavar="NAME=CKPT",
        help=f"reconstruct capture NAME ({', '.join(REAL)}) with CKPT instead of --checkpoint",
    )
    parser.add_argument("--real-size", nargs=2, type=int, default=(192, 256), metavar=("H", "W"))
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "compact.json")
    parser.add_argument("--plot", type=Path, default=ROOT / "benchmarks" / "results" / "compact.png")
    args = parser.parse_args()
    for level in args.levels:
        if level not in LEVELS:
            parser.error(f"--levels: expected values in {sorted(LEVELS)}, got {level}")

    capture_checkpoints = {}
    for item in args.capture_checkpoint:
        name, _, path = item.partition("=")
        if name not in REAL or not path:
            parser.error(f"--capture-checkpoint: expected NAME=CKPT with NAME in {sorted(REAL)}, got {item!r}")
        capture_checkpoints[name] = path

    model, label = load_model(ModelSpec(args.checkpoint), "cpu")
    model.eval()
    models = {name: load_model(ModelSpec(path), "cpu") for name, path in capture_checkpoints.items()}
    for capture_model, _ in models.values():
        capture_model.eval()
    scenes = procedural_scenes(args.scenes, args.image_size)
    if args.data is not None:
        scenes += real_scenes(args.data, tuple(args.real_size))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in scenes:
            scene_model = models[scene["group"]][0] if scene["group"] in models else model
            rows += measure_scene(scene_model, scene, [0, *args.levels], Path(tmp))
    summary = summarize(rows)
    document = {
        "settings": {
            "checkpoint": str(args.checkpoint),
            "model": label,
            "capture_models": {name: models[name][1] for name in models},
            "levels": {str(k): vars(LEVELS[k]) for k in args.levels},
            "procedural_scenes": args.scenes,
            "procedural_size": args.image_size,
            "real_size": list(args.real_size),
            "real_views": {k: {"context": v[2], "target": v[3]} for k, v in REAL.items()} if args.data else None,
            "torch": torch.__version__,
            "machine": platform.machine(),
            "threads": torch.get_num_threads(),
        },
        "summary": summary,
        "scenes": rows,
    }
    write_text(args.out, json.dumps(document, indent=1) + "\n")
    print(table(summary))
    print(f"wrote {args.out}")
    plotted = plot(summary, args.plot)
    print(f"wrote {args.plot}" if plotted else "plot skipped: matplotlib is not installed (pip install matplotlib)")


# ---------------------------------------------------------------------------------------------- scenes
def procedural_scenes(count: int, size: int) -> list[dict]:
    """Held-out rooms (the demo's evaluation seed) with native truth at every factor."""
    from surfsplat.data.eval_index import EvaluationIndex
    from surfsplat.demo import DemoConfig, native_truth, write_eval_data
    from surfsplat.evaluation import iter_index_samples

    if count < 1:
        return []
    demo = DemoConfig(image_size=size, eval_scenes=count, eval_frames=6, eval_targets=3)
    with tempfile.TemporaryDirectory() as tmp:
        index_path, data_dir = write_eval_data(demo, Path(tmp))
        samples = list(iter_index_samples([data_dir], EvaluationIndex.load(index_path), near=0.5, far=15.0))
    truth = native_truth(demo, samples, FACTORS)
    return [
        {
            "group": "procedural",
            "name": s.key,
            "context_images": s.context_images,
            "context_cameras": s.context_cameras,
            "target_cameras": s.target_cameras,
            "truth": {f: t[f]["image"] for f in FACTORS},
            "near": s.near,
            "far": s.far,
        }
        for s, t in zip(samples, truth)
    ]


def real_scenes(data: Path, shape: tuple[int, int]) -> list[dict]:
    from surfsplat.data.load import load_scene
    from surfsplat.data.transforms import rescale_and_crop

    out = []
    for name, (folder, images, context, target) in REAL.items():
        scene = load_scene(data / folder, images=images)
        views = context + target
        stack, K, _ = rescale_and_crop(scene.images[views], scene.cameras.K[views].float(), shape)
        cams = Cameras(scene.cameras.c2w[views].float(), K)
        near = float(scene.near[views].min()) if scene.near is not None else 0.5
        far = float(scene.far[views].max()) if scene.far is not None else 100.0
        n = len(context)
        out.append(
            {
                "group": name,
                "name": name,
                "context_images": stack[:n],
                "context_cameras": cams[:n],
                "target_cameras": cams[n:],
                "truth": {f: upsample_ground_truth(stack[n:], f) if f > 1 else stack[n:] for f in FACTORS},
                "near": near,
                "far": far,
            }
        )
    return out


# ---------------------------------------------------------------------------------------------- measuring
@torch.no_grad()
def measure_scene(model, scene: dict, levels: list[int], tmp: Path) -> list[dict]:
    images = scene["context_images"]
    H, W = images.shape[-2:]
    cams = scene["context_cameras"]
    prediction = model(images[None], cams, scene["near"], scene["far"])
    full = prediction.gaussians.select(0).to(torch.float32)
    tau = prediction.alpha_threshold
    mode = decoder_mode(model.cfg.adapter)
    rows = []
    uncompacted: dict[int, torch.Tensor] = {}  # level 0's renders, for the fidelity of the others
    for level in levels:
        start = time.perf_counter()
        if level == 0:
            g, stats = full, {"output": len(full)}
        else:
            result = compact_surfels(full, cams, H, W, level, mode=mode, alpha_threshold=tau)
            g, stats = result.gaussians, result.stats
        seconds_compact = time.perf_counter() - start if level else 0.0
        row = {
            "group": scene["group"],
            "scene": scene["name"],
            "level": level,
            "surfels": len(g),
            "stats": stats,
            "seconds_compact": seconds_compact,
            "ply_bytes": save_ply(g, tmp / "surfels.ply").stat().st_size,
        }
        targets = scene["target_cameras"]
        for f in FACTORS:
            render(g, targets[:1].scaled(f), W * f, H * f, mode=mode, alpha_threshold=tau)  # warm caches
            times = []
            for _ in range(REPEATS):
                start = time.perf_counter()
                out = render(g, targets.scaled(f), W * f, H * f, mode=mode, alpha_threshold=tau)
                times.append(time.perf_counter() - start)
            row[f"seconds_render_x{f}"] = statistics.median(times)
            # The renderer's work, independent of the machine's load: (pixel, surfel) pairs with alpha >= 1/255.
            row[f"pairs_x{f}"] = sum(contributing_pairs(g, targets.scaled(f), W * f, H * f, mode))
            row[f"psnr_x{f}"] = float(psnr(out.color, scene["truth"][f]).mean())
            uncompacted.setdefault(f, out.color)
            row[f"fidelity_x{f}"] = fidelity(out.color, uncompacted[f])
        rows.append(row)
        print(
            f"{scene['name']:>24} level {level}: {len(g):>7,} surfels, PSNR x1 {row['psnr_x1']:.3f} "
            f"x4 {row['psnr_x4']:.3f}, compact {seconds_compact:.2f} s",
            flush=True,
        )
    return rows


def fidelity(image: torch.Tensor, uncompacted: torch.Tensor) -> float | None:
    """PSNR in dB of a compacted render against the uncompacted one over all target views (None:
    identical pictures, as level 0 is with itself)."""
    mse = float((image.clamp(0, 1) - uncompacted.clamp(0, 1)).square().mean())
    return -10 * math.log10(mse) if mse > 0 else None


def summarize(rows: list[dict]) -> dict:
    """Per group and level: mean surfel reduction, PSNR loss and time/size ratios vs level 0."""
    base = {(r["group"], r["scene"]): r for r in rows if r["level"] == 0}
    out: dict[str, dict[str, dict]] = {}
    for r in rows:
        b = base[(r["group"], r["scene"])]
        out.setdefault(r["group"], {}).setdefault(str(r["level"]), []).append(
            {
                "surfels": r["surfels"],
                "reduction": b["surfels"] / r["surfels"],
                "psnr_x1": r["psnr_x1"],
                "psnr_x4": r["psnr_x4"],
                "loss_x1": b["psnr_x1"] - r["psnr_x1"],
                "loss_x4": b["psnr_x4"] - r["psnr_x4"],
                "render_x1": r["seconds_render_x1"] / b["seconds_render_x1"],
                "render_x4": r["seconds_render_x4"] / b["seconds_render_x4"],
                "pairs_x1": r["pairs_x1"] / b["pairs_x1"],
                "pairs_x4": r["pairs_x4"] / b["pairs_x4"],
                "fidelity_x1": r["fidelity_x1"],
                "fidelity_x4": r["fidelity_x4"],
                "ply_mb": r["ply_bytes"] / 2**20,
                "seconds_compact": r["seconds_compact"],
            }
        )
    return {
        group: {level: {k: _mean([e[k] for e in entries]) for k in entries[0]} for level, entries in lv.items()}
        for group, lv in out.items()
    }


def _mean(values: list) -> float | None:
    return None if None in values else sum(values) / len(values)


def _db(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def table(summary: dict) -> str:
    head = (
        "group        | level | surfels | fewer x | PSNR x1 | loss x1 dB | PSNR x4 | loss x4 dB "
        "| fidelity x1 | fidelity x4 | render x1 | render x4 | pairs x1 | pairs x4 | PLY MB | compact s"
    )
    lines = [head, "-" * len(head)]
    for group, levels in summary.items():
        for level, m in levels.items():
            lines.append(
                f"{group:<12} | {level:>5} | {m['surfels']:>7,.0f} | {m['reduction']:>7.2f} | {m['psnr_x1']:>7.3f} | "
                f"{m['loss_x1']:>10.3f} | {m['psnr_x4']:>7.3f} | {m['loss_x4']:>10.3f} | "
                f"{_db(m['fidelity_x1']):>11} | {_db(m['fidelity_x4']):>11} | {m['render_x1']:>9.2f} | "
                f"{m['render_x4']:>9.2f} | {m['pairs_x1']:>8.2f} | {m['pairs_x4']:>8.2f} | {m['ply_mb']:>6.2f} | "
                f"{m['seconds_compact']:>9.2f}"
            )
    lines.append(
        "fidelity xS: PSNR against the uncompacted render (same picture), render xS: median render time of the targets, pairs xS: (pixel, surfel) pairs with alpha >= 1/255, "
        "both relative to the uncompacted reconstruction (level 0)"
    )
    return "\n".join(lines)


def plot(summary: dict, path: Path) -> bool:
    """PSNR loss against surfel reduction per group, x1 and x4 side by side (matplotlib only)."""
    try:
        import matplotlib
    except ImportError:
        return False
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8, 3.8), sharey=True)
    for ax, f in zip(axes, FACTORS):
        for group, levels in summary.items():
            xs = [m["reduction"] for m in levels.values()]
            ys = [m[f"loss_x{f}"] for m in levels.values()]
            ax.plot(xs, ys, marker="o", label=group)
            last = None
            for level, x, y in zip(levels, xs, ys):
                # Levels that barely differ (0-2 near 1x) share one label instead of overprinting.
                if last is not None and abs(math.log2(x / last[0])) < 0.12 and abs(y - last[1]) < 0.25:
                    continue
                ax.annotate(level, (x, y), textcoords="offset points", xytext=(3, 3), fontsize=7)
                last = (x, y)
        # The target: at least 2x fewer within 0.1 dB.
        ax.axhline(0.1, color="grey", linestyle=":", linewidth=1)
        ax.axvline(2, color="grey", linestyle=":", linewidth=1)
        ax.annotate("0.1 dB", (2, 0.1), textcoords="offset points", xytext=(3, 3), fontsize=7, color="grey")
        ax.set_xscale("log", base=2)
        ax.set_xticks([1, 2, 4, 8], ["1", "2", "4", "8"])
        # Linear within 0.5 dB, where the target lies, logarithmic beyond (DTU's gains reach 2-4 dB).
        ax.set_yscale("symlog", linthresh=0.5, linscale=1.2)
        ax.set_yticks([-4, -2, -1, -0.5, -0.25, 0, 0.25, 0.5], ["-4", "-2", "-1", "-0.5", "-0.25", "0", "0.25", "0.5"])
        ax.set_xlabel("fewer surfels (x)")
        ax.set_title(f"x{f}")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("PSNR loss (dB; log beyond 0.5)")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


if __name__ == "__main__":
    main()
