"""bf16 speed/accuracy trade: which encoder parts stay float32 under autocast, and what each costs.

    python benchmarks/precision.py --golden GOLDEN_DIR            # the released small model's golden case
    python benchmarks/precision.py --golden GOLDEN_DIR --repeats 5 --configs default all-bf16

GOLDEN_DIR holds `formula_weights.json` and `case_identity.safetensors` (the golden fixture of the
released small model, 2 x 256 x 256). Every configuration runs the same model on the same inputs,
with one warm-up call; the timed calls of the configurations are interleaved (repeat 1 of each, then
repeat 2 of each, ...) so that a shared machine's load falls on all of them alike. Errors are the
relative L2 distance ||ours - golden|| / ||golden|| to the release's float32 outputs. Wall time and
the process's CPU time are both recorded: on a loaded machine the CPU time is the steadier measure
of the work done. Results go to
benchmarks/results/precision_<device>.json and a table is printed.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

from common import RESULTS, write_results

# name -> encoder parts kept in float32 under bf16 autocast (None: no autocast, the float32 model)
CONFIGS: dict[str, tuple[str, ...] | None] = {
    "fp32": None,
    "all-bf16": (),
    "cnn": ("cnn",),
    "depth_regressor": ("depth_regressor",),
    "default": ("cnn", "depth_regressor"),
    "default+transformer": ("cnn", "transformer", "depth_regressor"),
    "default+transformer+heads": (
        "cnn",
        "transformer",
        "depth_regressor",
        "depth_upsampler",
        "feature_upsampler",
        "gaussian_head",
    ),
}
OUTPUTS = ("depths", "gaussians.means", "gaussians.opacities", "gaussians.harmonics")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--golden", type=Path, required=True, help="folder of the golden fixture")
    parser.add_argument("--configs", nargs="+", choices=sorted(CONFIGS), default=list(CONFIGS))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()

    import torch
    from safetensors.torch import load_file

    from surfsplat import Cameras
    from surfsplat.model import SurfSplat, load_release_weights
    from surfsplat.model.encoder.encoder import DEFAULT_FLOAT32_PARTS
    from surfsplat.model.formula_weights import formula_state_dict

    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    weights = formula_state_dict(args.golden / "formula_weights.json")
    with tempfile.TemporaryDirectory() as tmp:
        ckpt = Path(tmp) / "release.ckpt"
        state = {f"encoder.{k}": torch.from_numpy(v) for k, v in weights.items()}
        torch.save({"state_dict": state, "global_step": 0, "epoch": 0}, ckpt)
        model = SurfSplat.from_preset("small", adapter="official").eval()
        load_release_weights(model, ckpt)
    model = model.to(device)
    case = load_file(str(args.golden / "case_identity.safetensors"))
    _, v, _, h, w = case["context.image"].shape
    cameras = Cameras.from_normalized(case["context.extrinsics"][0], case["context.intrinsics"][0], w, h).to(device)
    inputs = (
        case["context.image"].to(device),
        cameras,
        case["context.near"].to(device),
        case["context.far"].to(device),
    )

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize()

    def forward(parts: tuple[str, ...] | None):
        model.encoder.keep_float32(parts or ())
        with torch.no_grad(), torch.autocast(device.type, dtype=torch.bfloat16, enabled=parts is not None):
            return model(*inputs)

    def rel(ours: torch.Tensor, golden: torch.Tensor) -> float:
        return float((ours.double().cpu() - golden.double()).norm() / golden.double().norm())

    rows = {}
    for name in args.configs:
        pred = forward(CONFIGS[name])  # warm-up, and the outputs the errors are measured on
        g = pred.gaussians
        ours = {"depths": pred.depths, "gaussians.means": g.means, "gaussians.opacities": g.opacities}
        ours["gaussians.harmonics"] = g.sh
        rows[name] = {
            "float32_parts": None if CONFIGS[name] is None else list(CONFIGS[name]),
            "errors": {k: rel(ours[k], case[f"outputs.{k}"]) for k in OUTPUTS},
            "seconds": [],
            "cpu_seconds": [],
        }
    for _ in range(args.repeats):
        for name in args.configs:
            sync()
            start, cpu = time.perf_counter(), time.process_time()
            forward(CONFIGS[name])
            sync()
            rows[name]["seconds"].append(time.perf_counter() - start)
            rows[name]["cpu_seconds"].append(time.process_time() - cpu)
    model.encoder.keep_float32(DEFAULT_FLOAT32_PARTS)
    base = statistics.median(rows["fp32"]["seconds"]) if "fp32" in rows else None
    cpu_base = statistics.median(rows["fp32"]["cpu_seconds"]) if "fp32" in rows else None
    for row in rows.values():
        row["median_s"] = statistics.median(row["seconds"])
        row["vs_fp32"] = row["median_s"] / base if base else None
        row["median_cpu_s"] = statistics.median(row["cpu_seconds"])
        row["cpu_vs_fp32"] = row["median_cpu_s"] / cpu_base if cpu_base else None

    report = {
        "benchmark": "bf16 autocast: float32 parts vs time and error to the release's float32 outputs",
        "device": torch.cuda.get_device_name() if device.type == "cuda" else "cpu",
        "threads": args.threads,
        "load_average": os.getloadavg(),
        "torch": torch.__version__,
        "results": rows,
    }
    out = write_results(RESULTS / f"precision_{device.type}.json", report)
    short = {"depths": "depths", "gaussians.means": "means", "gaussians.opacities": "opacities"}
    short["gaussians.harmonics"] = "SH"
    head = f"{'configuration':<28} {'s (median)':>10} {'x fp32':>7} {'CPU s':>7} {'x fp32':>7} "
    print(head + " ".join(f"{s:>10}" for s in short.values()))
    for name, row in rows.items():
        ratio = "-" if row["vs_fp32"] is None else f"{row['vs_fp32']:.2f}"
        cpu_ratio = "-" if row["cpu_vs_fp32"] is None else f"{row['cpu_vs_fp32']:.2f}"
        errors = " ".join(f"{row['errors'][k]:>10.1e}" for k in short)
        print(f"{name:<28} {row['median_s']:>10.3f} {ratio:>7} {row['median_cpu_s']:>7.2f} {cpu_ratio:>7} {errors}")
    print(f"(load average {os.getloadavg()[0]:.2f} at the end; written to {out})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
