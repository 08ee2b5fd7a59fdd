"""GPU readiness: one short run that says whether surfsplat's GPU paths compute what the CPU ones do.

    python scripts/gpu_check.py --out gpu_check.json                     # CUDA; under 8 minutes on one H100
    python scripts/gpu_check.py --device cpu --quick --out check.json    # the same steps on CPU (tests run this)

Steps, each recorded in the JSON (with its seconds, or why it was skipped):
1. renderer: the torch backend on DEVICE against the compiled CPU renderer on the same surfels
   (131,072 from two 256^2 views; --quick: 2,048) at x1, x2 and x4: largest differences of colour,
   alpha and depth, how many colour values are more than 1e-4 off, and the relative L2 difference
   of the gradients of a fixed random loss with respect to means, quaternions, scales, opacities
   and SH (the means' error split by viewing angle). Times of both. The same in float64 on DEVICE,
   and, as the float32 control, the torch backend in float32 on the CPU.
2. gsplat: the same comparison for the gsplat backend when the package imports on a CUDA device
   (install its wheel first, e.g. `pip install gsplat`, or carry a built wheel and `pip install` it);
   otherwise the step is recorded as skipped with the reason.
3. encoder: the PRESET forward at 2 x SIZE x SIZE in fp32 and under bf16 autocast: median time,
   time ratio, peak memory, and the relative L2 difference of the bf16 depths to the fp32 ones.
4. training: STEPS bf16 autocast steps of PRESET (batch 1, 2 context + 4 target views, SIZE^2
   procedural rooms, MSE loss): median step time, peak memory, losses, gradient norms and how far
   the weights moved; the step fails if an update was skipped (a NaN/inf gradient, named) or the
   weights did not change.

`ran_on_gpu` in the JSON says whether DEVICE was a CUDA device.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import time
import traceback
from pathlib import Path

import torch

ATTRIBUTES = ("means", "quats", "scales", "opacities", "sh")


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def peak_bytes(device: torch.device) -> tuple[int, str]:
    from surfsplat.evaluation import peak_memory

    return peak_memory(device)


def render_pass(
    gaussians, cameras, size: int, backend: str, device: torch.device, weights: dict, mode: str = "surfel"
) -> dict:
    """Forward and backward of sum(weights * outputs) with `backend` on `device` (no forced-alpha
    normalization: it divides by small alphas and would magnify float32 rounding)."""
    from surfsplat.render import render

    leaves = {k: getattr(gaussians, k).detach().to(device).requires_grad_(True) for k in ATTRIBUTES}
    g = type(gaussians)(**leaves)
    cams = cameras.to(device)
    sync(device)
    start = time.perf_counter()
    out = render(g, cams, size, size, backend=backend, mode=mode, alpha_threshold=None)
    sync(device)
    forward = time.perf_counter() - start
    loss = sum((getattr(out, k) * weights[k].to(device)).sum() for k in ("color", "alpha", "depth"))
    start = time.perf_counter()
    loss.backward()
    sync(device)
    return {
        "outputs": {k: getattr(out, k).detach().cpu() for k in ("color", "alpha", "depth")},
        "grads": {k: v.grad.detach().cpu() for k, v in leaves.items()},
        "seconds_forward": forward,
        "seconds_backward": time.perf_counter() - start,
    }


def grad_error_by_tilt(gaussians, cameras, got: torch.Tensor, ref: torch.Tensor) -> dict:
    """Where a gradient's error lives: surfels binned by how obliquely the cameras see them
    (|cos| of the angle between the surfel normal and the viewing ray, the smallest over cameras),
    with each bin's share of the surfels and of the squared error, and its own relative L2."""
    from surfsplat.geometry import quat_to_matrix

    normals = quat_to_matrix(gaussians.quats.detach().double())[:, :, 2]
    rays = gaussians.means.detach().double()[None] - cameras.centers.detach().double()[:, None]
    cos = ((rays / rays.norm(dim=-1, keepdim=True)) * normals[None]).sum(-1).abs().amin(0)
    err = (got.double() - ref.double()).pow(2).flatten(1).sum(1)
    total = err.sum().clamp(min=1e-300)
    rows = {}
    for lo, hi in ((0.0, 0.05), (0.05, 0.2), (0.2, 1.01)):
        inside = (cos >= lo) & (cos < hi)
        ref_sq = ref.double()[inside].pow(2).sum().clamp(min=1e-300)
        rows[f"cos_{lo:g}_{min(hi, 1.0):g}"] = {
            "surfel_share": float(inside.double().mean()),
            "error_share": float(err[inside].sum() / total),
            "rel_l2": float((err[inside].sum() / ref_sq).sqrt()),
        }
    return rows


