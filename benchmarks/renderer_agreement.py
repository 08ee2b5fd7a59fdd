"""Renderer agreement table: every backend, mode and dtype against the field's reference and each other.

On this machine (CPU), with the conventions aligned through public options
(`lowpass_center_sigma=1`, `ewa_support="alpha"`, as in tests/render/test_gsplat_reference.py):
- the torch and compiled CPU backends against gsplat's own pure-PyTorch reference of 2DGS ("surfel")
  and 3DGS ("ewa") on three seeded scenes (200-2,000 surfels, SH 0 and 3, 64x48 and 128x96), in
  float64 and float32: largest differences of colour, alpha, normal and depth;
- float64 gradients of a fixed random loss against the reference's (relative L2, worst attribute);
- the project's gsplat backend with gsplat's CUDA entry points answered by its references, against
  the torch backend, float32.
GPU rows come from `scripts/gpu_check.py` JSON files (default: docs/results/gpu_check_*.json): each
GPU backend against the compiled CPU renderer in float64 on 131,072 surfels at x1 and x4.

    python benchmarks/renderer_agreement.py       # writes docs/results/renderer_agreement.{json,md}
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

import torch

from common import write_results
from surfsplat import Gaussians
from surfsplat.render import CpuRenderSettings, TorchRenderSettings, render
from surfsplat.render.gsplat_backend import render_gsplat
from surfsplat.testing.gsplat_reference import (
    ALIGNED,
    cpu_kernels,
    facing_normals,
    reference_scene,
    render_2dgs,
    render_3dgs,
    with_intrinsics,
)

DOCS = Path(__file__).resolve().parent.parent / "docs" / "results"
CASES = [(200, 0, 0, (64, 48)), (2000, 1, 3, (64, 48)), (800, 2, 3, (128, 96))]
ATTRIBUTES = ("means", "quats", "scales", "opacities", "sh")
DTYPES = {"float64": torch.float64, "float32": torch.float32}


def _ours(g, cams, width, height, mode, backend):
    settings = (CpuRenderSettings if backend == "cpu" else TorchRenderSettings)(**ALIGNED)
    out = render(g, cams, width, height, mode=mode, backend=backend, alpha_threshold=None, settings=settings)
    return {"colour": out.color, "alpha": out.alpha, "depth": out.depth, "normal": out.normal}


def _reference(g, cams, width, height, mode):
    w2c, K, centre = cams.w2c[0], cams.K[0], cams.centers[0]
    if mode == "surfel":
        colour, alpha, depth, normal = render_2dgs(g, w2c, K, centre, width, height)
    else:
        extra = facing_normals(g, centre)
        colour, alpha, depth, normal = render_3dgs(g, w2c, K, centre, width, height, extra=extra)
    return {"colour": colour, "alpha": alpha, "depth": depth, "normal": normal}


def against_gsplat_reference(backend: str, mode: str, dtype: str) -> dict:
    worst = {"colour": 0.0, "alpha": 0.0, "depth": 0.0, "normal": 0.0}
    for n, seed, degree, (W, H) in CASES:
        g, cams = reference_scene(n, seed + (10 if mode == "ewa" else 0), DTYPES[dtype], degree)
        cams = with_intrinsics(cams, W, H)
        ours, ref = _ours(g, cams, W, H, mode, backend), _reference(g, cams, W, H, mode)
        for k in worst:
            worst[k] = max(worst[k], float((ours[k] - ref[k]).abs().max()))
    return worst


def _grads(g: Gaussians, loss_of) -> dict:
    leaves = {k: getattr(g, k).detach().clone().requires_grad_(True) for k in ATTRIBUTES}
    loss_of(Gaussians(**leaves)).backward()
    return {k: v.grad for k, v in leaves.items()}


def _rel_l2(a: dict, b: dict) -> dict:
    return {k: float((a[k] - b[k]).norm() / b[k].norm().clamp(min=1e-30)) for k in a}


def gradients_against_gsplat_reference(backend: str) -> dict:
    g, cams = reference_scene(150, 7, torch.float64, 3)
    W, H = 48, 36
    cams = with_intrinsics(cams, W, H)
    gen = torch.Generator().manual_seed(0)
    wc, wa = (torch.rand(1, c, H, W, generator=gen, dtype=torch.float64) for c in (3, 1))

    def loss(maps):
        return (maps["colour"] * wc).sum() + (maps["alpha"] * wa).sum()

    ours = _grads(g, lambda gs: loss(_ours(gs, cams, W, H, "surfel", backend)))
    ref = _grads(g, lambda gs: loss(_reference(gs, cams, W, H, "surfel")))
    return _rel_l2(ours, ref)


def gsplat_backend_on_cpu(mode: str) -> dict:
    g, cams = reference_scene(600, 4, torch.float32, 3)
    W, H = 64, 48
    cams = with_intrinsics(cams, W, H)
    gen = torch.Generator().manual_seed(1)
    weights = {k: torch.rand(1, c, H, W, generator=gen) for k, c in (("colour", 3), ("alpha", 1), ("normal", 3))}
    settings = TorchRenderSettings()
    maps = {}

    def loss_of(backend):
        def loss(gs):
            if backend == "gsplat":
                colour, alpha, depth, normal = render_gsplat(gs, cams, W, H, mode, settings)
                out = {"colour": colour, "alpha": alpha, "depth": depth, "normal": normal}
            else:
                r = render(gs, cams, W, H, mode=mode, backend="torch", alpha_threshold=None, settings=settings)
                out = {"colour": r.color, "alpha": r.alpha, "depth": r.depth, "normal": r.normal}
            maps[backend] = {k: v.detach() for k, v in out.items()}
            return sum((out[k] * w).sum() for k, w in weights.items())

        return loss

    with cpu_kernels():
        ours = _grads(g, loss_of("gsplat"))
    ref = _grads(g, loss_of("torch"))
    diff = {k: float((maps["gsplat"][k] - maps["torch"][k]).abs().max()) for k in maps["torch"]}
    return {"max_abs_diff": diff, "grad_rel_l2": _rel_l2(ours, ref)}


def gpu_rows(path: Path) -> list[dict]:
    report = json.loads(path.read_text())
    rows = []
    for name, step in report["steps"].items():
        if not name.startswith("renderer_") or step.get("status") != "ok":
            continue
        backend = "gsplat" if "gsplat" in name else "torch"
        on = "CPU (float32 control)" if "cpu_float32" in name else report["device"]
        for factor in ("x1", "x4"):
            row = step["factors"][factor]
            tilt = row.get("means_grad_error_by_tilt", {})
            oblique = [v for k, v in tilt.items() if not k.startswith("cos_0.2")]
            rows.append(
                {
                    "source": path.name,
                    "device": on,
                    "backend": backend,
                    "mode": step["mode"],
                    "dtype": step.get("dtype", "torch.float32").removeprefix("torch."),
                    "factor": factor,
                    "size": row["size"],
                    "max_abs_diff": row["max_abs_diff"],
                    "colour_values_over_1e-4": row.get("colour_values_over_1e-4"),
                    "colour_values": row.get("colour_values"),
                    "grad_rel_l2_worst": max(row["grad_rel_l2"].values()),
                    "means_grad_error_share_oblique": sum(v["error_share"] for v in oblique) if tilt else None,
                    "oblique_surfel_share": sum(v["surfel_share"] for v in oblique) if tilt else None,
                }
            )
    return rows


def markdown(report: dict) -> str:
    lines = [
        "# Renderer agreement",
        "",
        "Generated by `benchmarks/renderer_agreement.py`; do not edit by hand.",
        "",
        "## Against gsplat's pure-PyTorch reference (CPU)",
        "",
        "gsplat's 2DGS reference for `surfel`, its 3DGS reference for `ewa`; conventions aligned through",
        '`lowpass_center_sigma=1` and `ewa_support="alpha"`. Largest absolute difference over three seeded',
        "scenes. Surfel depth differs by design: gsplat blends each surfel's centre depth, this project the",
        "depth of the ray-surfel intersection (2DGS).",
        "",
        "| backend | mode | dtype | colour | alpha | normal | depth |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in report["reference"]:
        d = r["max_abs_diff"]
        depth = f"{d['depth']:.1e}" + (" (centre depth, by design)" if r["mode"] == "surfel" else "")
        lines.append(
            f"| {r['backend']} | {r['mode']} | {r['dtype']} | {d['colour']:.1e} | {d['alpha']:.1e} "
            f"| {d['normal']:.1e} | {depth} |"
        )
    lines += ["", "Float64 gradients against the reference (relative L2, surfel mode):", ""]
    lines += ["| backend | " + " | ".join(ATTRIBUTES) + " |", "|---|" + "---|" * len(ATTRIBUTES)]
    for backend, g in report["reference_gradients"].items():
        lines.append(f"| {backend} | " + " | ".join(f"{g[k]:.1e}" for k in ATTRIBUTES) + " |")
    lines += [
        "",
        "## The gsplat backend on a CPU (gsplat's references as its kernels) against the torch backend, float32",
        "",
        "| mode | colour | alpha | normal | depth | worst gradient (rel. L2) |",
        "|---|---|---|---|---|---|",
    ]
    for mode, r in report["gsplat_backend_cpu"].items():
        d = r["max_abs_diff"]
        lines.append(
            f"| {mode} | {d['colour']:.1e} | {d['alpha']:.1e} | {d['normal']:.1e} | {d['depth']:.1e} "
            f"| {max(r['grad_rel_l2'].values()):.1e} |"
        )
    if report["gpu"]:
        lines += [
            "",
            "## On a GPU (`scripts/gpu_check.py`), against the compiled CPU renderer in float64",
            "",
            '131,072 surfels from two 256^2 views, rendered at x1 (256^2) and x4 (1024^2). "> 1e-4" counts',
            'the colour values more than 1e-4 off; "oblique share" is the part of the means gradient\'s',
            "squared error carried by the surfels seen at |cos| < 0.2 (their share of all surfels in brackets).",
            "",
            "| device | backend | mode | dtype | factor | colour | alpha | depth | > 1e-4 | worst gradient | "
            "oblique share |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in report["gpu"]:
            d = r["max_abs_diff"]
            share = r["means_grad_error_share_oblique"]
            oblique = "" if share is None else f"{share:.0%} ({r['oblique_surfel_share']:.1%})"
            lines.append(
                f"| {r['device']} | {r['backend']} | {r['mode']} | {r['dtype']} | {r['factor']} | "
                f"{d['color']:.1e} | {d['alpha']:.1e} | {d['depth']:.1e} | "
                f"{r['colour_values_over_1e-4']} of {r['colour_values']:,} | {r['grad_rel_l2_worst']:.1e} | "
                f"{oblique} |"
            )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DOCS / "renderer_agreement.json")
    parser.add_argument("--gpu-check", type=Path, nargs="*", default=None, help="gpu_check.py JSON files")
    args = parser.parse_args()
    gpu_files = args.gpu_check if args.gpu_check is not None else sorted(DOCS.glob("gpu_check_*.json"))
    report = {
        "meta": {"machine": platform.processor() or platform.machine(), "torch": torch.__version__},
        "reference": [],
        "reference_gradients": {},
        "gsplat_backend_cpu": {},
        "gpu": [row for path in gpu_files for row in gpu_rows(path)],
    }
    for backend in ("torch", "cpu"):
        for mode in ("surfel", "ewa"):
            for dtype in DTYPES:
                diff = against_gsplat_reference(backend, mode, dtype)
                report["reference"].append({"backend": backend, "mode": mode, "dtype": dtype, "max_abs_diff": diff})
        report["reference_gradients"][backend] = gradients_against_gsplat_reference(backend)
    for mode in ("surfel", "ewa"):
        report["gsplat_backend_cpu"][mode] = gsplat_backend_on_cpu(mode)
    write_results(args.out, report)
    table = markdown(report)
    args.out.with_suffix(".md").write_text(table)
    print(table)
    print(f"wrote {args.out} and {args.out.with_suffix('.md')}")


if __name__ == "__main__":
    main()
