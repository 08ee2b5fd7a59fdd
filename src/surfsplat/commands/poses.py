"""`surfsplat poses`: camera file from photos alone (no calibration, no poses needed).

    surfsplat poses photos/*.jpg --out cameras.json
    surfsplat poses a.png b.png --out cameras.json --focal 723 --max-size 1200

Writes the JSON camera file `load_cameras` reads (OpenCV camera-to-world, near/far; K of the pinhole
the photos are undistorted to, and each frame's fitted lens as "lens": COLMAP model, size and
parameters) and prints what happened: images registered, matches and inliers per pair, 3D points,
mean reprojection error, the focal length and where it came from, the camera model fitted and why
(photos of several sizes: a camera per size, each frame's "lens" that of its size). World frame: the first
registered photo's camera; unit of length: the median depth of the points it sees is 4. See
`surfsplat.poses` for the pipeline.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..utils.checks import SurfSplatInputError, check_output_file
from .options import add_depth_range

# PoseConfig.camera_model's values (surfsplat.poses.estimate.FITTED_MODELS), kept here so that --help needs no pycolmap
CAMERA_MODEL_CHOICES = ("auto", "SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def add_pose_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared with `reconstruct` when it estimates cameras itself."""
    parser.add_argument(
        "--focal", type=float, default=None, help="focal length in pixels of the photos (default: EXIF, else estimated)"
    )
    parser.add_argument(
        "--camera-model",
        choices=CAMERA_MODEL_CHOICES,
        default="auto",
        help="lens model fitted to the photos: auto (SIMPLE_RADIAL, or OPENCV where it explains 0.1 px more "
        "reprojection error), SIMPLE_PINHOLE (no distortion), PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV (default auto)",
    )
    parser.add_argument(
        "--max-size",
        type=int,
        default=1600,
        help="long side in pixels above which photos are downscaled for feature matching (default 1600)",
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "images",
        nargs="+",
        type=Path,
        help="two or more photos of one scene (of one size, or of several: a camera per size)",
    )
    parser.add_argument("--out", type=Path, default=Path("cameras.json"), help="camera file to write (.json)")
    add_pose_arguments(parser)
    add_depth_range(
        parser,
        None,
        None,
        "nearest depth (default: from the 3D points)",
        "farthest depth (default: from the 3D points)",
    )


def estimate_from_args(args: argparse.Namespace):
    """(CameraSet, PoseSummary) for args.images with the pose options of `add_pose_arguments`;
    the summary is printed. Raises SurfSplatInputError with the cause when the photos give no cameras."""
    from ..poses import PoseConfig, estimate_cameras

    for path in args.images:
        if not path.is_file():
            raise FileNotFoundError(f"{path}: image file not found")
    config = PoseConfig(
        focal=args.focal, camera_model=args.camera_model, max_size=args.max_size, near=args.near, far=args.far
    )
    camera_set, summary = estimate_cameras(args.images, config=config)
    print("\n".join(summary.lines()))
    return camera_set, summary


def run(args: argparse.Namespace) -> int:
    from ..data.cameras import save_cameras

    if args.out.suffix.lower() != ".json":
        raise SurfSplatInputError(f"--out: expected a .json camera file name, got {args.out}")
    check_output_file(args.out, "--out", inputs=args.images)
    camera_set, summary = estimate_from_args(args)
    written = save_cameras(
        args.out,
        camera_set.cameras,
        camera_set.width,
        camera_set.height,
        camera_set.names,
        camera_set.near,
        camera_set.far,
        lenses=camera_set.lenses,
    )
    print(f"wrote {written}")
    return 0
