"""What `Scene.save` writes about a capture of many views: capture.json and capture.html.

capture.html shows the whole capture: every context camera from above, the forward passes and
what fusion kept, each held-out view's photo beside the fused scene's render from its camera (with
PSNR and coverage), and for a video which frames were used and why the others were dropped.
"""

from __future__ import annotations

import json
from pathlib import Path

from ..capture import optimize_summary, refine_summary
from ..data.cameras import CameraSet

THUMBNAIL_WIDTH = 240  # pixels of the pictures in the report


def seconds_line(seconds: dict[str, float]) -> str:
    """Every timed stage but the total, in the order it ran; none is hidden for being short."""
    return ", ".join(f"{k} {v:.2f}" for k, v in seconds.items() if k != "total")


def held_out_line(scores: dict, views: int, lpips_note: str | None) -> str:
    """The held-out views' mean figures in one sentence (LPIPS only where it was computed)."""
    lpips = f", LPIPS {scores['mean_lpips']:.3f}" if scores.get("mean_lpips") is not None else ""
    line = (
        f"Mean over {views} held-out views: PSNR {scores['mean_psnr']:.2f} dB, SSIM {scores['mean_ssim']:.3f}{lpips}, "
        f"coverage (alpha >= 0.5) {scores['mean_coverage']:.3f}."
    )
    return line + (f" {lpips_note}." if lpips_note else "")


def zoom_line(zoom: dict, antialiased: bool) -> str:
    """The held-out zoom scores (`metrics.zoom`) in one sentence."""
    down = ", ".join(
        f"x1/{s} {zoom[f'x1/{s}']:.2f} (the x1 render averaged down: {zoom[f'x1/{s}_target']:.2f}; "
        f"the two compared: {zoom[f'x1/{s}_vs_render']:.2f})"
        for s in (2, 4)
        if f"x1/{s}" in zoom
    )
    up = ", ".join(f"x{s} {zoom[f'x{s}']:.2f}" for s in (2, 4) if f"x{s}" in zoom)
    line = (
        f"Held-out PSNR by zoom ({'with' if antialiased else 'without'} the antialiasing filter): x1 {zoom['x1']:.2f}"
    )
    line += f", {down}" if down else ""
    line += f", {up} ({zoom.get('upsample', 'bicubic')}-upsampled photos)" if up else ""
    ratio = zoom.get("coverage_x4_over_x1")
    line += " dB" + (f"; mean alpha x4 / x1 {ratio:.3f}" if ratio is not None else "")
    factors, asked = zoom.get("supersample", {}), zoom.get("drawn_at_size", {})
    if any(k > 1 for k in factors.values()):
        drawn = ", ".join(f"x1/{s} at {factors[f'x1/{s}']}x" for s in (2, 4) if f"x1/{s}" in factors)
        plain = ", ".join(f"x1/{s} {asked[f'x1/{s}']:.2f}" for s in (2, 4) if f"x1/{s}" in asked)
        line += f"; zoomed out drawn finer and averaged down ({drawn}; drawn at the size asked: {plain} dB)"
    plain_up = ", ".join(f"x{s} {asked[f'x{s}']:.2f}" for s in (2, 4) if f"x{s}" in asked)
    if plain_up:
        line += f"; zoomed in with the fitted pixels' filter (without: {plain_up} dB)"
    return line


