"""The export baked for standard 3DGS viewers: what they show of a reconstruction, before and after.

    python benchmarks/bake.py --data ../data
    python benchmarks/bake.py --data ../data --capture-checkpoint fern=runs/capture-fern --steps 100

Each real capture (`--data` folder holding llff_fern and dtu_scan24; the views of
benchmarks/compact.py) is reconstructed once, by `--checkpoint` or the capture's own model, and
baked by `surfsplat.export.bake.bake_for_viewers`, as `surfsplat export` writes surfels_3dgs.ply.
Standard compositing (EWA, no alpha normalisation, on black) of the raw thin surfels and of the
baked Gaussians is compared with our render (forced alpha blending) over the pixels our render
covers (alpha >= 0.05): the mean standard alpha there and the colour PSNR, from the context
cameras and from the held-out target cameras, at x1 and x2. Writes benchmarks/results/bake.json and
prints a table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
from pathlib import Path

import torch

from common import REAL, RESULTS
from compact import real_scenes  # the captures and views of the compaction figures
from surfsplat.export.bake import BakeConfig, bake_for_viewers, thin_gaussians, viewer_figures
from surfsplat.export.figures import write_text
from surfsplat.model.decoder import decoder_mode
from surfsplat.model.loading import ModelSpec, load_model
from surfsplat.render import render

FACTORS = (1, 2)
GRID = [  # --grid: (steps, factors, nearby views, jittered views), the export's default first
    (60, (1, 2), 2, 1),
    (0, (1,), 0, 0),
    (15, (1,), 0, 0),
    (30, (1,), 0, 0),
    (15, (1,), 2, 1),
    (30, (1,), 2, 1),
    (60, (1,), 2, 1),
    (30, (1, 2), 2, 1),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", default="tiny-synthetic", help="model (name, run folder or file)")
    parser.add_argument("--data", type=Path, required=True, help="folder with llff_fern and dtu_scan24")
    parser.add_argument("--capture-checkpoint", nargs="+", default=[], metavar="NAME=CKPT")
    parser.add_argument("--real-size", nargs=2, type=int, default=(192, 256), metavar=("H", "W"))
    parser.add_argument(
        "--steps", type=int, default=None, help="Adam steps of the bake (default: BakeConfig.steps_for the views)"
    )
    parser.add_argument("--scenes", nargs="+", default=sorted(REAL), choices=sorted(REAL))
    parser.add_argument("--out", type=Path, default=RESULTS / "bake.json")
    parser.add_argument(
        "--grid", action="store_true", help="the cost curve: every GRID setting (steps, factors, fitted views) in turn"
    )
    args = parser.parse_args()
    checkpoints = {}
    for item in args.capture_checkpoint:
        name, _, path = item.partition("=")
        if name not in REAL or not path:
            parser.error(f"--capture-checkpoint: expected NAME=CKPT with NAME in {sorted(REAL)}, got {item!r}")
        checkpoints[name] = path
    config = dataclasses.replace(BakeConfig(), steps=args.steps)
    configs = [config]
    if args.grid:
        configs = [
            dataclasses.replace(BakeConfig(), steps=n, factors=f, nearby_views=a, jittered_views=b)
            for n, f, a, b in GRID
        ]

    rows = []
    for scene in real_scenes(args.data, tuple(args.real_size)):
        if scene["name"] not in args.scenes:
            continue
        model, label = load_model(ModelSpec(checkpoints.get(scene["name"], args.checkpoint)), "cpu")
        model.eval()
        for each in configs:
            rows.append(measure(model, label, scene, each))
            write_document(args, config, rows)
    print(table(rows))
    print(f"wrote {args.out}")


def measure(model, label: str, scene: dict, config: BakeConfig) -> dict:
    images = scene["context_images"]
    H, W = images.shape[-2:]
    with torch.no_grad():
        prediction = model(images[None], scene["context_cameras"], scene["near"], scene["far"])
    g = prediction.gaussians.select(0).to(torch.float32)
    tau = prediction.alpha_threshold
    mode = decoder_mode(model.cfg.adapter)
    baked, report = bake_for_viewers(g, scene["context_cameras"], H, W, config, mode=mode, alpha_threshold=tau)
    row = {
        "scene": scene["name"],
        "model": label,
        "surfels": len(g),
        "size": [H, W],
        "seconds_bake": report.seconds,
        "bake": {
            k: v
            for k, v in dataclasses.asdict(config).items()
            if k in ("steps", "factors", "nearby_views", "jittered_views")
        },
        "best_step": report.best_step,
        "fit_views": report.fit_views,
        "figures": {},
    }
    for views in ("context", "target"):
        cameras = scene[f"{views}_cameras"]
        for f in FACTORS:
            cams, w, h = cameras.scaled(float(f)), W * f, H * f
            with torch.no_grad():
                ours = render(g, cams, w, h, mode=mode, alpha_threshold=tau)
            before = viewer_figures(thin_gaussians(g), ours.color, ours.alpha, cams, w, h)
            after = viewer_figures(baked, ours.color, ours.alpha, cams, w, h)
            row["figures"][f"{views} x{f}"] = {"before": vars(before), "after": vars(after)}
    print(
        f"{scene['name']}: baked {len(g):,} surfels in {report.seconds:.0f} s; " + report.summary(),
        flush=True,
    )
    return row


def write_document(args, config: BakeConfig, rows: list[dict]) -> None:
    document = {
        "settings": {
            "checkpoint": args.checkpoint,
            "capture_checkpoints": args.capture_checkpoint,
            "real_size": list(args.real_size),
            "views": {k: {"context": v[2], "target": v[3]} for k, v in REAL.items()},
            "bake": dataclasses.asdict(config),
            "torch": torch.__version__,
            "machine": platform.machine(),
            "threads": torch.get_num_threads(),
            "load_average": list(_load()),
        },
        "scenes": rows,
    }
    write_text(args.out, json.dumps(document, indent=1) + "\n")


def _load() -> tuple[float, ...]:
    try:
        import os

        return os.getloadavg()
    except OSError:
        return ()


def table(rows: list[dict]) -> str:
    lines = [
        "| scene | steps | factors | fitted views | views | alpha before | alpha after | PSNR before | PSNR after "
        "| bake time |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        bake = row["bake"]
        setting = f"{bake['steps']} | {','.join(map(str, bake['factors']))} | {row['fit_views']}"
        for key, fig in row["figures"].items():
            b, a = fig["before"], fig["after"]
            lines.append(
                f"| {row['scene']} | {setting} | {key} | {b['alpha']:.3f} | {a['alpha']:.3f} | {b['psnr']:.1f} dB | "
                f"{a['psnr']:.1f} dB | {row['seconds_bake']:.1f} s |"
            )
    return "\n".join(lines)


if __name__ == "__main__":
    main()
