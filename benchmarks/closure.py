"""Closed surfaces: closure, surfel size, image and geometry scores of models side by side.

    python benchmarks/closure.py --checkpoint tiny-synthetic
    python benchmarks/closure.py --checkpoint before=runs/old after=runs/new --data ../data
    python benchmarks/closure.py --checkpoint runs/ablation-* --rooms 12 --out benchmarks/results/ablation.json
    python benchmarks/closure.py --checkpoint before=runs/old after=tiny-synthetic --figure docs/closure_x4.png

Every model reconstructs the held-out procedural rooms the shipped model's metadata is measured on
(seed 2026, 12 rooms at 64x64, 6 frames along each camera path, context: the path's ends, targets:
the four frames between them) and renders the targets at x1, x2 and x4. Scored there:
- PSNR at x1 against the rooms' x1 images (the metadata's figure) and at x1 / x4 against native
  ray-cast truth at that resolution (not an upsampling);
- depth AbsRel and the median normal error of the rendered target views against exact truth;
- the closure metrics of `surfsplat.metrics.closure`: alpha and coverage at every factor, closure
  (alpha x4 / alpha x1), share of scale multipliers at each bound, share of surfels under half their
  pixel footprint, opacity quantiles.
With `--data` (a folder holding dtu_scan24 and llff_fern) every model also reconstructs the DTU pair
of the community's index and a fern pair at 192x256, scored for closure from the context cameras
(photos have no native high-resolution truth). Writes JSON (default benchmarks/results/closure.json)
and prints one table. With `--figure` it also writes a PNG of one held-out target at x4: its native
truth, then each model's render, with each render's alpha below it (white = 1).
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import torch

from surfsplat.evaluation import iter_index_samples, predict_sample
from surfsplat.evaluation.geometry import GeometryConfig, GeometryEvaluator
from surfsplat.export.figures import write_text
from surfsplat.geometry.pixels import pixel_footprints, views_of_pixels
from surfsplat.metrics.closure import ClosureAccumulator, closure_metrics
from surfsplat.metrics.image import psnr
from surfsplat.model.decoder import decoder_mode
from surfsplat.model.loading import ModelSpec, load_model

ROOT = Path(__file__).resolve().parents[1]
FACTORS = (1, 2, 4)
ROOM_SEED, ROOM_FRAMES, ROOM_SIZE = 2026, 6, 64  # the held-out set of scripts/tiny_synthetic.sh
# Real pairs: (folder, image folder, context views); DTU's are the community index's (33, 31).
REAL = {"dtu_scan24": ("dtu_scan24", "images_4", [33, 31]), "fern": ("llff_fern", "images_8", [4, 10])}
REAL_SHAPE = (192, 256)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", nargs="+", required=True, help="models: NAME=CKPT or CKPT (named by itself)")
    parser.add_argument("--rooms", type=int, default=12, help="held-out rooms (default 12, the metadata's)")
    parser.add_argument("--data", type=Path, default=None, help="folder with dtu_scan24 and llff_fern (optional)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "closure.json")
    parser.add_argument("--figure", type=Path, default=None, help="PNG of one held-out target at x4 (optional)")
    parser.add_argument(
        "--figure-view", type=int, nargs=2, default=(2, 1), metavar=("ROOM", "TARGET"), help="which one (default 2 1)"
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    models = dict(_named(c) for c in args.checkpoint)
    samples, native = heldout_rooms(args.rooms)
    real = real_pairs(args.data) if args.data is not None else []
    if args.figure is not None and not (0 <= args.figure_view[0] < len(samples) and 0 <= args.figure_view[1] < 4):
        parser.error(f"--figure-view: room 0..{len(samples) - 1}, target 0..3; got {args.figure_view}")
    rows, pictures = {}, []
    for name, spec in models.items():
        model, label = load_model(ModelSpec(spec))
        model.eval()
        start = time.perf_counter()
        rows[name] = {"checkpoint": spec, "model": label, **score_rooms(model, samples, native)}
        if args.figure is not None:
            pictures.append(render_x4(model, samples[args.figure_view[0]], args.figure_view[1]))
        for pair in real:
            rows[name][pair["name"]] = score_pair(model, pair)
        rows[name]["seconds"] = time.perf_counter() - start
        print(f"{name}: scored in {rows[name]['seconds']:.0f} s", flush=True)
    document = {
        "benchmark": "closure",
        "rooms": {"seed": ROOM_SEED, "count": args.rooms, "size": ROOM_SIZE, "frames": ROOM_FRAMES},
        "real_pairs": {k: {"folder": f, "images": i, "context": c} for k, (f, i, c) in REAL.items()} if real else None,
        "machine": {"platform": platform.platform(), "threads": args.threads},
        "models": rows,
    }
    write_text(args.out, json.dumps(document, indent=1) + "\n")
    if args.figure is not None:
        from surfsplat.export.figures import image_grid
        from surfsplat.export.images import write_png

        room, view = args.figure_view
        truth = native[room][FACTORS[-1]][view]
        grid = image_grid([[truth, *(c for c, _ in pictures)], [None, *(a for _, a in pictures)]])
        write_png(args.figure, grid)
        print(f"wrote {args.figure} (columns: native truth, {', '.join(models)})")
    print(table(rows, [p["name"] for p in real]))
    print(f"wrote {args.out}")


def _named(text: str) -> tuple[str, str]:
    name, sep, path = text.partition("=")
    return (name, path) if sep else (Path(text).name or text, text)


# ---------------------------------------------------------------------------------------------- data
def heldout_rooms(count: int) -> tuple[list, list[dict[int, torch.Tensor]]]:
    """The held-out rooms as evaluation samples, and native truth images of their targets per factor."""
    from surfsplat.data.eval_index import EvaluationIndex
    from surfsplat.data.synthetic import (
        SyntheticDataset,
        SyntheticDatasetConfig,
        render_synthetic,
        write_synthetic_chunks,
    )

    context, targets = [0, ROOM_FRAMES - 1], list(range(1, ROOM_FRAMES - 1))
    with tempfile.TemporaryDirectory() as tmp:
        chunks = Path(tmp) / "chunks"
        keys = write_synthetic_chunks(
            chunks, count, seed=ROOM_SEED, image_shape=(ROOM_SIZE, ROOM_SIZE), num_frames=ROOM_FRAMES, supersample=2
        )
        index = Path(tmp) / "index.json"
        index.write_text(json.dumps({k: {"context": context, "target": targets} for k in sorted(keys)}))
        samples = list(iter_index_samples([chunks], EvaluationIndex.load(index), near=0.5, far=15.0))
    rooms = SyntheticDataset(SyntheticDatasetConfig(length=count, seed=ROOM_SEED, image_shape=(ROOM_SIZE, ROOM_SIZE)))
    positions = torch.linspace(0, 1, ROOM_FRAMES, dtype=torch.float64)
    native = []
    for sample in samples:
        i = int(sample.scene.rsplit("-", 1)[1])
        scene = rooms.scene(i)
        cams = rooms.trajectory(i, scene).cameras(positions[targets], ROOM_SIZE, ROOM_SIZE)
        native.append(
            {s: render_synthetic(scene, cams.scaled(float(s)), ROOM_SIZE * s, ROOM_SIZE * s).image for s in FACTORS}
        )
    return samples, native


def real_pairs(data: Path) -> list[dict]:
    from surfsplat.data.load import load_scene
    from surfsplat.data.transforms import rescale_and_crop
    from surfsplat.geometry.cameras import Cameras

    out = []
    for name, (folder, images, views) in REAL.items():
        scene = load_scene(data / folder, images=images)
        stack, K, _ = rescale_and_crop(scene.images[views], scene.cameras.K[views].float(), REAL_SHAPE)
        near = float(scene.near[views].min()) if scene.near is not None else 0.5
        far = float(scene.far[views].max()) if scene.far is not None else 100.0
        cams = Cameras(scene.cameras.c2w[views].float(), K)
        out.append({"name": name, "images": stack, "cameras": cams, "near": near, "far": far})
    return out


# ---------------------------------------------------------------------------------------------- scoring
@torch.no_grad()
def score_rooms(model, samples: list, native: list[dict[int, torch.Tensor]]) -> dict:
    geometry = GeometryEvaluator(GeometryConfig(mesh=False))
    closure = ClosureAccumulator()
    x1, vs_native = [], {s: [] for s in FACTORS}
    for sample, truth in zip(samples, native):
        pred = predict_sample(model, sample, FACTORS)
        x1.append(float(psnr(pred.renders[1].color.clamp(0, 1), sample.target_images.clamp(0, 1)).mean()))
        for s in FACTORS:
            vs_native[s].append(float(psnr(pred.renders[s].color.clamp(0, 1), truth[s].clamp(0, 1)).mean()))
        geometry.add(sample, pred)
        closure.add_alpha({s: r.alpha for s, r in pred.renders.items()})
        closure.add_surfels(pred.gaussians, *pred.closure_surfels())
    mean = geometry.report().mean()
    return {
        "psnr_x1": sum(x1) / len(x1),
        "psnr_native": {f"x{s}": sum(v) / len(v) for s, v in vs_native.items()},
        "abs_rel": mean["abs_rel"],
        "median_normal_deg": mean["median_deg"],
        "closure": closure.report().to_json(),
    }


@torch.no_grad()
def render_x4(model, sample, view: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(colour [3, H, W], alpha [1, H, W]) of one target rendered at the largest factor."""
    render = predict_sample(model, sample, (FACTORS[-1],)).renders[FACTORS[-1]]
    return render.color[view].clamp(0, 1), render.alpha[view].clamp(0, 1)