def compare_renderers(
    candidate: str,
    device: torch.device,
    resolution: int,
    factors: tuple[int, ...],
    mode: str = "surfel",
    dtype: torch.dtype = torch.float32,
) -> dict:
    """`candidate` backend on `device` in `dtype` against the compiled CPU renderer (float64 there), per factor.

    Besides the largest differences, the number of colour values more than 1e-4 off says whether
    an error is everywhere (a wrong formula) or at a few pixels (a threshold such as 1/255 or the
    1e-4 transmittance cut falling the other way in float32), and the means gradient's error is
    split by how obliquely each surfel is seen.

    For the gsplat backend in "surfel" mode the depth is the blended centre depth by design
    (`surfsplat.render.gsplat_backend`): its depth difference is reported, not a defect, and the
    gradients compared there are those of colour and alpha alone.
    """
    from surfsplat.data.synthetic.surfel_scene import make_scene

    scene = make_scene(resolution=resolution, views=2, opacity=0.5)
    rows = {}
    for s in factors:
        size = resolution * s
        cams = scene.target.scaled(float(s))
        gen = torch.Generator().manual_seed(s)
        weights = {
            k: torch.rand(1, c, size, size, generator=gen) for k, c in (("color", 3), ("alpha", 1), ("depth", 1))
        }
        if candidate == "gsplat" and mode == "surfel":  # its depth is the centre depth: keep it out of the gradients
            weights["depth"] = torch.zeros_like(weights["depth"])
        ref_scene = type(scene.gaussians)(**{k: getattr(scene.gaussians, k).double() for k in ATTRIBUTES})
        ref = render_pass(ref_scene, cams.to(torch.float64), size, "cpu", torch.device("cpu"), weights, mode)
        cand_scene = type(scene.gaussians)(**{k: getattr(scene.gaussians, k).to(dtype) for k in ATTRIBUTES})
        got = render_pass(cand_scene, cams.to(dtype), size, candidate, device, weights, mode)
        colour_diff = (got["outputs"]["color"].double() - ref["outputs"]["color"]).abs()
        rows[f"x{s}"] = {
            "size": size,
            "max_abs_diff": {k: float((got["outputs"][k] - ref["outputs"][k]).abs().max()) for k in ref["outputs"]},
            "colour_values_over_1e-4": int((colour_diff > 1e-4).sum()),
            "colour_values_over_1e-5": int((colour_diff > 1e-5).sum()),
            "colour_values": colour_diff.numel(),
            "colour_abs_diff_p99_9": float(torch.quantile(colour_diff.flatten()[::7].float(), 0.999)),
            "grads_finite": {k: bool(v.isfinite().all()) for k, v in got["grads"].items()},
            "means_grad_error_by_tilt": grad_error_by_tilt(
                scene.gaussians, cams, got["grads"]["means"], ref["grads"]["means"]
            ),
            "grad_rel_l2": {
                k: float((got["grads"][k] - ref["grads"][k]).norm() / ref["grads"][k].norm().clamp(min=1e-30))
                for k in ATTRIBUTES
            },
            "seconds": {
                f"{candidate}_forward": got["seconds_forward"],
                f"{candidate}_backward": got["seconds_backward"],
                "cpu_forward": ref["seconds_forward"],
                "cpu_backward": ref["seconds_backward"],
            },
        }
    return {"surfels": len(scene.gaussians), "mode": mode, "dtype": str(dtype), "factors": rows}


