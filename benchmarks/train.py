"""Training-step benchmark: seconds per optimizer step and peak memory, per model preset.

One step is exactly what `surfsplat.train.fit` runs (`training_step`): encoder forward, surfel
rendering of the target views, MSE loss (lambda_LPIPS = 0 so no VGG files are needed; the LPIPS
term adds one VGG16 pass per target view), backward, gradient clipping, AdamW. Each preset runs in
a fresh process so its peak memory is its own: peak resident memory on CPU, peak allocated CUDA
memory on a GPU. Defaults follow the issue: batch 1, 2 context views, 256x256, 4 target views
(the release's training sample).

    python benchmarks/train.py                                  # tiny small base large, CPU
    python benchmarks/train.py --presets tiny --size 64 --targets 2
    python benchmarks/train.py --presets tiny --render-backends torch cpu   # the compiled renderer's gain
    python benchmarks/train.py --device cuda --precisions bf16
    python benchmarks/train.py --presets tiny small --precisions fp32 bf16   # side by side (the default)

bf16 is autocast with float32 master weights and AdamW state (TrainConfig.precision).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from common import RESULTS
from surfsplat.render.types import BACKENDS


def measure(
    preset: str,
    size: int,
    targets: int,
    batch: int,
    repeats: int,
    device: str,
    precision: str,
    render_backend: str = "auto",
) -> dict:
    """Time `repeats` training steps after one warm-up step, in this process."""
    from torch.utils.data import default_collate

    from surfsplat.data.synthetic import SyntheticDataset, SyntheticDatasetConfig
    from surfsplat.evaluation import peak_memory
    from surfsplat.model.decoder import decoder_mode
    from surfsplat.render import resolve_backend
    from surfsplat.train import build_model, build_optimizer, train_preset
    from surfsplat.train.config import override
    from surfsplat.train.data import to_train_batch
    from surfsplat.train.loop import resolve_precision, training_step
    from surfsplat.train.losses import ImageLoss

    config = override(
        train_preset(preset),
        {
            "data.image_shape": [size, size],
            "data.num_target_views": targets,
            "loss.lpips_weight": 0.0,
            "batch_size": batch,
            "precision": precision,
            "device": device,
            "model.render_backend": render_backend,
        },
    )
    dev = torch.device("cuda" if device == "cuda" else "cpu")
    torch.manual_seed(0)
    model = build_model(config).to(dev).train()
    optimizer = build_optimizer(model, config)
    loss_fn = ImageLoss(config.loss).to(dev)
    amp = resolve_precision(config, dev)
    scaler = torch.amp.GradScaler(dev.type) if amp == torch.float16 else None
    dataset = SyntheticDataset(
        SyntheticDatasetConfig(length=batch, image_shape=(size, size), num_target_views=targets, supersample=1)
    )
    sample = to_train_batch(default_collate([dataset[i] for i in range(batch)]), list(range(batch))).to(dev)
    mode = decoder_mode(model.cfg.adapter)
    cascade = model.cfg.encoder.num_scales > 1

    def step() -> float:
        if dev.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        out = training_step(
            model,
            model,
            sample,
            loss_fn,
            optimizer,
            mode=mode,
            backend=render_backend,
            amp_dtype=amp,
            scaler=scaler,
            grad_clip=config.optim.grad_clip,
            cascade=cascade,
        )
        float(out.loss)  # waits for the GPU
        return time.perf_counter() - start

    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats()
    warmup = step()
    times = [step() for _ in range(repeats)]
    peak_bytes, memory_kind = peak_memory(dev)
    return {
        "preset": preset,
        "parameters": sum(p.numel() for p in model.parameters()),
        "image_size": size,
        "batch": batch,
        "context_views": 2,
        "target_views": targets,
        "cascade_renders": 1 + (model.cfg.encoder.num_scales - 1),
        "render_mode": mode,
        "render_backend": resolve_backend(render_backend, dev, None, sample.target.cameras()),
        "precision": str(amp).replace("torch.", "") if amp is not None else "fp32",
        "device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else platform.processor() or platform.machine(),
        "threads": torch.get_num_threads(),
        "load_average_1min": os.getloadavg()[0],  # other work on the machine inflates CPU timings
        "warmup_seconds": warmup,
        "step_seconds_median": statistics.median(times),
        "step_seconds_min": min(times),
        "steps_timed": repeats,
        "peak_memory_mb": peak_bytes / 2**20,
        "memory_kind": memory_kind,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["tiny", "small", "base", "large"])
    parser.add_argument("--size", type=int, default=256, help="image height and width")
    parser.add_argument("--targets", type=int, default=4, help="target views rendered per sample")
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3, help="timed steps after one warm-up step")
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--precisions", nargs="+", choices=("auto", "fp32", "bf16", "fp16"), default=["fp32", "bf16"])
    parser.add_argument(
        "--render-backends",
        nargs="+",
        choices=BACKENDS,
        default=["auto"],
        help="renderers to compare (auto: gsplat on CUDA, the compiled one on CPU)",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="CPU threads of torch and the compiled renderer (default: their own choice)",
    )
    parser.add_argument("--out", default=None, help="JSON path (default benchmarks/results/train_<device>.json)")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:  # one preset and renderer, measured in this fresh process
        from surfsplat.train.loop import cpu_threads

        (preset,), (backend,), (precision,) = args.presets, args.render_backends, args.precisions
        with cpu_threads(args.threads or 0):  # torch's and the compiled renderer's; 0 keeps their defaults
            row = measure(preset, args.size, args.targets, args.batch, args.repeats, args.device, precision, backend)
        print(json.dumps(row))
        return

    rows = []
    for preset, backend, precision in itertools.product(args.presets, args.render_backends, args.precisions):
        cmd = [
            sys.executable,
            __file__,
            "--child",
            "--presets",
            preset,
            "--render-backends",
            backend,
            "--size",
            str(args.size),
            "--targets",
            str(args.targets),
            "--batch",
            str(args.batch),
            "--repeats",
            str(args.repeats),
            "--device",
            args.device,
            "--precisions",
            precision,
        ]
        if args.threads:
            cmd += ["--threads", str(args.threads)]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            lines = proc.stderr.strip().splitlines()
            rows.append(
                {
                    "preset": preset,
                    "render_backend": backend,
                    "precision": precision,
                    "error": lines[-1] if lines else f"exit {proc.returncode}",
                }
            )
        else:
            rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        r = rows[-1]
        if "error" in r:
            print(f"{preset:6s} {backend:>6s}  failed: {r['error']}", flush=True)
        else:
            print(
                f"{preset:6s} {r['render_backend']:>6s}  {r['parameters'] / 1e6:7.1f} M params  "
                f"step {r['step_seconds_median']:8.3f} s (min {r['step_seconds_min']:.3f})  "
                f"peak {r['peak_memory_mb']:9.0f} MB  {r['precision']}  load {r['load_average_1min']:.1f}",
                flush=True,
            )

    out = Path(args.out) if args.out else RESULTS / f"train_{args.device}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    report = {
        "benchmark": "training step (fit's training_step: forward, render, MSE, backward, clip, AdamW)",
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "settings": vars(args) | {"child": None},
        "results": rows,
    }
    out.write_text(json.dumps(report, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
