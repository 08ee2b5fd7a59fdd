"""Host synchronisations of one training step: where the host waits for the device, and how often.

    python benchmarks/host_syncs.py                       # stand-in device on CPU (no GPU needed)
    python benchmarks/host_syncs.py --device cuda         # the same step on a GPU
    python benchmarks/host_syncs.py --adapter official --targets 4 --out syncs.json

One step is `surfsplat.train.loop.training_step` on the tiny preset: batch 1, 2 context views and
TARGETS target views of SIZE^2 procedural rooms, MSE + 0.05 LPIPS (random VGG weights: only the
structure of the step matters here), the torch renderer (what a CUDA run without gsplat uses),
backward, clipping, AdamW. Without a GPU the step runs on the stand-in device of
surfsplat.testing.standin_device: tensors that report a non-CPU device and keep their values on the CPU,
so every op that reads device values on the host is seen exactly as on CUDA. With --device cuda a
dispatch mode records the same ops on the real device.

Recorded: scalar reads (.item(), bool(), float(), f-strings: aten._local_scalar_dense), copies to
the CPU (.cpu(), .tolist()), ops with value-dependent output sizes (nonzero, boolean-mask indexing,
masked_select, unique, bincount, repeat_interleave without output_size), equal/allclose, linalg's
error checks (torch.linalg.inv reads its info tensor on the host), and blocking copies from the CPU
(.to(device), torch.tensor(data, device=...): CUDA synchronises the stream after them). Each is
attributed to the innermost line of surfsplat on the Python stack; the table counts host waits per
line (bincount and repeat_interleave wait twice). The JSON (--out) holds the rows and, per sync, the
op and up to four surfsplat frames. With --device cuda the step runs a second time under
torch.cuda.set_sync_debug_mode("warn") and the JSON's "cuda_sync_debug" compares PyTorch's own count
with the list, line by line.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from collections import Counter
from pathlib import Path

import torch

from surfsplat.testing.standin_device import HostSyncRecorder, StandinDevice

REPO = Path(__file__).resolve().parents[1]


def random_lpips():
    """LPIPS-VGG with random weights (the structure of the loss, no weight files needed)."""
    from surfsplat.metrics.lpips import Lpips, lin_shapes, vgg_shapes

    g = torch.Generator().manual_seed(0)
    vgg = {k: 0.1 * torch.randn(s, generator=g) for k, s in vgg_shapes().items()}
    lin = {k: torch.rand(s, generator=g) for k, s in lin_shapes().items()}
    return Lpips(vgg, lin)


def build_step(
    preset: str = "tiny",
    adapter: str = "paper",
    size: int = 32,
    targets: int = 1,
    lpips: bool = True,
    overrides: dict | None = None,
    highres_factor: int = 0,
):
    """(model, make_optimizer, loss, batch, config) of one training step, all on the CPU.

    `overrides`: further TrainConfig fields (e.g. {"loss.depth_weight": 0.1}); `highres_factor`:
    native high-resolution truth for the targets (needed by loss.highres_weight / closure_weight).
    """
    from torch.utils.data import default_collate

    from surfsplat.data.synthetic import SyntheticDataset, SyntheticDatasetConfig
    from surfsplat.train import build_model, build_optimizer, train_preset
    from surfsplat.train.config import override
    from surfsplat.train.data import to_train_batch
    from surfsplat.train.losses import ImageLoss

    settings = {
        "data.image_shape": [size, size],
        "data.num_target_views": targets,
        "loss.lpips_weight": 0.05 if lpips else 0.0,
        "batch_size": 1,
        "model.adapter.mode": adapter,
        "data.highres_factor": highres_factor,
        "data.highres_crop": size // 2 if highres_factor else 0,
    }
    config = override(train_preset(preset), {**settings, **(overrides or {})})
    torch.manual_seed(0)
    model = build_model(config).train()
    loss_fn = ImageLoss(config.loss, lpips=random_lpips() if lpips else None)
    data = SyntheticDatasetConfig(
        length=1,
        image_shape=(size, size),
        num_target_views=targets,
        supersample=1,
        highres_factor=config.data.highres_factor,
        highres_crop=config.data.highres_crop,
    )
    batch = to_train_batch(default_collate([SyntheticDataset(data)[0]]), [0])
    return model, build_optimizer, loss_fn, batch, config


def run_step(model, make_optimizer, loss_fn, batch, config, amp_dtype=None):
    """One `training_step` as `fit` runs it (cascade supervision for two-scale presets)."""
    from surfsplat.model.decoder import decoder_mode
    from surfsplat.train.cascade import num_intermediate_depths
    from surfsplat.train.loop import training_step

    return training_step(
        model,
        model,
        batch,
        loss_fn,
        make_optimizer(model, config),
        mode=decoder_mode(model.cfg.adapter),
        backend="torch",
        amp_dtype=amp_dtype,
        grad_clip=config.optim.grad_clip,
        cascade=num_intermediate_depths(model) > 0,
    )


def measure(
    preset: str = "tiny", adapter: str = "paper", size: int = 32, targets: int = 1, device: str = "standin"
) -> dict:
    """The host synchronisations of one training step on `device` ("standin" or e.g. "cuda")."""
    model, make_optimizer, loss_fn, batch, config = build_step(preset, adapter, size, targets)
    start = time.perf_counter()
    if device == "standin":
        with StandinDevice() as recorder:
            on = recorder.device
            model, loss_fn, batch = model.to(on), loss_fn.to(on), batch.to(on)
            recorder.syncs.clear()  # moving the inputs is not part of the step
            out = run_step(model, make_optimizer, loss_fn, batch, config)
            loss = out.loss.detach().elem.item()
    else:
        on = torch.device(device)
        model, loss_fn, batch = model.to(on), loss_fn.to(on), batch.to(on)
        recorder = HostSyncRecorder()
        with recorder:
            out = run_step(model, make_optimizer, loss_fn, batch, config)
        loss = float(out.loss.detach())
    seconds = time.perf_counter() - start
    counts: Counter = recorder.sync_counts()
    rows = [{"where": where, "kind": kind, "waits": n} for (where, kind), n in sorted(counts.items())]
    report = {
        "settings": {"preset": preset, "adapter": adapter, "size": size, "targets": targets, "device": device},
        "total": sum(counts.values()),
        "rows": rows,
        "syncs": [{"op": s.op, "kind": s.kind, "waits": s.waits, "stack": s.stack} for s in recorder.syncs],
        "loss": loss,
        "seconds": seconds,
    }
    if device != "standin" and on.type == "cuda":
        report["cuda_sync_debug"] = cuda_sync_debug(report, preset, adapter, size, targets, on)
    return report


def cuda_sync_debug(report: dict, preset: str, adapter: str, size: int, targets: int, device: torch.device) -> dict:
    """PyTorch's own count, as an independent check of the list: the same step again (same seed and
    batch) under torch.cuda.set_sync_debug_mode("warn"), its warnings counted per Python line.

    A warning names the line that called into torch, so syncs reached through torch's Python code
    (backward, optimizer) are named by torch's files; "differences" lists the lines where the two
    counts differ ({line: [recorded, cuda]})."""
    model, make_optimizer, loss_fn, batch, config = build_step(preset, adapter, size, targets)
    model, loss_fn, batch = model.to(device), loss_fn.to(device), batch.to(device)
    torch.cuda.synchronize(device)
    previous = torch.cuda.get_sync_debug_mode()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            run_step(model, make_optimizer, loss_fn, batch, config)
        finally:
            torch.cuda.set_sync_debug_mode(previous)
    package = REPO / "src" / "surfsplat"
    lines: Counter = Counter()
    for w in caught:
        if "synchroniz" in str(w.message):
            path = Path(w.filename).resolve()
            name = str(path.relative_to(package)) if package in path.parents else f"{path.parent.name}/{path.name}"
            lines[f"{name}:{w.lineno}"] += 1
    recorded: Counter = Counter()
    for row in report["rows"]:
        recorded[row["where"].split(" ")[0]] += row["waits"]
    differences = {k: [recorded[k], lines[k]] for k in sorted(set(lines) | set(recorded)) if recorded[k] != lines[k]}
    return {"total": sum(lines.values()), "by_line": dict(sorted(lines.items())), "differences": differences}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="standin", help="standin (CPU, no GPU needed) or a device, e.g. cuda")
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--adapter", default="paper", choices=("paper", "official"))
    parser.add_argument("--size", type=int, default=32)
    parser.add_argument("--targets", type=int, default=1)
    parser.add_argument("--out", type=Path, default=None, help="JSON report (default: none)")
    args = parser.parse_args()
    report = measure(args.preset, args.adapter, args.size, args.targets, args.device)
    width = max(len(r["where"]) for r in report["rows"]) if report["rows"] else 10
    print(f"{'waits':>5}  {'where':<{width}}  kind")
    for r in report["rows"]:
        print(f"{r['waits']:>5}  {r['where']:<{width}}  {r['kind']}")
    print(f"{report['total']:>5}  total (one step, {report['seconds']:.1f} s, loss {report['loss']:.4f})")
    if "cuda_sync_debug" in report:
        check = report["cuda_sync_debug"]
        print(f"torch.cuda.set_sync_debug_mode: {check['total']} synchronising calls in the same step")
        for line, (ours, theirs) in check["differences"].items():
            print(f"  differs at {line}: recorded {ours}, cuda {theirs}")
    if args.out is not None:
        from common import write_results  # lazily: the tests load this file without the benchmarks folder on the path

        write_results(args.out, report)
        print(f"written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