def encoder_timings(preset: str, size: int, device: torch.device, repeats: int) -> dict:
    from surfsplat import Cameras
    from surfsplat.model import SurfSplat

    torch.manual_seed(0)
    model = SurfSplat.from_preset(preset, adapter="official").eval().to(device)
    images = torch.rand(1, 2, 3, size, size, device=device)
    K = torch.tensor([[0.9 * size, 0, size / 2], [0, 0.9 * size, size / 2], [0, 0, 1.0]]).repeat(2, 1, 1)
    c2w = torch.eye(4).repeat(2, 1, 1)
    c2w[1, 0, 3] = 0.15
    cameras = Cameras(c2w, K).to(device)
    rows, depths = {}, {}
    for name in ("fp32", "bf16"):
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        with torch.no_grad(), torch.autocast(device.type, dtype=torch.bfloat16, enabled=name == "bf16"):
            depths[name] = model(images, cameras, 0.5, 100.0).depths.float()  # warm-up
            times = []
            for _ in range(repeats):
                sync(device)
                start = time.perf_counter()
                model(images, cameras, 0.5, 100.0)
                sync(device)
                times.append(time.perf_counter() - start)
        peak, kind = peak_bytes(device)
        rows[name] = {
            "seconds": times,
            "median_s": statistics.median(times),
            "peak_mb": peak / 2**20,
            "peak_kind": kind,
        }
    rows["bf16_vs_fp32_time"] = rows["bf16"]["median_s"] / rows["fp32"]["median_s"]
    rows["bf16_depth_rel_l2"] = float((depths["bf16"] - depths["fp32"]).norm() / depths["fp32"].norm())
    return {"preset": preset, "views": 2, "size": size, **rows}


def training_steps(preset: str, size: int, steps: int, device: torch.device) -> dict:
    from torch.utils.data import default_collate

    from surfsplat.data.synthetic import SyntheticDataset, SyntheticDatasetConfig
    from surfsplat.model.decoder import decoder_mode
    from surfsplat.train import build_model, build_optimizer, train_preset
    from surfsplat.train.config import override
    from surfsplat.train.data import to_train_batch
    from surfsplat.train.loop import training_step
    from surfsplat.train.losses import ImageLoss

    config = override(
        train_preset(preset),
        {"data.image_shape": [size, size], "data.num_target_views": 4, "loss.lpips_weight": 0.0, "batch_size": 1},
    )
    torch.manual_seed(0)
    model = build_model(config).to(device).train()
    optimizer = build_optimizer(model, config)
    loss_fn = ImageLoss(config.loss).to(device)
    dataset = SyntheticDataset(
        SyntheticDatasetConfig(length=2, image_shape=(size, size), num_target_views=4, supersample=1)
    )
    batches = [to_train_batch(default_collate([dataset[i]]), [i]).to(device) for i in range(2)]
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    before = [p.detach().clone() for p in model.parameters()]
    times, losses, grad_norms, skipped = [], [], [], []
    for step in range(steps):
        sync(device)
        start = time.perf_counter()
        out = training_step(
            model,
            model,
            batches[step % 2],
            loss_fn,
            optimizer,
            mode=decoder_mode(model.cfg.adapter),
            amp_dtype=torch.bfloat16,
            grad_clip=config.optim.grad_clip,
        )
        losses.append(float(out.loss.detach()))  # waits for the device
        times.append(time.perf_counter() - start)
        grad_norms.append(float(out.grad_norm))
        if out.nonfinite is not None:  # the update was not applied
            skipped.append({"step": step, "reason": out.nonfinite})
    moved = sum(float((p.detach() - b).norm() ** 2) for p, b in zip(model.parameters(), before)) ** 0.5
    size_of = sum(float(b.norm() ** 2) for b in before) ** 0.5
    peak, kind = peak_bytes(device)
    # A training step that skips its update (a NaN/inf gradient) or leaves the weights where they were
    # repeats its losses exactly; the check fails then, naming what was not finite.
    problems = [f"step {s['step']}: update skipped ({s['reason']})" for s in skipped]
    if moved == 0.0:
        problems.append(f"the weights did not change over {steps} steps")
    finite = all(math.isfinite(x) for x in losses)
    if not finite:
        problems.append("a loss is not finite")
    timed = times[1:] or times  # the first step includes kernel selection and allocator warm-up
    return {
        "preset": preset,
        "size": size,
        "steps": steps,
        "precision": "bf16 autocast, float32 weights and AdamW state",
        "step_seconds": times,
        "step_median_s": statistics.median(timed),
        "losses": losses,
        "losses_finite": finite,
        "grad_norms": grad_norms,
        "skipped_updates": skipped,
        "weights_moved_rel": moved / max(size_of, 1e-30),
        "problems": problems,
        "master_weights_dtype": str({p.dtype for p in model.parameters()}),
        "peak_mb": peak / 2**20,
        "peak_kind": kind,
    }


