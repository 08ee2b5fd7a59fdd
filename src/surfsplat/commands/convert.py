"""`surfsplat convert {dtu,llff,blender,colmap,dl3dv,scannet} SRC OUT`: raw layouts -> chunks."""

from __future__ import annotations

import argparse
import logging

logger = logging.getLogger(__name__)

# The formats of surfsplat.data.convert.CONVERTERS, spelled out so `surfsplat --help` does not
# import the data stack (a test keeps the two equal).
FORMATS = ("dtu", "llff", "blender", "colmap", "dl3dv", "scannet")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("format", choices=FORMATS, help="layout of SRC")
    parser.add_argument("src", help="one scene folder, or a folder of scene folders")
    parser.add_argument("out", help="output folder for *.torch chunks and index.json (must hold no chunks)")
    parser.add_argument(
        "--images",
        default=None,
        help="image folder name inside each scene (e.g. images_8 for LLFF; DL3DV default images_8)",
    )
    parser.add_argument(
        "--image-format",
        choices=("png", "jpeg"),
        default="png",
        help="encoding of re-encoded images (dtu/llff/blender/colmap; dl3dv and scannet copy files as they are)",
    )
    parser.add_argument("--quality", type=int, default=95, help="JPEG quality")
    parser.add_argument("--chunk-mb", type=float, default=100.0, help="approximate size of one chunk in MB")
    parser.add_argument("--frame-step", type=int, default=1, help="ScanNet: keep every N-th frame")
    parser.add_argument(
        "--skip-bad", action="store_true", help="skip scenes that fail to read and list them, instead of stopping"
    )
    parser.add_argument("--append", action="store_true", help="add to a folder that already holds chunks")


def run(args: argparse.Namespace) -> int:
    from ..data.convert import convert
    from ..utils.checks import check_output_dir

    check_output_dir(args.out, "OUT", inputs=[args.src])

    report = convert(
        args.format,
        args.src,
        args.out,
        images=args.images,
        image_format=args.image_format,
        quality=args.quality,
        target_bytes=int(args.chunk_mb * 1e6),
        frame_step=args.frame_step,
        skip_bad=args.skip_bad,
        append=args.append,
    )
    print(f"{args.out}: {report}")
    if report.skipped:
        logger.warning(f"{len(report.skipped)} scenes or frame groups skipped (listed above)")
    return 0