@torch.no_grad()
def score_pair(model, pair: dict) -> dict:
    cams, (h, w) = pair["cameras"], pair["images"].shape[-2:]
    prediction = model(pair["images"][None], cams, pair["near"], pair["far"])
    gaussians = prediction.gaussians.select(0).to(torch.float32)
    fixed = model.cfg.adapter.prior != "surface"
    metrics = closure_metrics(
        gaussians,
        cams,
        w,
        h,
        FACTORS,
        views=views_of_pixels(len(cams), h, w),
        multipliers=None if fixed else prediction.adapter_output.scales_mul[0],
        multiplier_range=None if fixed else model.cfg.adapter.scale_multiplier_range,
        mode=decoder_mode(model.cfg.adapter),
    )
    footprints = pixel_footprints(gaussians, cams, w, h, views_of_pixels(len(cams), h, w))
    return {"closure": metrics.to_json(), "footprint_median": float(footprints.median())}


# ---------------------------------------------------------------------------------------------- report
def table(rows: dict, real: list[str]) -> str:
    head = [
        "model",
        "PSNR x1",
        "native x1",
        "native x4",
        "AbsRel",
        "normal med",
        "closure",
        "undersized",
        "mult at 1/3",
        "cov x4",
        "opacity p50",
    ] + [f"{r} closure / undersized" for r in real]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, r in rows.items():
        c = r["closure"]
        low = c["multiplier_at_low"]
        cells = [
            name,
            f"{r['psnr_x1']:.2f}",
            f"{r['psnr_native']['x1']:.2f}",
            f"{r['psnr_native']['x4']:.2f}",
            f"{r['abs_rel']:.3f}",
            f"{r['median_normal_deg']:.1f}",
            f"{c['closure']:.3f}",
            f"{100 * c['undersized_share']:.0f}%",
            "n/a" if low is None else f"{100 * low:.0f}%",
            f"{c['coverage']['x4']['alpha>=0.5']:.3f}",
            f"{c['opacity_quantiles']['p50']:.2f}",
        ]
        for p in real:
            pc = r[p]["closure"]
            cells.append(f"{pc['closure']:.3f} / {100 * pc['undersized_share']:.0f}%")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
