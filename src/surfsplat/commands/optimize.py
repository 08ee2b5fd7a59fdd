"""`surfsplat optimize OUTPUT_DIR`: the per-scene optimization of a reconstruction saved earlier.

    surfsplat reconstruct --images photos/ --cameras cams.json --out out/ --formats ply
    surfsplat optimize out/ --optimize-seconds 300 --out out_optimized/     # the saved surfels, continued
    surfsplat optimize out/ --optimize-start points                          # restarted from COLMAP's points

It reads what `reconstruct` saved (surfels.ply, cameras.json, reconstruction.json and the context
photos it names), optimizes every surfel on those photos (`surfsplat.capture.OptimizeConfig`),
continuing from the saved surfels unless another start is asked for, and writes a reconstruction
folder again, which `optimize`, `export` and `view` read like any other. The result is compared
with its input (held-out PSNR where the reconstruction kept views out, else the context views'):
one line says which is better, and a worse result says so in its reconstruction.json
(`worse_than_input`); it never replaces its input. This module only parses arguments: the work is
`surfsplat.reconstruction.optimize_saved`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..export.flow import FORMATS
from ..utils.checks import SurfSplatInputError, check_output_dir
from .export import print_written
from .options import add_device
from .reconstruct import add_optimize_arguments, optimize_from_args


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("folder", type=Path, help="a folder written by surfsplat reconstruct (with the ply format)")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: FOLDER_optimized beside it)")
    parser.add_argument(
        "--formats", nargs="+", choices=FORMATS, default=["ply", "renders"], help="what to write (default ply renders)"
    )
    parser.add_argument(
        "--raw-3dgs", action="store_true", help="write surfels_3dgs.ply as the surfels are, without baking it"
    )
    parser.add_argument("--no-progress", action="store_true")
    add_device(parser, "the optimization, bake and renders")
    add_optimize_arguments(parser, continuing=True)


def run(args: argparse.Namespace) -> int:
    from ..capture import optimize_summary
    from ..reconstruction.scene_fit import optimize_saved, versus_input_line

    if not args.folder.is_dir():
        raise FileNotFoundError(f"{args.folder}: no such reconstruction folder")
    if args.optimize_steps is not None and args.optimize_steps < 1:
        raise SurfSplatInputError(f"--optimize-steps: expected at least 1 step, got {args.optimize_steps}")
    out = args.out if args.out is not None else args.folder.with_name(args.folder.name + "_optimized")
    check_output_dir(out, "--out", inputs=[args.folder])
    scene, written = optimize_saved(
        args.folder,
        out,
        optimize_from_args(args),
        formats=tuple(args.formats),
        bake=not args.raw_3dgs,
        progress=not args.no_progress,
        device=args.device,
    )
    print(optimize_summary(scene.optimize_stats))
    print(versus_input_line(scene.optimize_stats))
    print(f"wrote {out}/:")
    print_written(written)
    return 0
