"""`surfsplat reconstruct`: posed photos -> surfels, renders, depth and normal maps, videos, a mesh.

    surfsplat reconstruct --checkpoint runs/tiny --images a.png b.png --cameras cameras.json --out out/
    surfsplat reconstruct --checkpoint runs/tiny --images a.jpg b.jpg --out out/     # cameras estimated
    surfsplat reconstruct --checkpoint depthsplat_small.ckpt --trust-pickle --preset small \\
        --images scan24/images_4/000000.png scan24/images_4/000001.png --cameras scan24 --images-folder images_4

CAMS is a JSON camera file (see `surfsplat.export.paths.load_cameras`), a COLMAP model folder, or a
scene folder of any format `load_scene` reads (LLFF, DTU, transforms.json, COLMAP, RE10K); the
images are matched to its cameras by file name. Images are rescaled and centre-cropped to a size
the network accepts (multiples of 16; `--size` to choose), with K following exactly. Without
`--cameras` the cameras are estimated from the images first (`surfsplat poses`): the output folder
then also holds estimated_cameras.json, poses.json and report.html (each photo beside its camera).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import time
from pathlib import Path

import torch

from ..checks import SurfSplatInputError, check_output_dir
from ..precision import PRECISIONS, autocast
from .export import (
    FORMATS,
    add_export_arguments,
    compact_from_args,
    export_reconstruction,
    options_from_args,
    output_names,
    print_written,
)
from .poses import add_pose_arguments, estimate_from_args

logger = logging.getLogger(__name__)

# Written beside the export's files; reconstruction.json last, so it marks a finished run.
SUMMARY_FILES = ("estimated_cameras.json", "poses.json", "report.html", "reconstruction.json")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--checkpoint",
        required=True,
        help="a weights name (`surfsplat weights list`, e.g. re10k-256x256-small), hf://owner/repo/file, "
        "our checkpoint (run folder, checkpoint folder or model.safetensors) or a release .ckpt/.pth",
    )
    parser.add_argument("--images", nargs="+", required=True, type=Path, help="two or more context images")
    parser.add_argument(
        "--cameras",
        default=None,
        type=Path,
        help="JSON camera file, COLMAP model or scene folder (default: estimate them from the images)",
    )
    parser.add_argument("--out", type=Path, default=Path("outputs/reconstruction"), help="output folder")
    parser.add_argument(
        "--images-folder", default=None, help="image folder of a scene folder given as --cameras (e.g. images_4)"
    )
    parser.add_argument(
        "--size",
        nargs=2,
        type=int,
        metavar=("H", "W"),
        default=None,
        help="network input size (multiples of 16; default: the largest crop of the images)",
    )
    parser.add_argument(
        "--near", type=float, default=None, help="nearest scene depth (default: from the cameras, else 0.5)"
    )
    parser.add_argument(
        "--far", type=float, default=None, help="farthest scene depth (default: from the cameras, else 100)"
    )
    parser.add_argument(
        "--preset", default=None, help="encoder preset of a release .ckpt/.pth given by path (default small)"
    )
    parser.add_argument(
        "--trust-pickle", action="store_true", help="allow unpickling a release .ckpt's hyper-parameters"
    )
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    parser.add_argument(
        "--precision",
        choices=PRECISIONS,
        default="auto",
        help="forward-pass precision (auto: bf16 where the device has fast bf16, else fp32); rendering is fp32",
    )
    parser.add_argument("--formats", nargs="+", choices=FORMATS, default=list(FORMATS), help="what to write")
    add_export_arguments(parser)
    add_pose_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from ..data.images import read_image
    from ..data.transforms import rescale_and_crop
    from ..evaluate import ModelSpec, load_model
    from ..export.paths import load_cameras
    from ..geometry.cameras import Cameras
    from ..model.pretrained import check_resolution

    # ---- validate every input and the output folder before any heavy work
    check_output_dir(
        args.out, "--out", inputs=[*args.images, args.cameras], writes=[*output_names(args.formats), *SUMMARY_FILES]
    )
    if len(args.images) < 2:
        raise SurfSplatInputError(
            f"--images: the model matches views, expected at least 2 images, got {len(args.images)}"
        )
    for path in args.images:
        if not path.is_file():
            raise FileNotFoundError(f"{path}: image file not found")
    photos, poses = list(args.images), None
    if args.cameras is None:  # estimated (nothing is written before the reconstruction succeeds)
        cams, poses = estimate_from_args(args)
        args.images = [p for p in args.images if p.name in cams.names]
    else:
        if args.focal is not None:
            raise SurfSplatInputError("--focal: only used when the cameras are estimated (without --cameras)")
        cams = load_cameras(args.cameras, images=args.images_folder).select(
            [p.name for p in args.images], str(args.cameras)
        )
    images = []
    for path in args.images:
        rgb, _ = read_image(path, background=(0.0, 0.0, 0.0))
        images.append(rgb)
    sizes = {tuple(im.shape[1:]) for im in images}
    if len(sizes) != 1:
        raise SurfSplatInputError(f"--images: all images must have one size, got {sorted(sizes)}")
    ((height, width),) = sizes
    K = cams.resized(width, height, str(args.cameras)).K
    near, far = _depth_range(args, cams)
    device = _device(args.device)
    model, label = load_model(ModelSpec(args.checkpoint, preset=args.preset, trust_pickle=args.trust_pickle), device)
    m = model.cfg.encoder.size_multiple
    if args.size is None and (height < m or width < m):  # the user gave images, not a size: name them
        raise SurfSplatInputError(
            f"--images: {args.images[0]} is {width}x{height} pixels; the network needs at least {m}x{m}"
        )
    shape = tuple(args.size) if args.size else (height // m * m, width // m * m)
    if shape[0] < m or shape[1] < m or shape[0] % m or shape[1] % m:
        raise SurfSplatInputError(f"--size: expected multiples of {m} of at least {m}, got {shape[0]}x{shape[1]}")
    stack, K, _ = rescale_and_crop(torch.stack(images), K.to(torch.float32), shape)
    check_resolution(model, *shape)  # named weights know the resolution they were trained at
    cameras = Cameras(cams.cameras.c2w.to(torch.float32), K)

    # ---- reconstruct
    start = time.perf_counter()
    with torch.no_grad(), autocast(args.precision, device) as precision:
        prediction = model(stack[None].clamp(0, 1).to(device), cameras.to(device), near, far)
    seconds = time.perf_counter() - start
    gaussians = prediction.gaussians.select(0).to("cpu", torch.float32)
    logger.info(
        f"{label}: {len(gaussians):,} surfels from {len(args.images)} views at {shape[1]}x{shape[0]} in {seconds:.2f} s"
    )

    from ..model.decoder import decoder_mode

    mode = decoder_mode(model.cfg.adapter)
    options = options_from_args(args, tuple(args.formats), mode)
    options = dataclasses.replace(options, alpha_threshold=prediction.alpha_threshold)
    gaussians = compact_from_args(args, gaussians, cameras, shape[0], shape[1], options)
    written = export_reconstruction(
        gaussians,
        cameras,
        shape[1],
        shape[0],
        args.out,
        options,
        names=[p.name for p in args.images],
        near=near,
        far=far,
    )
    from ..export.figures import write_text

    if poses is not None:
        from ..poses.report import write_pose_outputs

        renders = [args.out / "renders" / f"view{i:02d}_color.png" for i in range(len(args.images))]
        renders = renders if "context renders" in written else None
        written.update(write_pose_outputs(args.out, cams, poses, photos, renders))
    summary = {
        "checkpoint": str(args.checkpoint),
        "model": label,
        "images": [str(p) for p in args.images],
        "size": list(shape),
        "near": near,
        "far": far,
        "surfels": len(gaussians),
        "compact_level": args.compact,
        "seconds_forward": seconds,
        "precision": precision,
        "render_mode": mode,
        "alpha_threshold": prediction.alpha_threshold,
        "files": {k: str(v) for k, v in written.items()},
        "cameras": str(args.cameras) if args.cameras is not None else "estimated from the images (poses.json)",
    }
    written["summary"] = write_text(args.out / "reconstruction.json", json.dumps(summary, indent=1) + "\n")
    print(f"wrote {args.out}/:")
    print_written(written)
    return 0


def _depth_range(args: argparse.Namespace, cams) -> tuple[float, float]:
    near = args.near if args.near is not None else (cams.near if cams.near is not None else 0.5)
    far = args.far if args.far is not None else (cams.far if cams.far is not None else 100.0)
    if not 0 < near < far:
        raise SurfSplatInputError(f"--near/--far: expected 0 < near < far, got {near}, {far}")
    return float(near), float(far)


def _device(choice: str) -> torch.device:
    if choice == "cuda" and not torch.cuda.is_available():
        raise SurfSplatInputError("--device cuda: no CUDA device is available")
    if choice == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(choice)
