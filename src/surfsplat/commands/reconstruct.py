"""`surfsplat reconstruct`: photos, a folder or a video -> surfels, renders, depth and normal maps, videos, a mesh.

    surfsplat reconstruct --checkpoint runs/tiny --images a.png b.png --cameras cameras.json --out out/
    surfsplat reconstruct --checkpoint runs/tiny --images a.jpg b.jpg --out out/     # cameras estimated
    surfsplat reconstruct --checkpoint depthsplat_small.ckpt --trust-pickle --preset small \\
        --images scan24/images_4/000000.png scan24/images_4/000001.png --cameras scan24 --images-folder images_4

CAMS is a camera file or folder recognised by its content (see `surfsplat.data.cameras.load_cameras`):
a transforms.json of nerfstudio, instant-ngp or Blender, a COLMAP model (its folder or one of its files),
this package's camera file (reconstruct's cameras.json, accepted back with the photos it was written
for), or a scene folder of any format `load_scene` reads; the images are matched to its cameras by file
name, and frames the file lists without a photo are left out with one warning. Cameras with a lens
(COLMAP models 0-10, OPENCV / OPENCV_FISHEYE transforms) have their photos undistorted to a pinhole as
they are read. Images are rescaled and centre-cropped to a size
the network accepts (multiples of 16; `--size` to choose), with K following exactly. Without
`--cameras` the cameras are estimated from the images first (`surfsplat poses`): the output folder
then also holds estimated_cameras.json, poses.json and report.html (each photo beside its camera).

Many photos (`--images` with a folder or any number of files) and videos (`--video`) are cut into
forward passes of `--views-per-pass` neighbouring views and fused into one scene; the folder then
also holds capture.json and capture.html (every camera, the passes, held-out views with
`--holdout-every`, the video's frames and why unused ones were dropped).

This module only parses arguments: the work is `surfsplat.reconstruct` and `Scene.save`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from ..export.flow import FORMATS, output_names
from ..utils.checks import check_output_dir
from .export import add_export_arguments, options_from_args, print_written
from .options import add_cameras, add_depth_range, add_device, add_precision, add_release_options, add_size
from .poses import add_pose_arguments


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--checkpoint",
        default="tiny-synthetic",
        help="a weights name (`surfsplat weights list`, e.g. re10k-256x256-small), hf://owner/repo/file, "
        "our checkpoint (run folder, checkpoint folder or model.safetensors) or a release .ckpt/.pth "
        "(default: the shipped tiny-synthetic, as surfsplat.reconstruct)",
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--images", nargs="+", type=Path, help="two or more context images, or one folder of images")
    source.add_argument("--video", type=Path, help="a video of the scene (frames chosen by motion and sharpness)")
    add_cameras(
        parser,
        "camera file or folder, recognised by its content: a transforms.json (nerfstudio, instant-ngp, Blender), "
        "a COLMAP model (folder or its cameras/images file), reconstruct's cameras.json, or a scene folder "
        "(default: the cameras of a capture folder given as --images that holds a transforms.json or sparse/0, "
        "else estimated from the images)",
    )
    parser.add_argument("--out", type=Path, default=Path("outputs/reconstruction"), help="output folder")
    parser.add_argument(
        "--images-folder", default=None, help="image folder of a scene folder given as --cameras (e.g. images_4)"
    )
    add_size(parser, "network input size (multiples of 16; default: the largest crop of the images)")
    add_depth_range(
        parser,
        None,
        None,
        "nearest scene depth (default: from the cameras, else 0.5)",
        "farthest scene depth (default: from the cameras, else 100)",
    )
    add_release_options(parser)
    add_device(parser, "the network and every stage after it (fusion, refinement, bake, renders, mesh)")
    add_precision(parser)
    parser.add_argument(
        "--compile",
        action="store_true",
        help="run the encoder through torch.compile (its compilation takes minutes; pays over many captures)",
    )
    parser.add_argument("--formats", nargs="+", choices=FORMATS, default=list(FORMATS), help="what to write")
    add_export_arguments(parser)
    add_pose_arguments(parser)
    group = parser.add_argument_group("many views and videos")
    group.add_argument("--views-per-pass", type=int, default=3, help="context views of one forward pass (default 3)")
    group.add_argument(
        "--holdout-every",
        type=int,
        default=None,
        metavar="K",
        help="keep views 0, K, 2K, ... out of the passes and render them from the fused scene",
    )
    group.add_argument("--max-frames", type=int, default=None, help="video: at most this many frames (evenly spaced)")
    group.add_argument(
        "--min-motion",
        type=float,
        default=0.02,
        help="video: a frame is used when it differs from the last used one by this much (mean grey, 0..1)",
    )
    from ..capture import RefineConfig

    refine = RefineConfig()
    group.add_argument(
        "--refine-steps",
        type=int,
        default=None,
        metavar="N",
        help="steps fitting a fused scene's colours, opacities and sizes to its context views, "
        f"{refine.views_per_step} views each (0: none; default: each view fitted {refine.fits_per_view:g} times)",
    )
    group.add_argument(
        "--refine-scale",
        type=float,
        default=refine.scale,
        metavar="S",
        help=f"the refinement renders at this fraction of the working size (default {refine.scale:g})",
    )
    add_optimize_arguments(group)


def add_optimize_arguments(group, continuing: bool = False) -> None:
    """--optimize-steps, --optimize-seconds, --optimize-start, --optimize-scale, --optimize-strategy and the per-photo terms: the per-scene
    optimization (reconstruct, and optimize, whose default start continues the saved fit)."""
    from ..capture import OptimizeConfig
    from ..capture.optimize import MAX_STEPS, MIN_STEPS, STRATEGIES, VIEW_PIXELS_PER_STEP
    from ..capture.starts import START_KINDS, StartConfig

    optimize = OptimizeConfig()
    group.add_argument(
        "--optimize-steps",
        type=int,
        default=None,
        metavar="N",
        help="steps of the per-scene optimization (every surfel's position, rotation, size, opacity and colour "
        "fitted to the context photos, the surfels grown and pruned as 3DGS does; it replaces the refinement); "
        f"0: none (the network's pass and the refinement alone); default for three context views or more one "
        f"step per {VIEW_PIXELS_PER_STEP:,} pixels of the context views (their number times the working size), "
        f"{MIN_STEPS:,} to {MAX_STEPS:,}; none for two",
    )
    group.add_argument(
        "--optimize-seconds",
        type=float,
        default=None,
        metavar="S",
        help="a time budget for the optimization instead of a step count: it runs S seconds, its schedules "
        "(resolution, rates, growth) following the time spent",
    )
    if continuing:
        group.add_argument(
            "--optimize-start",
            choices=START_KINDS,
            default="continue",
            help="continue from the saved surfels (the default), or restart from points COLMAP triangulates "
            "from the photos, the saved surfels thinned as the network's are (network), both, or auto",
        )
    else:
        group.add_argument(
            "--optimize-start",
            choices=tuple(k for k in START_KINDS if k != "continue"),
            default=StartConfig().kind,
            help="what the optimization starts from: points COLMAP triangulates from the photos, the network's "
            f"surfels, or both (default {StartConfig().kind}: the points where COLMAP finds enough; the "
            "network's passes run only where its surfels start the optimization)",
        )
    group.add_argument(
        "--optimize-scale",
        type=float,
        default=optimize.scale,
        metavar="S",
        help=f"the optimization renders at this fraction of the working size (default {optimize.scale:g})",
    )
    group.add_argument(
        "--optimize-appearance",
        action=argparse.BooleanOptionalAction,
        default=optimize.appearance,
        help="fit an affine exposure map per context photo beside the surfels (3DGS's exposure); held-out "
        "views are then scored by 3DGS's train_test_exp protocol (map fitted on the photo's left half, "
        f"figures on the right half) (default {'on' if optimize.appearance else 'off'})",
    )
    group.add_argument(
        "--optimize-cameras",
        choices=("auto", "on", "off"),
        default={True: "on", False: "off"}.get(optimize.refine_cameras, "auto"),
        help="refine each context camera (rotation and translation, the first camera fixed) beside the surfels, "
        "and align the held-out cameras to their photos before scoring; auto: where the cameras were "
        "estimated from the photos",
    )
    group.add_argument(
        "--optimize-antialiased",
        action="store_true",
        help="fit with the antialiasing filter (each surfel's opacity compensated for the pixel-sized widening, "
        "Mip-Splatting's 2D filter), so renders at other sizes stay consistent; the scene keeps it for every "
        "later render",
    )
    group.add_argument(
        "--optimize-strategy",
        choices=sorted(STRATEGIES),
        default=optimize.strategy,
        help="how the optimization grows the surfels: 3dgs (clone and split where the screen gradient is high), "
        "absgs (the same with the absolute screen gradient of AbsGS), mcmc (3DGS-MCMC: faint surfels relocated "
        "under a fixed budget), auto (absgs; 3dgs on the gsplat backend, which cannot give the absolute "
        f"gradient of surfels) (default {optimize.strategy})",
    )
    group.add_argument(
        "--optimize-seed",
        type=int,
        default=optimize.seed,
        metavar="N",
        help=f"seed of the optimization (which views each step renders, the splits' samples); a fit repeats bit "
        f"for bit with the same seed (default {optimize.seed})",
    )


def optimize_from_args(args: argparse.Namespace):
    """The OptimizeConfig of the --optimize-* flags."""
    from ..capture import OptimizeConfig

    config = OptimizeConfig()
    return dataclasses.replace(
        config,
        steps=args.optimize_steps,
        seconds=args.optimize_seconds,
        scale=args.optimize_scale,
        antialiased=args.optimize_antialiased,
        start=dataclasses.replace(config.start, kind=args.optimize_start),
        appearance=args.optimize_appearance,
        refine_cameras={"on": True, "off": False, "auto": "auto"}[args.optimize_cameras],
        strategy=args.optimize_strategy,
        seed=args.optimize_seed,
    )


def run(args: argparse.Namespace) -> int:
    from ..capture import FrameConfig, RefineConfig, optimize_summary, refine_summary
    from ..reconstruction import CaptureOptions, reconstruct
    from ..reconstruction.scene import SUMMARY_FILES

    # The output folder first: nothing heavy runs before a bad --out is refused.
    given = [args.video] if args.video is not None else list(args.images)
    check_output_dir(
        args.out, "--out", inputs=[*given, args.cameras], writes=[*output_names(args.formats), *SUMMARY_FILES]
    )

    if args.video is not None:
        images = args.video
    elif len(args.images) == 1 and args.images[0].is_dir():
        images = args.images[0]
    else:
        images = args.images
    capture = CaptureOptions(
        views_per_pass=args.views_per_pass,
        holdout_every=args.holdout_every,
        frames=FrameConfig(max_size=min(args.max_size, 960), min_motion=args.min_motion, max_frames=args.max_frames),
        refine=dataclasses.replace(RefineConfig(), steps=args.refine_steps, scale=args.refine_scale),
        optimize=optimize_from_args(args),
    )
    scene = reconstruct(
        images,
        checkpoint=args.checkpoint,
        # not given: a processed capture folder's own cameras (transforms.json, sparse/0), else estimated
        cameras=args.cameras if args.cameras is not None else "auto",
        device=args.device,
        size=tuple(args.size) if args.size else None,
        near=args.near,
        far=args.far,
        preset=args.preset,
        trust_pickle=args.trust_pickle,
        images_folder=args.images_folder,
        focal=args.focal,
        camera_model=args.camera_model,
        max_size=args.max_size,
        compact=args.compact,
        capture=capture,
        progress=not args.no_progress,
        precision=args.precision,
        compile=args.compile,
    )
    if scene.video is not None:
        print("\n".join(scene.video.lines()))
    if scene.lenses is not None:
        print("\n".join(scene.lens_lines()))
    if scene.poses is not None:
        print("\n".join(scene.poses.lines()))
    if scene.network != "ran":
        print(f"network: {scene.network}")
    if scene.compact_stats:
        s = scene.compact_stats
        print(
            f"compact level {args.compact}: {s['input']:,} -> {s['output']:,} surfels ({s['input'] / s['output']:.2f}x "
            f"fewer; {s['pruned']:,} pruned, {s['duplicates']:,} duplicates, {s['merged_away']:,} merged away)"
        )
    if scene.fusion_stats:
        f = scene.fusion_stats
        print(
            f"fused {f['passes']} passes of {len(scene.names)} views: {f['predicted']:,} surfels predicted, "
            f"{f['duplicates']:,} duplicates removed, {f.get('replaced', 0):,} replaced by closer views, "
            f"{int(scene.optimize_stats.get('surfels_before', len(scene.gaussians))):,} kept"
        )
    if scene.refine_stats:
        print(refine_summary(scene.refine_stats))
    if scene.optimize_stats:
        print(optimize_summary(scene.optimize_stats))
    if scene.holdout is not None:
        print_held_out(scene.holdout)
    options = options_from_args(args, tuple(args.formats), scene.mode)
    options = dataclasses.replace(options, alpha_threshold=scene.alpha_threshold, antialiased=scene.antialiased)
    written = scene.save(args.out, options=options)
    summary = json.loads(written["summary"].read_text())
    c = summary["closure"]
    print(
        f"closure {c['closure']:.3f} (alpha x4 / x1 from the context views), {c['undersized_share']:.0%} of surfels "
        f"under half their pixel footprint, median opacity {c['opacity_quantiles']['p50']:.2f}"
        + ("" if c["closed"] else f": not closed ({'; '.join(c['problems'])})")
    )
    from ..reconstruction.report import seconds_line

    print("seconds: " + seconds_line(summary["seconds"]))
    print(f"wrote {args.out}/:")
    print_written(written)
    return 0


def print_held_out(holdout) -> None:
    """The held-out views' figures, before the optimization too where it ran."""
    h = holdout.to_dict()
    lpips = f", LPIPS {h['mean_lpips']:.3f}" if h["mean_lpips"] is not None else ""
    line = (
        f"held out {len(holdout.names)} views: PSNR {h['mean_psnr']:.2f} dB, SSIM {h['mean_ssim']:.3f}{lpips}, "
        f"coverage {h['mean_coverage']:.3f}"
    )
    if holdout.before is not None:
        line += f" (before the optimization: PSNR {holdout.before['mean_psnr']:.2f} dB, SSIM {holdout.before['mean_ssim']:.3f})"
    print(line)
    if holdout.zoom is not None:
        from ..reconstruction.report import zoom_line

        print(zoom_line(holdout.zoom, holdout.zoom.get("antialiased", False)))
    if holdout.lpips_note:
        print(holdout.lpips_note)
