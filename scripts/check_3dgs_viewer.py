"""Open a reconstruction in a standard 3D Gaussian splatting viewer: raw, baked, compacted and baked.

    python scripts/check_3dgs_viewer.py --out docs/viewer_check --level 4

One held-out procedural room is reconstructed by the shipped model and compacted. Three 3DGS-layout
PLY files are written, turned so that our z-up world stands upright in the viewer: the thin surfels
as they are (`surfsplat export --raw-3dgs`), and the reconstruction and its compaction baked for
standard viewers (`surfsplat.export.bake`, what `surfsplat export` writes as surfels_3dgs.ply).
PlayCanvas's `splat-transform` (the converter behind SuperSplat; fetched by npx) then reads each
file, prints its per-column summary and writes it as the SuperSplat viewer's self-contained HTML
page, whose camera is set behind the middle of the two context views; headless Chromium (software
WebGL) shows each page and takes a picture. The same viewpoint is rendered by surfsplat's own
renderer, as it renders and as a 3DGS viewer blends the baked file. Written: the PLY files, the
pages, `viewer_check.png` (ours | SuperSplat, raw | ours of the baked file as 3DGS | SuperSplat,
baked | SuperSplat, compacted and baked) and `viewer_check.json` (counts read back, the bake's
figures and PSNR between the pictures).

Needs node/npm (for npx) and Chromium (Debian: apt-get install chromium); neither is a dependency
of the package, so this is a script, not a test.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import shlex
import subprocess
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from surfsplat.compaction import compact_surfels
from surfsplat.data.synthetic import make_scene, make_trajectory, render_synthetic
from surfsplat.export.bake import bake_for_viewers, thin_gaussians
from surfsplat.export.images import to_uint8
from surfsplat.export.ply import save_ply
from surfsplat.geometry.gaussians import Gaussians
from surfsplat.geometry.sh_rotation import rotate_sh
from surfsplat.metrics.image import psnr
from surfsplat.model.decoder import decoder_mode
from surfsplat.model.loading import ModelSpec, load_model
from surfsplat.render import render
from surfsplat.testing.browser import Browser, chromium

ROOT = Path(__file__).resolve().parents[1]

SPLAT_TRANSFORM = "npx --yes @playcanvas/splat-transform@2.7.1"
# The SuperSplat viewer turns every scene by 180 degrees about z (3DGS scenes have y down) and keeps
# y up; our world has z up, so the splats are first turned by 90 degrees about x (y <- -z, z <- y).
# Together, a point (x, y, z) of ours shows at (-x, z, y) in the viewer's world.
TURN = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
TO_VIEWER = torch.diag(torch.tensor([-1.0, -1.0, 1.0])) @ TURN
HIDE_UI = "for (const e of document.body.children) if (e.tagName !== 'CANVAS' && !e.contains(document.querySelector('canvas'))) e.style.display = 'none';"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", default="tiny-synthetic", help="model (name or path)")
    parser.add_argument("--level", type=int, default=4, help="compaction level")
    parser.add_argument("--seed", type=int, default=2026, help="procedural room (the held-out seed)")
    parser.add_argument("--size", type=int, default=64, help="context image size")
    parser.add_argument("--view", type=int, default=384, help="picture size in pixels")
    parser.add_argument("--step-back", type=float, default=1.5, help="metres behind the middle camera")
    parser.add_argument("--splat-transform", default=SPLAT_TRANSFORM, help="command running splat-transform")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "viewer_check")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    tool = shlex.split(args.splat_transform)

    scene = make_scene(args.seed)
    path = make_trajectory(scene, torch.Generator().manual_seed(args.seed))
    context = path.cameras(torch.tensor([0.0, 1.0]), args.size, args.size)
    viewpoint = path.cameras(torch.tensor([0.5]), args.size, args.size).scaled(args.view / args.size)
    # Step back behind the cameras (through the unreconstructed wall behind them), so the whole
    # reconstruction is in view, as an orbit camera shows it.
    viewpoint.c2w[:, :3, 3] -= args.step_back * viewpoint.c2w[:, :3, 2]
    images = render_synthetic(scene, context, args.size, args.size, supersample=2).image

    model, label = load_model(ModelSpec(args.checkpoint), "cpu")
    model.eval()
    with torch.no_grad():
        prediction = model(images[None], context, scene.config.near, scene.config.far)
    full = prediction.gaussians.select(0).to(torch.float32)
    tau = prediction.alpha_threshold
    mode = decoder_mode(model.cfg.adapter)
    small = compact_surfels(full, context, args.size, args.size, args.level, mode=mode, alpha_threshold=tau).gaussians

    baked, bake_report = bake_for_viewers(full, context, args.size, args.size, mode=mode, alpha_threshold=tau)
    baked_small, small_report = bake_for_viewers(small, context, args.size, args.size, mode=mode, alpha_threshold=tau)

    ours = to_uint8(render(full, viewpoint, args.view, args.view, mode=mode, alpha_threshold=tau).color[0])
    # What a 3DGS viewer draws of the baked file: its Gaussians blended without forced alpha blending.
    plain = to_uint8(render(baked, viewpoint, args.view, args.view, mode="ewa", alpha_threshold=None).color[0])
    settings_file = args.out / "viewer_settings.json"
    settings_file.write_text(json.dumps(viewer_settings(viewpoint), indent=1))
    report = {
        "checkpoint": label,
        "level": args.level,
        "seed": args.seed,
        "viewer": " ".join(tool),
        "bake": {
            name: {k: v for k, v in r.to_dict().items() if k != "losses"}
            for name, r in (("full", bake_report), ("compact", small_report))
        },
        "files": {},
    }
    viewer = {}
    files = (("raw", thin_gaussians(full)), ("baked", baked), ("compact_baked", baked_small))
    for name, g in files:
        ply = save_ply(turned(g), args.out / f"{name}_3dgs.ply")
        summary = run(tool + [str(ply), "-m", "null"])
        rows = int(re.search(r"Row Count:\*\*\s*(\d+)", summary).group(1))
        page = args.out / f"{name}.html"
        run(tool + ["-w", "-g", "cpu", "-E", str(settings_file), str(ply), str(page)])
        viewer[name] = (screenshot(page, args.view), rows)
        report["files"][name] = {
            "surfels": len(g),
            "rows_read_by_splat_transform": rows,
            "ply_bytes": ply.stat().st_size,
        }
        if rows != len(g):
            raise SystemExit(f"splat-transform read {rows} splats from {ply}, expected {len(g)}")

    pictures = {
        "surfsplat renderer": ours,
        f"SuperSplat viewer, raw thin surfels ({viewer['raw'][1]:,} splats)": viewer["raw"][0],
        "surfsplat renderer as 3DGS (EWA, no alpha normalization), baked file": plain,
        f"SuperSplat viewer, baked ({viewer['baked'][1]:,} splats)": viewer["baked"][0],
        f"SuperSplat viewer, compacted and baked ({viewer['compact_baked'][1]:,} splats)": viewer["compact_baked"][0],
    }
    names = list(pictures)
    report["psnr_db"] = {
        "SuperSplat baked vs surfsplat as 3DGS of the baked file": picture_psnr(viewer["baked"][0], plain),
        "SuperSplat baked vs surfsplat renderer": picture_psnr(viewer["baked"][0], ours),
        "SuperSplat raw vs surfsplat renderer": picture_psnr(viewer["raw"][0], ours),
        "SuperSplat compacted and baked vs surfsplat renderer": picture_psnr(viewer["compact_baked"][0], ours),
    }
    iio.imwrite(args.out / "viewer_check.png", np.concatenate(list(pictures.values()), axis=1))
    (args.out / "viewer_check.json").write_text(json.dumps(report, indent=1) + "\n")
    print(json.dumps(report, indent=1))
    print(f"wrote {args.out / 'viewer_check.png'} ({' | '.join(names)})")


def turned(g: Gaussians) -> Gaussians:
    """`g` as thin 3D Gaussians (the 3DGS layout) turned by TURN: positions, covariances and SH."""
    R = TURN.to(g.means)
    return Gaussians(
        means=g.means @ R.T,
        quats=g.quats,
        scales=g.scales,
        opacities=g.opacities,
        sh=rotate_sh(g.sh, R),
        explicit_covariances=R @ g.covariances @ R.T,
    )


def viewer_settings(camera) -> dict:
    """SuperSplat viewer settings placing its camera at `camera` (one camera, square picture)."""
    c2w = camera.c2w[0].double()
    eye = TO_VIEWER.double() @ c2w[:3, 3]
    target = TO_VIEWER.double() @ (c2w[:3, 3] + 3 * c2w[:3, 2])  # orbit cameras keep a distance to it
    fov = math.degrees(2 * math.atan(float(camera.K[0, 1, 2]) / float(camera.K[0, 1, 1])))  # vertical
    return {
        "version": 2,
        "tonemapping": "none",
        "highPrecisionRendering": True,
        "background": {"color": [0.0, 0.0, 0.0]},
        "postEffectSettings": {
            "sharpness": {"enabled": False, "amount": 0},
            "bloom": {"enabled": False, "intensity": 1, "blurLevel": 2},
            "grading": {"enabled": False, "brightness": 0, "contrast": 1, "saturation": 1, "tint": [1, 1, 1]},
            "vignette": {"enabled": False, "intensity": 0.5, "inner": 0.3, "outer": 0.75, "curvature": 1},
            "fringing": {"enabled": False, "intensity": 0.5},
        },
        "animTracks": [],
        "cameras": [{"initial": {"position": eye.tolist(), "target": target.tolist(), "fov": fov}}],
        "annotations": [],
        "startMode": "default",
    }


def run(command: list[str]) -> str:
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{result.stdout}\n{result.stderr}")
    return result.stdout


def screenshot(page: Path, size: int) -> np.ndarray:
    """The page's canvas, its buttons hidden, once two captures a second apart are the same picture.

    Without an animation track in its settings the viewer makes one (an orbit around the scene, or
    a figure of eight inside it) and plays it from the initial camera; `noanim` keeps it paused
    there and `fullload` shows the splats once all are loaded, so the picture is taken from the
    settings' camera. "The same" is taken strictly (a still frame drawn in software repeats
    exactly)."""
    url = page.resolve().as_uri() + "?noanim&noui&fullload"
    with Browser(chromium(), url, size, size) as browser:
        browser.wait_for(lambda image: image.std() > 5, settle=5.0, timeout=120, alike=0.02)
        browser.call("Runtime.evaluate", expression=HIDE_UI)
        return browser.wait_for(lambda image: image.std() > 5, settle=2.0, timeout=120, alike=0.02)


def picture_psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB between two [H, W, 3] uint8 pictures (surfsplat.metrics.image.psnr)."""
    as_batch = lambda p: torch.from_numpy(p).permute(2, 0, 1)[None].double() / 255  # noqa: E731
    return float(psnr(as_batch(a), as_batch(b))[0])


if __name__ == "__main__":
    main()
