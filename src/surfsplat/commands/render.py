"""`surfsplat render PLY --cameras CAMS --scale 4`: render saved surfels at any resolution.

    surfsplat render out/surfels.ply --cameras out/cameras.json --scale 4 --out out/x4

Renders every camera of CAMS (a JSON camera file such as reconstruct's cameras.json, a COLMAP
model or a scene folder) at `--scale` times its calibrated size with K' = diag(s, s, 1) K, and
writes colour, colour-mapped depth and normal PNGs per view plus render.json (sizes, timing,
coverage).
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import torch

from ..utils.checks import SurfSplatInputError, check_output_dir
from ..utils.log import progress
from .options import add_cameras, add_device

logger = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("ply", type=Path, help="surfels (2DGS or 3DGS layout PLY)")
    add_cameras(parser, "JSON camera file, COLMAP model or scene folder", required=True)
    parser.add_argument("--scale", type=float, default=1.0, help="resolution factor over the cameras' image size")
    parser.add_argument(
        "--views", nargs="+", type=int, default=None, help="indices of the cameras to render (default: all)"
    )
    parser.add_argument("--out", type=Path, default=Path("outputs/render"), help="output folder")
    parser.add_argument(
        "--mode",
        choices=("surfel", "ewa"),
        default=None,
        help="rasterization (default: surfel; ewa for files carrying 3D covariances)",
    )
    parser.add_argument(
        "--alpha-threshold",
        type=float,
        default=0.001,
        help="forced alpha blending tau (paper Sec. 3.4); a negative value turns it off",
    )
    parser.add_argument(
        "--antialiased",
        action="store_true",
        help="the antialiasing filter (for a scene fitted with it: reconstruction.json's 'antialiased')",
    )
    add_device(parser, "the renders")
    parser.add_argument("--background", nargs=3, type=float, default=[0.0, 0.0, 0.0], metavar=("R", "G", "B"))
    parser.add_argument("--images-folder", default=None, help="image folder of a scene folder given as --cameras")


def run(args: argparse.Namespace) -> int:
    from ..data.cameras import load_cameras
    from ..export.images import colorize_depth, normal_to_rgb, write_png
    from ..export.ply import load_ply
    from ..reconstruction.pipeline import resolve_device
    from ..render import render

    if not args.ply.is_file():
        raise FileNotFoundError(f"{args.ply}: no such PLY file")
    if not args.scale > 0:
        raise SurfSplatInputError(f"--scale: expected a positive factor, got {args.scale}")
    if any(not 0 <= c <= 1 for c in args.background):
        raise SurfSplatInputError(f"--background: expected colours in [0, 1], got {args.background}")
    device = resolve_device(args.device)
    cams = load_cameras(args.cameras, images=args.images_folder)
    views = args.views if args.views is not None else list(range(len(cams.cameras)))
    bad = [v for v in views if not 0 <= v < len(cams.cameras)]
    if bad:
        raise SurfSplatInputError(f"--views: {bad} out of range for {len(cams.cameras)} cameras")
    stems = [Path(cams.names[v]).stem for v in views]
    writes = [f"{s}_{kind}.png" for s in stems for kind in ("color", "depth", "normal")] + ["render.json"]
    check_output_dir(args.out, "--out", inputs=[args.ply, args.cameras], writes=writes)
    gaussians = load_ply(args.ply).to(device)
    mode = args.mode or ("ewa" if gaussians.explicit_covariances is not None else "surfel")
    tau = None if args.alpha_threshold < 0 else args.alpha_threshold
    width, height = round(cams.width * args.scale), round(cams.height * args.scale)
    if width < 1 or height < 1:
        raise SurfSplatInputError(f"--scale: {args.scale} gives an empty {width}x{height} image")
    cameras = cams.cameras.to(device, torch.float32).scaled(args.scale)
    report = {
        "ply": str(args.ply),
        "surfels": len(gaussians),
        "mode": mode,
        "antialiased": args.antialiased,
        "scale": args.scale,
        "width": width,
        "height": height,
        "views": [],
    }
    for v in progress(views, desc=f"render x{args.scale:g}", unit="view", enabled=len(views) >= 2):
        start = time.perf_counter()
        with torch.inference_mode():
            r = render(
                gaussians,
                cameras[v],
                width,
                height,
                mode=mode,
                alpha_threshold=tau,
                background=args.background,
                antialiased=args.antialiased,
            )
        seconds = time.perf_counter() - start
        stem = Path(cams.names[v]).stem
        write_png(args.out / f"{stem}_color.png", r.color[0])
        write_png(args.out / f"{stem}_depth.png", colorize_depth(r.depth[0], r.alpha[0]))
        write_png(args.out / f"{stem}_normal.png", normal_to_rgb(r.normal[0]))
        coverage = float((r.alpha[0] > 0.5).float().mean())
        report["views"].append({"name": cams.names[v], "seconds": seconds, "coverage": coverage})
        logger.info(f"{cams.names[v]}: {width}x{height} in {seconds:.2f} s, coverage {coverage:.3f}")
    from ..export.figures import write_text

    write_text(args.out / "render.json", json.dumps(report, indent=1) + "\n")  # last: the folder is complete
    print(f"wrote {args.out}/ ({len(views)} views: *_color.png, *_depth.png, *_normal.png, render.json)")
    return 0
