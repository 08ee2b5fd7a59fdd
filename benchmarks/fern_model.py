"""A COLMAP model of LLFF fern made by the pose-free estimation, as COLMAP's automatic reconstruction
makes one: the 20 photos at 504x378 (`images_8` of the full samples), one shared SIMPLE_RADIAL camera.

    python benchmarks/fern_model.py                          # model in benchmarks/results/fern_model/sparse/0
    python benchmarks/fern_model.py --out DIR --camera-model auto

pycolmap writes the model (cameras.bin, images.bin, points3D.bin, with the photos' names), in the
world of the returned cameras (the first photo's camera at the origin, median depth 4). The figures
(registered photos, 3D points, mean reprojection error, the fitted f and k, and the rotation error
against LLFF's own calibration after aligning the worlds) go to benchmarks/results/fern_model.json
and are printed.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from common import RESULTS, ROOT, SHARED_DATA, machine, write_results


def _shown(path: Path) -> str:
    """A path as the results name it: relative to the repository where it is inside it."""
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        return path.name


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=SHARED_DATA / "llff_fern", help="LLFF fern folder")
    parser.add_argument("--out", type=Path, default=RESULTS / "fern_model", help="folder for sparse/0")
    parser.add_argument("--camera-model", default="SIMPLE_RADIAL")
    parser.add_argument("--json", type=Path, default=None, help="figures (default benchmarks/results/fern_model.json)")
    args = parser.parse_args()

    import pycolmap

    from surfsplat.data.load import load_scene_cameras
    from surfsplat.poses import PoseConfig, aligned_pose_errors, estimate_cameras, relative_pose_errors

    photos = sorted((args.data / "images_8").glob("*.png"))
    if len(photos) != 20:
        print(f"{args.data / 'images_8'}: expected LLFF fern's 20 photos, found {len(photos)}", file=sys.stderr)
        return 1
    model_dir = args.out / "sparse" / "0"
    start = time.perf_counter()
    cams, summary = estimate_cameras(photos, config=PoseConfig(camera_model=args.camera_model), colmap_model=model_dir)
    seconds = time.perf_counter() - start
    written = pycolmap.Reconstruction(model_dir)  # read back what pycolmap wrote
    (camera,) = written.cameras.values()
    truth = load_scene_cameras(args.data, images="images_8")
    order = [truth.names.index(n) for n in cams.names]
    rot, _ = aligned_pose_errors(cams.cameras.c2w, truth.cameras.c2w[order].double())
    relative, _ = relative_pose_errors(cams.cameras.c2w, truth.cameras.c2w[order].double())
    figures = {
        "benchmark": "COLMAP model of LLFF fern by surfsplat.poses.estimate_cameras",
        "photos": f"{len(photos)} of llff_fern/images_8 ({summary.width}x{summary.height})",
        "camera_model_asked": args.camera_model,
        "model_dir": _shown(model_dir),
        "registered": len(summary.registered),
        "registered_in_model": written.num_reg_images(),
        "points": written.num_points3D(),
        "mean_reprojection_error_px": written.compute_mean_reprojection_error(),
        "mean_track_length": written.compute_mean_track_length(),
        "camera": {
            "model": camera.model.name,
            "width": camera.width,
            "height": camera.height,
            "params": dict(zip(camera.params_info.split(", "), map(float, camera.params))),
        },
        "pinhole": summary.pinhole.to_dict(),
        "model_choice": summary.model_choice,
        "focal_source": summary.focal_source,
        "llff_focal_px": float(truth.cameras.K[0, 0, 0]),
        "max_rotation_error_deg": float(rot.max()),
        "max_relative_rotation_error_deg": float(relative.max()),
        "seconds": seconds,
        "stages_s": summary.timings,
        "machine": {**machine(), "pycolmap": pycolmap.__version__},
    }
    out = write_results(args.json or "fern_model", figures)
    print("\n".join(summary.lines()))
    print(
        f"model: {figures['registered_in_model']} images, {figures['points']} points, reprojection "
        f"{figures['mean_reprojection_error_px']:.3f} px, {camera.model.name} {camera.params_info} = "
        f"{', '.join(f'{v:.5g}' for v in camera.params)}; rotation error vs LLFF max {rot.max():.3f} deg "
        f"(LLFF focal {figures['llff_focal_px']:.1f} px)"
    )
    print(f"(model in {model_dir}, figures in {out})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
