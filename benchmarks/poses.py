"""Camera estimation benchmark: seconds and peak memory of `estimate_cameras` for 2, 4 and 8 photos.

    python benchmarks/poses.py                       # 2, 4, 8 views at 400x300 and 1000x750
    python benchmarks/poses.py --views 8 --sizes 1000 --repeats 3 --min-idle 0.9

The photos are the procedural room (seed 0) ray-cast natively at each size (not upscaled) from
cameras 5.7 degrees apart on an arc around its middle (8 views span 40 degrees), so the rotation
error against the exact cameras is reported beside the time. Focal length unknown (the prior, refined by bundle adjustment) for 3+
views, given for two (the two-view path). Each measurement runs in a fresh process, so its peak
resident memory is its own; pycolmap uses every core (`--threads` to change). Results go to
benchmarks/results/poses.json and a table is printed. Goal: 8 photos at 1000 px in 10 s on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import machine, text_table, write_results
from encoder import idle_fraction, wait_for_idle  # the benchmarks' shared idle gauge (same folder)

SIZES = {400: (400, 300), 1000: (1000, 750)}


def orbit(n: int, width: int, height: int, step_deg: float = 40.0 / 7, fov_deg: float = 60.0):
    import torch

    from surfsplat.data.synthetic.scene import WORLD_DOWN
    from surfsplat.geometry.cameras import Cameras, look_at

    target = torch.tensor([0.0, 0.0, 0.6], dtype=torch.float64)
    spread = step_deg * (n - 1)
    angles = torch.deg2rad(torch.linspace(-spread / 2, spread / 2, n, dtype=torch.float64))
    eyes = torch.stack([2 * torch.cos(angles), 2 * torch.sin(angles), torch.full_like(angles, 1.4)], -1)
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Cameras(look_at(eyes, target.expand(n, 3), WORLD_DOWN), K.repeat(n, 1, 1))


def write_views(folder: Path, n: int, width: int, height: int) -> list[Path]:
    import numpy as np
    from PIL import Image

    from surfsplat.data.synthetic.render import render_synthetic
    from surfsplat.data.synthetic.scene import make_scene
    from surfsplat.geometry.cameras import Cameras

    cams = orbit(n, width, height)
    images = render_synthetic(make_scene(0), Cameras(cams.c2w.float(), cams.K.float()), width, height).image
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, image in enumerate(images):
        paths.append(folder / f"view{i}.png")
        Image.fromarray((image.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)).save(paths[-1])
    return paths


def run_one(folder: Path, n: int, size: int, repeats: int, threads: int, min_idle: float, timeout: float) -> dict:
    from surfsplat.evaluation import peak_rss_bytes
    from surfsplat.poses import PoseConfig, estimate_cameras, relative_pose_errors

    width, height = SIZES[size]
    truth = orbit(n, width, height)
    paths = sorted(folder.glob("view*.png"))
    focal = float(truth.K[0, 0, 0]) if n == 2 else None
    seconds, cpu, idle = [], [], []
    for _ in range(repeats):
        idle.append(wait_for_idle(min_idle, timeout) if min_idle > 0 else idle_fraction(0.2))
        start, start_cpu = time.perf_counter(), _cpu_seconds()
        cams, summary = estimate_cameras(paths, focal=focal, config=PoseConfig(threads=threads))
        seconds.append(time.perf_counter() - start)
        cpu.append(_cpu_seconds() - start_cpu)
    rot, trans = relative_pose_errors(cams.cameras.c2w, truth.c2w)
    return {
        "views": n,
        "width": width,
        "height": height,
        "extraction_size": list(summary.extraction_size),
        "threads": threads,
        "method": summary.method,
        "seconds": seconds,
        "median_s": statistics.median(seconds),
        "cpu_s": cpu,  # user + system time of every thread: the work, whatever the machine's load
        "stages_s": summary.timings,
        "idle_before": idle,
        "peak_mb": peak_rss_bytes() / 2**20,
        "registered": len(summary.registered),
        "points": summary.points,
        "max_rotation_error_deg": float(rot.max()),
        "max_translation_error_deg": float(trans.max()),
        "focal_error": abs(summary.focal / float(truth.K[0, 0, 0]) - 1),
    }


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", nargs="+", type=int, default=[2, 4, 8])
    parser.add_argument("--sizes", nargs="+", type=int, choices=sorted(SIZES), default=sorted(SIZES))
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--threads", type=int, default=-1, help="pycolmap threads (-1: every core)")
    parser.add_argument("--min-idle", type=float, default=0.0, help="wait for this idle CPU share before each run")
    parser.add_argument("--idle-timeout", type=float, default=1800.0)
    parser.add_argument("--single", nargs=3, help=argparse.SUPPRESS)  # internal: FOLDER VIEWS SIZE -> JSON
    args = parser.parse_args()

    if args.single:
        folder, n, size = Path(args.single[0]), int(args.single[1]), int(args.single[2])
        result = run_one(folder, n, size, args.repeats, args.threads, args.min_idle, args.idle_timeout)
        print(json.dumps(result))
        return 0

    rows = []
    with tempfile.TemporaryDirectory(prefix="poses-bench-") as tmp:
        for size in args.sizes:
            for n in args.views:
                folder = Path(tmp) / f"{size}_{n}"
                write_views(folder, n, *SIZES[size])
                cmd = [sys.executable, __file__, "--single", str(folder), str(n), str(size)]
                cmd += ["--repeats", str(args.repeats), "--threads", str(args.threads)]
                cmd += ["--min-idle", str(args.min_idle), "--idle-timeout", str(args.idle_timeout)]
                done = subprocess.run(cmd, capture_output=True, text=True)
                if done.returncode != 0:
                    print(f"{n} views at {size}: failed\n{done.stderr.strip()[-2000:]}", file=sys.stderr)
                    return 1
                rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
                print(f"{n} views at {SIZES[size]}: {rows[-1]['median_s']:.2f} s", file=sys.stderr)

    import pycolmap

    report = {
        "benchmark": "camera estimation (surfsplat.poses.estimate_cameras)",
        "images": "procedural room, seed 0, ray-cast natively at each size, views 5.7 degrees apart on an arc",
        "machine": {**machine(), "pycolmap": pycolmap.__version__},
        "results": rows,
    }
    out = write_results("poses", report)

    headers = ["views", "size", "SIFT at", "method", "seconds (median, min)", "CPU s", "extract/match/solve s"]
    headers += ["peak MB", "points", "rot err deg", "idle before"]
    table = [
        [
            r["views"],
            f"{r['width']}x{r['height']}",
            "x".join(map(str, r["extraction_size"])),
            r["method"],
            f"{r['median_s']:.2f}, {min(r['seconds']):.2f}",
            round(statistics.median(r["cpu_s"]), 1),
            "/".join(f"{r['stages_s'][k]:.1f}" for k in ("extract", "match", "reconstruct")),
            round(r["peak_mb"]),
            r["points"],
            round(r["max_rotation_error_deg"], 3),
            ",".join("-" if x is None else f"{x:.2f}" for x in r["idle_before"]),
        ]
        for r in rows
    ]
    print(text_table(headers, table))
    print(f"(load average at the end {os.getloadavg()[0]:.2f}; written to {out})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