def write_capture_outputs(scene, out_dir: str | Path, options) -> dict[str, Path]:
    """Write capture.json, capture/ (cameras from above, held-out renders) and capture.html."""
    from ..export.figures import line_chart, write_text
    from ..export.images import write_png
    from ..export.report import HtmlReport
    from ..poses.report import top_view_svg

    out = Path(out_dir)
    written = {
        "capture summary": write_text(out / "capture.json", json.dumps(scene.capture_summary(), indent=1) + "\n")
    }
    report = HtmlReport("SurfSplat reconstruction of a capture")
    report.heading("The capture")
    fusion = scene.fusion_stats
    passes = f"in {len(scene.passes)} forward passes" if scene.network == "ran" else f"(network: {scene.network})"
    lines = [
        f"{len(scene.names)} context views at {scene.width}x{scene.height} {passes}; {len(scene.gaussians):,} surfels"
    ]
    if fusion:
        lines.append(
            f"fusion: {fusion['predicted']:,} surfels predicted, {fusion['duplicates']:,} duplicates of surfaces "
            f"already fused removed ({fusion['duplicates'] / max(fusion['predicted'], 1):.0%}), "
            f"{fusion.get('replaced', 0):,} fused surfels replaced by a closer view's"
        )
    if scene.refine_stats:
        lines.append(refine_summary(scene.refine_stats))
    if scene.optimize_stats:
        lines.append(optimize_summary(scene.optimize_stats))
    lines.append("seconds: " + seconds_line(scene.seconds))
    if scene.video is not None:
        lines.extend(scene.video.lines())
    report.preformatted("\n".join(lines))
    cameras = CameraSet(scene.cameras, scene.width, scene.height, list(scene.names))
    written["capture cameras"] = write_text(out / "capture" / "cameras.svg", top_view_svg(cameras))
    report.figure("capture/cameras.svg", "Every context camera from above (x right, z forward of the first camera)")
    report.table(
        "Forward passes (context views of each)",
        ["pass", "views"],
        [[str(i), ", ".join(p)] for i, p in enumerate(scene.passes)],
    )
    h = scene.holdout
    if h is not None:
        from ..data.cameras import save_cameras

        # `surfsplat optimize` of this folder scores the same views again from these
        written["held-out cameras"] = save_cameras(
            out / "capture" / "held_out_cameras.json",
            h.cameras,
            scene.width,
            scene.height,
            list(h.names),
            crop=scene.crop,
            lenses=scene.view_lenses(list(h.names)),
        )
        fitted = "the optimized scene" if scene.optimize_stats else "the fused scene"
        report.heading(f"Held-out views: never a context view, rendered from {fitted}")
        out_h = scene.render(h.cameras)
        for i, name in enumerate(h.names):  # one row a view: photo, [before the optimization,] render
            stem = Path(name).stem  # IMG_4026.JPG -> capture/IMG_4026_photo.png
            photo = write_png(out / "capture" / f"{stem}_photo.png", h.images[i])
            figures = [(str(photo.relative_to(out)), f"{name}: photo")]
            after = ""
            if h.before_renders is not None:
                early = write_png(out / "capture" / f"{stem}_render_before.png", h.before_renders[i])
                caption = f"{name}: before the optimization, {h.before['psnr'][i]:.2f} dB"
                figures.append((str(early.relative_to(out)), caption))
                after = " after the optimization"
            render = write_png(out / "capture" / f"{stem}_render.png", out_h.color[i].clamp(0, 1))
            caption = f"{name}: render{after}, {h.psnr[i]:.2f} dB, coverage {h.coverage[i]:.2f}"
            figures.append((str(render.relative_to(out)), caption))
            report.figure_row(figures, width=THUMBNAIL_WIDTH, pixelated=True)
        report.paragraph(held_out_line(h.scores(), len(h.names), h.lpips_note))
        if h.protocol == "exposure":
            report.paragraph(
                "Scored as 3DGS's train_test_exp protocol: the scene was fitted with an exposure map per context "
                "photo, so each held-out photo's map is fitted on its left half and the figures are those of the "
                "right half."
            )
        if h.alignment is not None:
            shifts = ", ".join(f"{a:.2f}" for a in h.alignment["rotation_deg"])
            report.paragraph(
                "The context cameras were refined with the scene, so each held-out camera was aligned to its photo "
                f"first (the scene frozen, {h.alignment['steps']} steps; rotations moved by {shifts} degrees)."
            )
        if h.before is not None:
            report.paragraph("Before the per-scene optimization: " + held_out_line(h.before, len(h.names), None))
        if h.zoom is not None:
            report.paragraph(zoom_line(h.zoom, scene.antialiased))
        curve = scene.optimize_stats.get("held_out_curve") if scene.optimize_stats else None
        if curve:
            chart = line_chart(
                {"held-out PSNR": [(p["seconds"], p["psnr"]) for p in curve]},
                title="Held-out PSNR (dB) during the per-scene optimization",
                x_label="seconds of the optimization",
                y_label="dB",
            )
            written["optimization curve"] = write_text(out / "capture" / "optimize_curve.svg", chart)
            report.figure(
                "capture/optimize_curve.svg",
                f"Held-out PSNR against the optimization's seconds: {curve[0]['psnr']:.2f} dB at its start "
                f"({curve[0]['surfels']:,} surfels), {curve[-1]['psnr']:.2f} dB after {curve[-1]['seconds']:.0f} s "
                f"and {curve[-1]['step']:,} steps ({curve[-1]['surfels']:,} surfels)",
            )
        written["held-out renders"] = out / "capture"
    if scene.video is not None:
        rows = [
            [
                str(r.index),
                "yes" if r.kept else "no",
                r.reason,
                f"{r.sharpness:.4g}",
                "" if r.motion is None else f"{r.motion:.4f}",
            ]
            for r in scene.video.records
        ]
        report.table("Video frames", ["frame", "used", "why", "sharpness", "motion"], rows)
    report.links("Files:", [("capture.json", "the capture summary"), ("cameras.json", "every context camera")])
    written["capture report"] = report.write(out / "capture.html")
    return written