def run_step(report: dict, name: str, fn, *args) -> None:
    """Run one step into report["steps"][name]; a failure is recorded and the other steps go on."""
    start = time.perf_counter()
    try:
        result = fn(*args)
        report["steps"][name] = {"status": "failed" if result.get("problems") else "ok", **result}
    except Exception as err:  # recorded in the JSON: this script reports, it does not stop at the first failure
        report["steps"][name] = {"status": "failed", "error": repr(err), "traceback": traceback.format_exc()}
    report["steps"][name]["seconds_total"] = time.perf_counter() - start
    print(f"{name}: {report['steps'][name]['status']} ({report['steps'][name]['seconds_total']:.1f} s)", flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", help="cuda (the check) or cpu (the same steps on CPU)")
    parser.add_argument("--out", type=Path, default=Path("gpu_check.json"))
    parser.add_argument("--quick", action="store_true", help="small sizes and the tiny preset (CPU tests)")
    parser.add_argument("--preset", default=None, help="encoder and training preset (default small; quick: tiny)")
    parser.add_argument("--size", type=int, default=None, help="encoder and training image size (default 256)")
    parser.add_argument("--train-steps", type=int, default=None, help="bf16 training steps (default 20)")
    parser.add_argument(
        "--steps",
        default="renderer,gsplat,encoder,training",
        help="comma-separated steps to run (default: all of renderer, gsplat, encoder, training)",
    )
    args = parser.parse_args()
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print("--device cuda: no CUDA device is available (use --device cpu to run the steps on CPU)", file=sys.stderr)
        return 2
    preset = args.preset or ("tiny" if args.quick else "small")
    size = args.size or (64 if args.quick else 256)
    steps = args.train_steps or (2 if args.quick else 20)
    resolution, factors = (32, (1, 2, 4)) if args.quick else (256, (1, 2, 4))

    from surfsplat.render import gsplat_available

    report = {
        "ran_on_gpu": device.type == "cuda",
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor() or "cpu",
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "threads": torch.get_num_threads(),
        "load_average": os.getloadavg(),
        "settings": {"preset": preset, "size": size, "train_steps": steps, "render_resolution": resolution},
        "steps": {},
    }
    wanted = set(args.steps.split(","))
    if "renderer" in wanted:
        run_step(report, "renderer_torch_vs_cpu", compare_renderers, "torch", device, resolution, factors)
        run_step(
            report,
            "renderer_torch_float64_vs_cpu",
            compare_renderers,
            "torch",
            device,
            resolution,
            factors,
            "surfel",
            torch.float64,
        )
        if device.type != "cpu":  # the float32 control: the same backend and dtype on the CPU
            run_step(
                report,
                "renderer_torch_cpu_float32_vs_cpu",
                compare_renderers,
                "torch",
                torch.device("cpu"),
                resolution,
                factors,
            )
    if "gsplat" not in wanted:
        pass
    elif gsplat_available(device):
        for mode in ("surfel", "ewa"):
            run_step(
                report, f"renderer_gsplat_vs_cpu_{mode}", compare_renderers, "gsplat", device, resolution, factors, mode
            )
    else:
        reason = "not a CUDA device" if device.type != "cuda" else "the gsplat package does not import"
        report["steps"]["renderer_gsplat_vs_cpu"] = {"status": "skipped", "reason": reason}
        print(f"renderer_gsplat_vs_cpu: skipped ({reason})", flush=True)
    if "encoder" in wanted:
        run_step(report, "encoder_fp32_bf16", encoder_timings, preset, size, device, 3)
    if "training" in wanted:
        run_step(report, "training_bf16", training_steps, preset, size, steps, device)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1))
    print(f"wrote {args.out} (ran on {'GPU' if report['ran_on_gpu'] else 'CPU'}: {report['device']})")
    return 0 if all(s["status"] != "failed" for s in report["steps"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
