"""HRRC of the same reconstructions in fp32 and bf16: PSNR / SSIM per render scale, side by side.

    python benchmarks/hrrc_precision.py                          # shipped tiny-synthetic, 6 held-out rooms
    python benchmarks/hrrc_precision.py --checkpoint runs/x/checkpoints/step-00001000 --rooms 12

The held-out procedural rooms are the demo's (`surfsplat demo`: same seed, context views at the
ends of each camera path, targets between them); each is reconstructed with the forward pass in
fp32 and under bf16 autocast (`EvalConfig.precision`), rendered in float32 at x1, x2 and x4, and
scored against bicubic-upsampled truth. Writes benchmarks/results/hrrc_precision.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
from pathlib import Path

from common import RESULTS, write_results


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", default="tiny-synthetic", help="weights name or checkpoint path")
    parser.add_argument("--rooms", type=int, default=6, help="held-out procedural rooms")
    parser.add_argument("--size", type=int, default=64, help="image size (the shipped model's is 64)")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()

    import torch

    from surfsplat.data.eval_index import EvaluationIndex
    from surfsplat.demo import DemoConfig, write_eval_data
    from surfsplat.evaluation import EvalConfig, evaluate, iter_index_samples
    from surfsplat.metrics.lpips import try_load_lpips
    from surfsplat.model.loading import ModelSpec, load_model

    torch.set_num_threads(args.threads)
    demo = dataclasses.replace(DemoConfig(), eval_scenes=args.rooms, image_size=args.size)
    model, name = load_model(ModelSpec(args.checkpoint))
    lpips = try_load_lpips()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        index_path, chunks = write_eval_data(demo, Path(tmp))
        index = EvaluationIndex.load(index_path)
        for precision in ("fp32", "bf16"):
            samples = iter_index_samples([chunks], index, near=0.5, far=15.0)
            config = EvalConfig(factors=demo.factors, progress=False, precision=precision)
            results[precision] = evaluate(model, samples, config, lpips=lpips, name=name)
    rows = {p: {f"x{s}": r.report.mean[s] for s in demo.factors} for p, r in results.items()}
    delta = {
        f"x{s}": {m: rows["bf16"][f"x{s}"][m] - rows["fp32"][f"x{s}"][m] for m in ("psnr", "ssim")}
        for s in demo.factors
    }
    report = {
        "benchmark": "HRRC of one model's reconstructions, forward pass in fp32 vs bf16 (renders float32)",
        "model": name,
        "rooms": args.rooms,
        "size": args.size,
        "images_per_factor": results["fp32"].report.num_images,
        "precision_ran": {p: r.precision for p, r in results.items()},
        "metrics": rows,
        "bf16_minus_fp32": delta,
        "seconds_forward_mean": {p: r.seconds_forward for p, r in results.items()},
        "load_average": os.getloadavg(),
    }
    out = write_results(RESULTS / "hrrc_precision.json", report)
    print(f"{name}: {args.rooms} rooms, {report['images_per_factor']} target images per scale")
    print(f"{'scale':<6} {'fp32 PSNR':>10} {'bf16 PSNR':>10} {'dPSNR dB':>9} {'fp32 SSIM':>10} {'bf16 SSIM':>10}")
    for s in demo.factors:
        a, b = rows["fp32"][f"x{s}"], rows["bf16"][f"x{s}"]
        print(
            f"x{s:<5} {a['psnr']:>10.3f} {b['psnr']:>10.3f} {b['psnr'] - a['psnr']:>+9.4f} "
            f"{a['ssim']:>10.4f} {b['ssim']:>10.4f}"
        )
    print(f"(precision ran: {report['precision_ran']}; load average {os.getloadavg()[0]:.2f}; written to {out})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
