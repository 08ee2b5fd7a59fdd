"""The demo's report.html: what the numbers say, the shipped model's summary, and the page."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .pipeline import DemoConfig, Phase

from .pipeline import DEPTH_ERROR_MAX, NORMAL_ERROR_MAX, SHIPPED_LABEL, SHIPPED_MODEL


# ----------------------------------------------------------------------------------------------- report
def read_numbers(metrics: dict, train: dict) -> str:
    """A short paragraph that reads the table: geometry of each network, then sharpness at x4."""
    names = list(metrics)

    def geo(name: str) -> dict | None:
        return metrics[name]["geometry"]["mean"]

    def views(name: str) -> str:
        g = geo(name)
        if g is None:
            return "no geometry"
        return (
            f"depth AbsRel {g['abs_rel']:.3f} ({g['delta1']:.0%} of pixels within 1.25x), "
            f"median normal error {g['median_deg']:.1f} deg, surfel Chamfer {g['surfels_chamfer']:.2f} m "
            f"(F-score {g['surfels_fscore']:.2f} at 5 cm)"
        )

    shipped, here, untrained = names[0], names[1], names[2]
    text = [
        f"At the target views the shipped model reaches {views(shipped)}; the model trained here for "
        f"{train['steps']} steps reaches {views(here)}, and the untrained network {views(untrained)}."
    ]
    g_ship, g_here = geo(shipped), geo(here)
    if g_ship and g_here:
        better = g_ship["median_deg"] < g_here["median_deg"] and g_ship["abs_rel"] < g_here["abs_rel"]
        text.append(
            "Long training is what turns the network's depth into a surface: "
            if better
            else "Here the brief run is not behind the shipped model on every geometry column: "
        )
        text[-1] += (
            f"its normals are off by {g_ship['median_deg']:.1f} instead of {g_here['median_deg']:.1f} degrees "
            f"(median) and its depth by {g_ship['abs_rel']:.1%} instead of {g_here['abs_rel']:.1%}."
        )
    native = {n: metrics[n]["vs_native_truth"] for n in names}
    x1, x4 = native[shipped]["x1"]["psnr"], native[shipped]["x4"]["psnr"]
    cover = metrics[shipped]["coverage"]
    closure = metrics[shipped]["closure"]
    holes = not closure["closed"]
    text.append(
        f"Against natively ray-cast truth the shipped model scores {x1:.2f} dB PSNR at x1 and {x4:.2f} dB at x4, "
        f"with {cover['x1']:.0%} of pixels covered by alpha > 0.5 at x1 and {cover['x4']:.0%} at x4; its mean "
        f"alpha at x4 is {closure['closure']:.2f} of that at x1 (closure) and "
        f"{closure['undersized_share']:.0%} of its surfels are under half their pixel footprint: "
        + (
            "at four times the resolution its surfels leave gaps that forced alpha blending fills by "
            "normalising what little alpha remains, which the x4 renders and the novel view show as texture "
            "broken into discs."
            if holes
            else "at four times the resolution its surfels still close into a surface."
        )
        + " A low-resolution input cannot supply the detail the native x4 image holds in any case."
    )
    return " ".join(text)


def shipped_summary() -> str:
    """How the shipped model was trained, as its metadata records it (`scripts/ship_model.py --summary`)."""
    from ..model.pretrained import describe

    return str(describe(SHIPPED_MODEL)["summary"])


def write_demo_report(
    config: DemoConfig,
    out: Path,
    train: dict,
    evaluation: dict,
    exports: dict[str, Path],
    novel: dict[str, str],
    curve: Path,
    phases: list[Phase],
) -> Path:
    from ..export.report import HtmlReport

    rel = lambda p: str(Path(p).resolve().relative_to(out.resolve()))  # noqa: E731 - a one-line path helper
    report = HtmlReport("SurfSplat demo: a learned surface, measured at x1/x2/x4")
    size = config.image_size
    report.paragraph(
        f"Three networks are scored on {config.eval_scenes} held-out procedural rooms at {size}x{size}: "
        f"{SHIPPED_LABEL}, {shipped_summary()}, shipped with the "
        f"package (--checkpoint {SHIPPED_MODEL}); the same preset trained here for {train['steps']} "
        f"steps ({train['seconds']:.0f} s) on {train['scenes']} rooms with the MSE loss, to show training; and the "
        "untrained network. Renders at x2 and x4 use K scaled by the factor (HRRC, paper Sec. 3.6). Two ground "
        "truths: the x1 image upsampled bicubically (the paper's HRRC) and the scene ray-cast natively at the "
        "higher resolution; geometry is scored against the rooms' exact depth, normals and surfaces."
    )
    report.heading("What the numbers say")
    report.paragraph(read_numbers(evaluation["metrics"], train))
    if train["stopped_by_deadline"]:
        report.paragraph(
            f"Training was stopped by its time limit at step {train['steps']} of the {train['planned_steps']} "
            "planned (a slow or busy machine); the learning-rate schedule did not finish.",
            note=True,
        )
    if evaluation["lpips"] is not None:
        report.paragraph(evaluation["lpips"], note=True)
    report.heading("Metrics")
    factors = config.factors
    header = [
        "Model",
        "Resolution",
        "PSNR (bicubic GT)",
        "SSIM (bicubic GT)",
        "LPIPS (bicubic GT)",
        "PSNR (native GT)",
        "SSIM (native GT)",
        "Coverage (alpha > 0.5)",
    ]
    rows = []
    for name, m in evaluation["metrics"].items():
        up = m["vs_bicubic_upsampled_truth"]
        for s in factors:
            label = f"{size * s}x{size * s} (" + ("standard" if s == 1 else f"HRRC x{s}") + ")"
            u, n = up["mean"][f"x{s}"], m["vs_native_truth"][f"x{s}"]
            rows.append([name, label, u["psnr"], u["ssim"], u["lpips"], n["psnr"], n["ssim"], m["coverage"][f"x{s}"]])
        avg = up["average"]
        rows.append([name, "average", avg["psnr"], avg["ssim"], avg["lpips"], None, None, None])
    report.table("Standard and HRRC metrics (means over target views)", header, rows)
    report.paragraph(
        "Coverage is the share of pixels whose accumulated alpha exceeds 0.5. Forced alpha blending "
        "divides colour, depth and normals by alpha wherever alpha >= 0.001 (paper Sec. 3.4), so a "
        "render can look complete while its surfels leave gaps between them at higher resolutions."
    )
    report.paragraph("The same numbers in the paper's table layout:")
    report.preformatted(evaluation["table"])

    report.heading("Closure: does the surface stay closed at x2 and x4?")
    closure_rows = []
    for name, m in evaluation["metrics"].items():
        c = m["closure"]
        q = c["opacity_quantiles"]
        closure_rows.append(
            [name, c["closure"]]
            + [c["mean_alpha"][f"x{s}"] for s in factors]
            + [c["coverage"][f"x{s}"]["alpha>=0.9"] for s in factors]
            + [c["undersized_share"], c["multiplier_at_low"], q["p50"], "yes" if c["closed"] else "no"]
        )
    report.table(
        "Closure of the target views (means over every rendered pixel; surfel shares over every surfel)",
        ["Model", "Closure (alpha x4 / x1)"]
        + [f"Mean alpha x{s}" for s in factors]
        + [f"Coverage alpha >= 0.9, x{s}" for s in factors]
        + ["Surfels under half their footprint", "Scale multipliers at 1/3", "Median opacity", "Closed"],
        closure_rows,
    )
    report.paragraph(
        "A continuous surface keeps its alpha at any resolution: closure is the mean alpha at x4 over the mean "
        "alpha at x1, and counts as closed at 0.9 or more with at most 15% of surfels smaller than half the "
        "surface one pixel spans at their depth (z / f). The screen-space low-pass widens every surfel to about "
        "a pixel at x1, so surfels of a third of a pixel look whole there and part at x4."
    )

    report.heading("Geometry against the exact truth")
    report.paragraph(
        "Target views at x1: rendered depth (AbsRel, RMSE in metres, share within 1.25x) and normals (angular "
        "error) over the pixels whose true surface a context view sees and where alpha >= 0.1. Surfaces: surfel "
        "centres weighted by opacity, and points sampled on the TSDF mesh, against area-uniform samples of the "
        "true surfaces the context views see: accuracy and completeness (mean distances, metres), Chamfer "
        "distance and F-score at 5 cm. Silhouette pixels blend foreground and background depth, so even surfels "
        "placed exactly on the true surfaces score an AbsRel of a few percent here."
    )
    report.preformatted(evaluation["geometry_table"])

    report.heading("Renders at x1, x2, x4")
    report.paragraph(
        "Each row: native ground truth, render, rendered depth, rendered normals; all shown at the "
        "same size, so the x1 row shows its pixels and the x4 row the detail a continuous surface keeps."
    )
    for fig in evaluation["figures"]:
        report.paragraph(f"Held-out room {fig['key']}; context views:")
        report.figure_row([(p, f"context {i}") for i, p in enumerate(fig["context"])], width=160, pixelated=True)
        for row in fig["rows"]:
            s = row["factor"]
            report.figure_row(
                [
                    (row["truth"], f"truth {row['size']} px (x{s})"),
                    (row["render"], f"render x{s}"),
                    (row["depth"], f"depth x{s}"),
                    (row["normal"], f"normal x{s}"),
                    (row["truth depth"], f"true depth x{s}"),
                    (row["truth normal"], f"true normal x{s}"),
                    (row["depth error"], f"depth error x{s} (0-{DEPTH_ERROR_MAX:.0%})"),
                    (row["normal error"], f"normal error x{s} (0-{NORMAL_ERROR_MAX:.0f} deg)"),
                ],
                width=104,
                pixelated=True,
            )
        report.figure(
            fig["grid"],
            "grid: truth | render | depth | normal | depth error | normal error, rows x1, x2, x4 "
            "(error maps: black = exact, yellow = at or above the scale; grey = not scored)",
            width=960,
            pixelated=True,
        )

    report.heading("Training curve")
    report.figure(rel(curve), f"MSE loss per step ({train['steps']} steps)", width=640)

    report.heading("Exports of the first held-out room (shipped model)")
    report.paragraph(
        f"From a viewpoint no input saw (orbited and raised from the first target view), at {size * max(config.factors)} "
        "px: the true room, the shipped model's surfels (exact 2DGS render), the TSDF mesh fused from their depth "
        "with its colours, and the mesh's shape alone."
    )
    report.figure(rel(novel["grid"]), "truth | surfels | mesh | mesh shape", width=960)
    bake = novel["viewer"]
    report.paragraph(
        "The exported surfels_3dgs.ply as standard 3DGS viewers (SuperSplat, gsplat's) composite it: EWA splatting "
        "without forced alpha blending, on black. The export bakes it so that this reproduces our render: "
        + "; ".join(
            f"from the context views at {k.split()[-1]}, mean alpha {bake['before'][k]['alpha']:.2f} -> "
            f"{bake['after'][k]['alpha']:.2f} and colour PSNR {bake['before'][k]['psnr']:.1f} -> "
            f"{bake['after'][k]['psnr']:.1f} dB against our render over the pixels it covers"
            for k in bake["after"]
        )
        + f" (raw thin surfels -> baked; {bake['seconds']:.0f} s)."
    )
    report.figure(
        rel(bake["grid"]),
        "context view: ours | exported PLY in a standard viewer; novel view: ours | exported PLY in a standard viewer",
        width=960,
    )
    videos = [(k, p) for k, p in exports.items() if str(p).endswith(".mp4")]
    for key, path in videos:
        report.video(rel(path), key, width=320)
    report.links("Files:", [(rel(p), k) for k, p in exports.items()])
    report.heading("Time")
    report.table("Wall time per phase", ["Phase", "Seconds"], [[p.name, p.seconds] for p in phases])
    return report.write(out / "report.html")
