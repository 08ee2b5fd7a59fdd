"""Loss curves of the same training run in fp32 and bf16, plotted side by side.

    surfsplat train --preset tiny --steps 500 --precision fp32 --out runs/curve-fp32 --val-every 0 --log-every 5
    surfsplat train --preset tiny --steps 500 --precision bf16 --out runs/curve-bf16 --val-every 0 --log-every 5
    python benchmarks/precision_curve.py --runs fp32=runs/curve-fp32 bf16=runs/curve-bf16 --out docs/precision_curve

Reads each run's metrics.jsonl (same seed, data and schedule: only the precision differs) and writes
OUT.png (the logged MSE per step and its moving average, `pip install matplotlib`) and OUT.json: the
mean loss over windows of the run for each precision and their relative difference, beside the
step-to-step spread of the fp32 curve in the same windows (the noise the difference is read against).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path


def read_curve(run: Path) -> dict[int, float]:
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines() if line.strip()]
    return {r["step"]: r["loss/mse"] for r in rows if "loss/mse" in r}


def moving_average(values: list[float], width: int) -> list[float]:
    out = []
    for i in range(len(values)):
        window = values[max(0, i - width + 1) : i + 1]
        out.append(sum(window) / len(window))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", nargs=2, required=True, metavar="NAME=DIR", help="fp32=DIR bf16=DIR")
    parser.add_argument("--out", type=Path, required=True, help="output path without extension")
    parser.add_argument("--windows", type=int, default=5, help="windows of the run the means are taken over")
    args = parser.parse_args()
    runs = dict(item.split("=", 1) for item in args.runs)
    if set(runs) != {"fp32", "bf16"}:
        parser.error("--runs: expected fp32=DIR bf16=DIR")
    curves = {name: read_curve(Path(path)) for name, path in runs.items()}
    steps = sorted(set(curves["fp32"]) & set(curves["bf16"]))
    if len(steps) < 2 * args.windows:
        parser.error(f"the runs share only {len(steps)} logged steps")
    size = len(steps) // args.windows
    windows = []
    for w in range(args.windows):
        part = steps[w * size : (w + 1) * size] if w < args.windows - 1 else steps[w * size :]
        fp32 = [curves["fp32"][s] for s in part]
        bf16 = [curves["bf16"][s] for s in part]
        windows.append(
            {
                "steps": [part[0], part[-1]],
                "fp32_mean": statistics.mean(fp32),
                "bf16_mean": statistics.mean(bf16),
                "relative_difference": statistics.mean(bf16) / statistics.mean(fp32) - 1,
                # standard error of the fp32 window mean: the logged losses vary from sample to sample
                "fp32_standard_error_relative": statistics.stdev(fp32) / len(fp32) ** 0.5 / statistics.mean(fp32),
            }
        )
    summary = {"runs": runs, "logged_steps": len(steps), "last_step": steps[-1], "windows": windows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(summary, indent=1) + "\n")
    for w in windows:
        print(
            f"steps {w['steps'][0]:>4}-{w['steps'][1]:<4} fp32 {w['fp32_mean']:.5f}  bf16 {w['bf16_mean']:.5f}  "
            f"difference {w['relative_difference']:+.1%}  (fp32 standard error {w['fp32_standard_error_relative']:.1%})"
        )

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=120)
    for name, colour in (("fp32", "tab:blue"), ("bf16", "tab:orange")):
        values = [curves[name][s] for s in steps]
        ax.plot(steps, values, color=colour, alpha=0.25, linewidth=0.8)
        ax.plot(
            steps, moving_average(values, 10), color=colour, linewidth=1.8, label=f"{name} (moving average of 10 logs)"
        )
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("training MSE")
    ax.set_title("tiny preset, same seed and data: fp32 vs bf16 autocast")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(args.out.with_suffix(".png"))
    print(f"wrote {args.out.with_suffix('.png')} and {args.out.with_suffix('.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
