"""`surfsplat export PLY --cameras CAMS`: PLY, mesh and videos from a reconstruction saved earlier.

    surfsplat export out/surfels.ply --cameras out/cameras.json --formats mesh video --out out/export

It writes the files of `surfsplat.export.flow.export_reconstruction` (see its module for the list),
as `reconstruct` and `demo` do.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import torch

from ..compaction import DEFAULT_LEVEL, LEVELS
from ..export.bake import BakeConfig
from ..export.flow import FORMATS, ExportOptions, export_reconstruction, output_names
from ..utils.checks import SurfSplatInputError, check_output_dir
from .options import add_cameras, add_device

logger = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("ply", type=Path, help="surfels written by reconstruct (surfels.ply)")
    add_cameras(
        parser,
        "the reconstruction's cameras.json, another JSON camera file, a COLMAP model or a scene folder",
        required=True,
    )
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: beside the PLY)")
    parser.add_argument("--formats", nargs="+", choices=FORMATS, default=["ply", "video", "mesh"], help="what to write")
    add_device(parser, "the compaction, bake, renders and mesh")
    add_export_arguments(parser)


def add_export_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by reconstruct and export."""
    group = parser.add_argument_group("renders, videos and mesh")
    group.add_argument("--scale", type=float, default=1.0, help="render resolution factor for images and videos")
    group.add_argument("--frames", type=int, default=48, help="frames of the interpolated path and of the turntable")
    group.add_argument("--degrees", type=float, default=30.0, help="total sweep of the turntable")
    group.add_argument("--fps", type=float, default=24.0)
    group.add_argument("--mesh-resolution", type=int, default=128, help="TSDF voxels along the longest side")
    group.add_argument(
        "--mode",
        choices=("surfel", "ewa"),
        default=None,
        help="rasterization (default: surfel; ewa for 3DGS-layout files)",
    )
    group.add_argument(
        "--alpha-threshold",
        type=float,
        default=0.001,
        help="forced alpha blending tau (paper Sec. 3.4; reconstruct uses the model's); negative turns it off",
    )
    group.add_argument(
        "--raw-3dgs",
        action="store_true",
        help="write surfels_3dgs.ply as the thin surfels are, without baking it for standard 3DGS viewers "
        "(which then show it faint: they do not apply forced alpha blending)",
    )
    add_compact_argument(
        group,
        f"fewer surfels for the same picture (surfsplat.compact): level 1 (gentle) to 5 (strong); "
        f"{DEFAULT_LEVEL} when no level is given",
    )
    group.add_argument("--no-progress", action="store_true")


def add_compact_argument(group: argparse._ActionsContainer, help_text: str) -> None:
    """`--compact [LEVEL]`: a compaction level of `surfsplat.compact`, the default level when none is given."""
    group.add_argument(
        "--compact",
        nargs="?",
        type=int,
        const=DEFAULT_LEVEL,
        default=None,
        choices=sorted(LEVELS),
        metavar="LEVEL",
        help=help_text,
    )


def options_from_args(args: argparse.Namespace, formats: tuple[str, ...], mode: str) -> ExportOptions:
    return ExportOptions(
        formats=formats,
        scale=args.scale,
        path_frames=args.frames,
        turntable_frames=args.frames,
        turntable_degrees=args.degrees,
        fps=args.fps,
        mesh_resolution=args.mesh_resolution,
        mode=args.mode or mode,
        progress=not args.no_progress,
        alpha_threshold=None if args.alpha_threshold < 0 else args.alpha_threshold,
        bake=None if args.raw_3dgs else BakeConfig(),
    )


def run(args: argparse.Namespace) -> int:
    from ..data.cameras import load_cameras
    from ..export.ply import load_ply
    from ..reconstruction.pipeline import resolve_device

    if not args.ply.is_file():
        raise FileNotFoundError(f"{args.ply}: no such PLY file")
    out = args.out or args.ply.parent
    # cameras.json is left out of the clash check: written from the cameras read, it holds what an
    # input cameras.json in the same place already held.
    writes = [name for name in output_names(args.formats) if name != "cameras.json"]
    option = "--out" if args.out is not None else "--out (default: the PLY's folder)"
    check_output_dir(out, option, inputs=[args.ply, args.cameras], writes=writes)
    device = resolve_device(args.device)
    cams = load_cameras(args.cameras)
    cameras = cams.cameras.to(device, torch.float32)
    gaussians = load_ply(args.ply).to(device)  # read on the host, then every step runs on the device
    mode = "ewa" if gaussians.explicit_covariances is not None else "surfel"
    options = options_from_args(args, tuple(args.formats), mode)
    gaussians = compact_from_args(args, gaussians, cameras, cams.height, cams.width, options)
    written = export_reconstruction(
        gaussians,
        cameras,
        cams.width,
        cams.height,
        out,
        options,
        names=cams.names,
        near=cams.near,
        far=cams.far,
        write_surfels="ply" in options.formats,
        crop=cams.crop,
        lenses=cams.lenses,
    )
    print_written(written)
    return 0


def compact_from_args(args: argparse.Namespace, gaussians, cameras, height: int, width: int, options: ExportOptions):
    """`--compact LEVEL`: the compacted surfels (unchanged without the option), with a one-line summary."""
    if args.compact is None:
        return gaussians
    from ..compaction import compact_surfels

    expected = len(cameras) * height * width
    if len(gaussians) != expected:
        raise SurfSplatInputError(
            f"--compact: expected the uncompacted reconstruction, one surfel per pixel of {len(cameras)} context "
            f"views of {width}x{height} ({expected:,}), got {len(gaussians):,} surfels"
        )
    result = compact_surfels(
        gaussians, cameras, height, width, args.compact, mode=options.mode, alpha_threshold=options.alpha_threshold
    )
    s = result.stats
    print(
        f"compact level {args.compact}: {s['input']:,} -> {s['output']:,} surfels ({s['input'] / s['output']:.2f}x fewer; "
        f"{s['pruned']:,} pruned, {s['duplicates']:,} duplicates, {s['merged_away']:,} merged away)"
    )
    return result.gaussians


def print_written(written: dict[str, Path]) -> None:
    width = max(len(k) for k in written)
    for key, path in written.items():
        print(f"  {key.ljust(width)}  {path}")
