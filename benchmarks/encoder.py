"""Encoder benchmark: forward time and peak memory per preset.

    python benchmarks/encoder.py                      # tiny, small, base, large at 2 x 256 x 256 on CPU
    python benchmarks/encoder.py --device cuda        # on a GPU
    python benchmarks/encoder.py --presets small --views 4 --size 512
    python benchmarks/encoder.py --presets small --min-idle 0.9   # on a shared machine
    python benchmarks/encoder.py --presets small --precisions fp32 bf16   # bf16 autocast beside fp32

On a shared machine, `--min-idle` waits before every timed call until the CPUs were at least that
idle over the last second (Linux /proc/stat); each sample records the idle fraction it started at.

Each preset and precision runs in a fresh subprocess so that its peak resident memory (CPU) or
peak allocated memory (CUDA) is its own. bf16 is `torch.autocast(device, dtype=torch.bfloat16)`
around the call (surfsplat.utils.precision); the table gives its time as a fraction of fp32 without levers. The timed call is one full `SurfSplat` forward (encoder + official
adapter, as the release's encoder call) under `no_grad` in eval mode, after one warm-up call; the
encoder alone is timed as well. Results go to benchmarks/results/encoder_<device>.json and a table
is printed.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

from common import machine, text_table, write_results

LEVERS = {  # --levers: the standard CPU levers, each alone and together, against today's no_grad forward
    "none": (),
    "inference_mode": ("inference_mode",),
    "channels_last": ("channels_last",),
    "compile": ("compile",),
    "inference_mode+channels_last": ("inference_mode", "channels_last"),
    "all": ("inference_mode", "channels_last", "compile"),
}


def idle_fraction(seconds: float = 1.0) -> float | None:
    """Share of CPU time spent idle over the next `seconds` (None where /proc/stat is absent)."""

    def read() -> tuple[int, int]:
        with open("/proc/stat") as f:
            ticks = [int(x) for x in f.readline().split()[1:]]
        return ticks[3] + ticks[4], sum(ticks)  # idle + iowait, total

    try:
        idle0, total0 = read()
        time.sleep(seconds)
        idle1, total1 = read()
    except OSError:
        return None
    return (idle1 - idle0) / max(total1 - total0, 1)


def wait_for_idle(min_idle: float, timeout: float) -> float | None:
    """Block until the machine is at least `min_idle` idle (or `timeout` seconds passed)."""
    deadline = time.time() + timeout
    while True:
        idle = idle_fraction()
        if idle is None or idle >= min_idle or time.time() > deadline:
            return idle


def run_one(
    preset: str,
    views: int,
    size: int,
    device: str,
    repeats: int,
    threads: int,
    min_idle: float,
    idle_timeout: float,
    precision: str = "fp32",
    lever: str = "none",
) -> dict:
    import torch

    from surfsplat import Cameras
    from surfsplat.evaluation import peak_memory
    from surfsplat.model import SurfSplat
    from surfsplat.model.loading import prepare_for_inference
    from surfsplat.utils.precision import autocast

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    model = SurfSplat.from_preset(preset, adapter="official").eval().to(device)
    levers = set(LEVERS[lever])
    prepare_for_inference(model, channels_last="channels_last" in levers, compile="compile" in levers)
    grad_off = torch.inference_mode if "inference_mode" in levers else torch.no_grad
    images = torch.rand(1, views, 3, size, size, device=device)
    K = torch.tensor([[0.9 * size, 0, size / 2], [0, 0.9 * size, size / 2], [0, 0, 1.0]]).repeat(views, 1, 1)
    c2w = torch.eye(4).repeat(views, 1, 1)
    c2w[:, 0, 3] = 0.15 * torch.arange(views)
    cameras = Cameras(c2w, K).to(device)
    K_b, c2w_b = cameras.K.view(1, views, 3, 3), cameras.c2w.view(1, views, 4, 4)
    near = torch.full((1, views), 0.5, device=device)
    far = torch.full((1, views), 100.0, device=device)

    def sync() -> None:
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    full, encoder_only, idle = [], [], []
    with grad_off(), autocast(precision, device) as ran:
        t = time.perf_counter()
        reference = model(images, cameras, near, far).depths  # warm-up: allocator, kernel selection, compilation
        sync()
        first_call = time.perf_counter() - t
        if device.startswith("cuda"):
            torch.cuda.reset_peak_memory_stats()
        for _ in range(repeats):
            idle.append(wait_for_idle(min_idle, idle_timeout) if min_idle > 0 else idle_fraction(0.2))
            t = time.perf_counter()
            model(images, cameras, near, far)
            sync()
            full.append(time.perf_counter() - t)
            t = time.perf_counter()
            model.encoder(images, K_b, c2w_b, near, far)
            sync()
            encoder_only.append(time.perf_counter() - t)
    peak_bytes, peak_kind = peak_memory(torch.device(device))
    return {
        "preset": preset,
        "device": device,
        "views": views,
        "size": size,
        "threads": threads,
        "precision": ran,
        "lever": lever,
        "first_call_s": first_call,
        "depth_checksum": float(reference.double().sum()),
        "parameters": sum(p.numel() for p in model.parameters()),
        "forward_s": full,
        "forward_median_s": statistics.median(full),
        "encoder_forward_s": encoder_only,
        "encoder_median_s": statistics.median(encoder_only),
        "idle_before": idle,
        "peak_mb": peak_bytes / 2**20,
        "peak_kind": peak_kind,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["tiny", "small", "base", "large"])
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--precisions", nargs="+", choices=("fp32", "bf16", "auto"), default=["fp32", "bf16"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--min-idle", type=float, default=0.0, help="wait for this idle CPU share before each call")
    parser.add_argument("--idle-timeout", type=float, default=1800.0, help="longest wait for --min-idle, seconds")
    parser.add_argument(
        "--levers",
        nargs="+",
        choices=tuple(LEVERS),
        default=["none"],
        help="inference_mode, channels_last, torch.compile (inductor), all: each measured beside none",
    )
    parser.add_argument("--single", help=argparse.SUPPRESS)  # internal: run one preset, print JSON
    args = parser.parse_args()

    if args.single:
        result = run_one(
            args.single,
            args.views,
            args.size,
            args.device,
            args.repeats,
            args.threads,
            args.min_idle,
            args.idle_timeout,
            args.precisions[0],
            args.levers[0],
        )
        print(json.dumps(result))
        return 0

    rows = []
    for preset, precision, lever in [(p, q, v) for p in args.presets for q in args.precisions for v in args.levers]:
        cmd = [sys.executable, __file__, "--single", preset, "--views", str(args.views), "--size", str(args.size)]
        cmd += ["--device", args.device, "--repeats", str(args.repeats), "--threads", str(args.threads)]
        cmd += ["--min-idle", str(args.min_idle), "--idle-timeout", str(args.idle_timeout)]
        cmd += ["--precisions", precision, "--levers", lever]
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0:
            print(f"{preset} {precision} {lever}: failed\n{done.stderr.strip()}", file=sys.stderr)
            return 1
        rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    fp32 = {r["preset"]: r["forward_median_s"] for r in rows if r["precision"] == "fp32" and r["lever"] == "none"}
    for r in rows:
        r["forward_vs_fp32"] = r["forward_median_s"] / fp32[r["preset"]] if r["preset"] in fp32 else None

    import torch

    report = {
        "benchmark": "encoder forward",
        "machine": {
            **machine(),
            "cuda_device": torch.cuda.get_device_name() if args.device.startswith("cuda") else None,
        },
        "results": rows,
    }
    out = write_results(f"encoder_{args.device.split(':')[0]}", report)

    headers = ["preset", "precision", "lever", "first call s", "params", "views", "size", "forward s (median, min)"]
    headers += ["x base", "encoder s", "peak MB", "idle before"]
    table = [
        [
            r["preset"],
            r["precision"],
            r["lever"],
            round(r["first_call_s"], 2),
            r["parameters"],
            r["views"],
            r["size"],
            f"{r['forward_median_s']:.3f}, {min(r['forward_s']):.3f}",
            "-" if r["forward_vs_fp32"] is None else round(r["forward_vs_fp32"], 2),
            round(r["encoder_median_s"], 3),
            round(r["peak_mb"]),
            ",".join("-" if x is None else f"{x:.2f}" for x in r["idle_before"]),
        ]
        for r in rows
    ]
    print(text_table(headers, table))
    print(f"({rows[0]['peak_kind']}; load average at the end {os.getloadavg()[0]:.2f}; written to {out})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
