"""What the benchmarks share: where results go, the machine they ran on, tables, and the real
captures (DTU scan 24, LLFF fern) they measure on.

Each benchmark is a script (`python benchmarks/NAME.py`); Python puts this folder first on its
path, so `from common import ...` needs no path edit.
"""

from __future__ import annotations

import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).resolve().parent / "results"
SHARED_DATA = ROOT.parent / "shared" / "data"  # the full sample captures, where they sit beside the repository
FIXTURE_DATA = ROOT / "tests" / "data"  # their reduced copies in the repository

# The real captures the compaction and bake figures are measured on: name -> (folder, image folder,
# context views, target views). DTU's views follow the community's scan evaluation index (context
# 33 and 31); LLFF's are neighbours along the capture.
REAL = {
    "fern": ("llff_fern", "images_8", [4, 10], [6, 7, 8]),
    "dtu_scan24": ("dtu_scan24", "images_4", [33, 31], [32, 24, 23]),
}


def sample_data(path: Path | None = None) -> Path:
    """The folder holding the real captures: `path`, else the full samples, else the repository's copies."""
    if path is not None:
        return path
    return SHARED_DATA if SHARED_DATA.is_dir() else FIXTURE_DATA


def machine() -> dict:
    """What ran the benchmark, for its JSON: wall times mean little without the machine and its load."""
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "load_average": os.getloadavg() if hasattr(os, "getloadavg") else None,
    }


def write_results(target: str | Path, document: dict) -> Path:
    """`document` as indented JSON at `target`: a path, or a bare name for `RESULTS/name.json`;
    returns the path written."""
    path = Path(target)
    if isinstance(target, str) and path.parent == Path("."):
        path = RESULTS / (target if target.endswith(".json") else f"{target}.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(document, indent=1) + "\n")
    return path


def text_table(headers: list[str], rows: list[list[object]]) -> str:
    """A plain-text table: columns as wide as their widest cell, numbers right-aligned."""
    cells = [[str(h) for h in headers]] + [[_cell(v) for v in row] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    numeric = [all(isinstance(row[i], (int, float)) for row in rows) for i in range(len(headers))]

    def line(row: list[str]) -> str:
        return "  ".join(c.rjust(w) if n else c.ljust(w) for c, w, n in zip(row, widths, numeric)).rstrip()

    return "\n".join([line(cells[0]), line(["-" * w for w in widths])] + [line(r) for r in cells[1:]])


def reconstruct_cli(images: list[str], cameras: Path, out: Path, flags: list[str]) -> dict:
    """`surfsplat reconstruct --images ... --cameras CAMERAS --out OUT FLAGS --device cpu` as a child process:
    its CPU seconds (user + system, from the operating system), wall seconds, peak memory, the held-out
    scores its reconstruction.json reports, and that file's working crop and lenses."""
    command = [
        sys.executable, "-m", "surfsplat", "reconstruct", "--images", *images, "--cameras", str(cameras),
        *flags, "--device", "cpu", "--out", str(out),
    ]  # fmt: skip
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    tick = time.perf_counter()
    run = subprocess.run(command, capture_output=True, text=True)
    wall = time.perf_counter() - tick
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if run.returncode:
        raise SystemExit(f"{cameras}: surfsplat reconstruct failed:\n{run.stderr[-3000:]}")
    summary = json.loads((out / "reconstruction.json").read_text())
    capture = summary.get("capture", {})
    held = capture.get("held_out", {})
    return {
        "command": " ".join(command[1:]),
        "cpu_seconds": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
        "wall_seconds": wall,
        "peak_rss_mb": after.ru_maxrss / 1024,
        "load_average_after": os.getloadavg() if hasattr(os, "getloadavg") else None,
        "held_out_psnr": held.get("mean_psnr"),
        "held_out_psnr_before": (held.get("before_optimization") or {}).get("mean_psnr"),
        "held_out": held,
        "size": summary.get("size"),
        "working_crop": summary.get("working_crop"),
        "lenses": summary.get("lenses"),
        "antialiased": summary.get("antialiased", False),
        "held_out_zoom": held.get("zoom"),
        "seconds": summary.get("seconds"),
        "optimize": summary.get("optimize"),
        "stdout_tail": run.stdout[-2000:],
    }


def _cell(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return "" if value is None else str(value)
