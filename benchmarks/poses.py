"""Camera estimation benchmark: seconds and peak memory of `estimate_cameras` for 2, 4 and 8 photos.

    python benchmarks/poses.py                       # 2, 4, 8 views at 400x300 and 1000x750
    python benchmarks/poses.py --views 8 --sizes 1000 --repeats 3 --min-idle 0.9

The photos are the procedural room (seed 0) ray-cast natively at each size (not upscaled) from
cameras 5.7 degrees apart on an arc around its middle (8 views span 40 degrees), so the rotation
error against the exact cameras is reported beside the time. Focal length unknown (the prior, refined by bundle adjustment) for 3+
views, given for two (the two-view path). Each measurement runs in a fresh process, so its peak
resident memory is its own; pycolmap uses every core (`--threads` to change). Results go to
benchmarks/results/poses.json and a table is printed. Goal: 8 photos at 1000 px in 10 s on 2 cores.

    python benchmarks/poses.py --lens                # a lens fitted to photos distorted with known coefficients
    python benchmarks/poses.py --repeat 3            # the same photos, the same cameras bit for bit?

--lens: DTU scan 24's views 12..26 (400x300, from the full samples) distorted here through an OPENCV
lens (k1 -0.1, k2 0.05, p1 0.001, p2 -0.001; the DTU calibration's focal lengths; its principal point
(205.8, 154.8), and again with the principal point moved to the centre, where the fitted models put
it) by OpenCV's inverse map, then estimated pose-free with each camera model; per view the rotation
error after aligning the estimated world to the calibration's (`aligned_pose_errors`), the fitted
distortion beside the true one. Results: benchmarks/results/poses_lens.json and a table.
--repeat N: N estimations of the same distorted photos per thread setting, compared bit for bit.

    python benchmarks/poses.py --mixed               # photos of several sizes: a camera per size

--mixed: DTU scan 24's views 12..26 (400x300, from the full samples) as one size (the control), with
every other view resized to 300x225 (Lanczos), and with every third view turned 90 degrees clockwise to a
300x400 portrait (pixels turned, no EXIF); estimated pose-free (focal unknown, --mixed-model, default
auto); per capture the rotation error of each view after aligning
to the calibration (turned with the photo for the portraits), and each camera's fitted focal length
against its true one (the calibration's, scaled or turned with the photo). Results:
benchmarks/results/poses_mixed.json and a table.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import SHARED_DATA, machine, sample_data, text_table, write_results
from encoder import idle_fraction, wait_for_idle  # the benchmarks' shared idle gauge (same folder)

SIZES = {400: (400, 300), 1000: (1000, 750)}


def orbit(n: int, width: int, height: int, step_deg: float = 40.0 / 7, fov_deg: float = 60.0):
    import torch

    from surfsplat.data.synthetic.scene import WORLD_DOWN
    from surfsplat.geometry.cameras import Cameras, look_at

    target = torch.tensor([0.0, 0.0, 0.6], dtype=torch.float64)
    spread = step_deg * (n - 1)
    angles = torch.deg2rad(torch.linspace(-spread / 2, spread / 2, n, dtype=torch.float64))
    eyes = torch.stack([2 * torch.cos(angles), 2 * torch.sin(angles), torch.full_like(angles, 1.4)], -1)
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Cameras(look_at(eyes, target.expand(n, 3), WORLD_DOWN), K.repeat(n, 1, 1))


def write_views(folder: Path, n: int, width: int, height: int) -> list[Path]:
    import numpy as np
    from PIL import Image

    from surfsplat.data.synthetic.render import render_synthetic
    from surfsplat.data.synthetic.scene import make_scene
    from surfsplat.geometry.cameras import Cameras

    cams = orbit(n, width, height)
    images = render_synthetic(make_scene(0), Cameras(cams.c2w.float(), cams.K.float()), width, height).image
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, image in enumerate(images):
        paths.append(folder / f"view{i}.png")
        Image.fromarray((image.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)).save(paths[-1])
    return paths


def run_one(folder: Path, n: int, size: int, repeats: int, threads: int, min_idle: float, timeout: float) -> dict:
    from surfsplat.evaluation import peak_rss_bytes
    from surfsplat.poses import PoseConfig, estimate_cameras, relative_pose_errors

    width, height = SIZES[size]
    truth = orbit(n, width, height)
    paths = sorted(folder.glob("view*.png"))
    focal = float(truth.K[0, 0, 0]) if n == 2 else None
    seconds, cpu, idle = [], [], []
    for _ in range(repeats):
        idle.append(wait_for_idle(min_idle, timeout) if min_idle > 0 else idle_fraction(0.2))
        start, start_cpu = time.perf_counter(), _cpu_seconds()
        cams, summary = estimate_cameras(paths, focal=focal, config=PoseConfig(threads=threads))
        seconds.append(time.perf_counter() - start)
        cpu.append(_cpu_seconds() - start_cpu)
    rot, trans = relative_pose_errors(cams.cameras.c2w, truth.c2w)
    return {
        "views": n,
        "width": width,
        "height": height,
        "extraction_size": list(summary.extraction_size),
        "threads": threads,
        "method": summary.method,
        "seconds": seconds,
        "median_s": statistics.median(seconds),
        "cpu_s": cpu,  # user + system time of every thread: the work, whatever the machine's load
        "stages_s": summary.timings,
        "idle_before": idle,
        "peak_mb": peak_rss_bytes() / 2**20,
        "registered": len(summary.registered),
        "points": summary.points,
        "max_rotation_error_deg": float(rot.max()),
        "max_translation_error_deg": float(trans.max()),
        "focal_error": abs(summary.focal / float(truth.K[0, 0, 0]) - 1),
    }


# ----------------------------------------------------------------------------------------- lenses
DTU_VIEWS = list(range(12, 27))
TRUE_LENS = {"k1": -0.1, "k2": 0.05, "p1": 0.001, "p2": -0.001}  # OPENCV, on normalized coordinates


def distort_photo(image, K, K_lens, coefficients: dict):
    """The photo an OPENCV lens (intrinsics K_lens, distortion `coefficients` k1, k2, p1, p2) would
    have taken from where a pinhole photo [H, W, 3] uint8 with intrinsics K was (pixel centres at
    +0.5): for every pixel of the distorted photo, OpenCV's iterative undistortion of its centre
    gives the ray it sees and K the pinhole pixel of that ray, sampled bilinearly (borders replicated)."""
    import cv2
    import numpy as np

    height, width = image.shape[:2]
    K_cv, K_lens_cv = np.array(K, dtype=np.float64).copy(), np.array(K_lens, dtype=np.float64).copy()
    K_cv[:2, 2] -= 0.5  # OpenCV's pixel centres are at integers
    K_lens_cv[:2, 2] -= 0.5
    dist = np.array([coefficients[k] for k in ("k1", "k2", "p1", "p2")], dtype=np.float64)
    jj, ii = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    points = np.stack([jj, ii], -1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    source = cv2.undistortPoints(points, K_lens_cv, dist, None, None, K_cv, criteria).reshape(height, width, 2)
    return cv2.remap(
        image,
        source[..., 0].astype(np.float32),
        source[..., 1].astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )


def lens_intrinsics(K, centred: bool):
    """The distorting lens's K: the calibration's, or with the principal point moved to the image centre."""
    K_lens = K.clone()
    if centred:
        K_lens[0, 2], K_lens[1, 2] = 200.0, 150.0  # the centre of DTU's 400x300 photos
    return K_lens


def write_distorted_dtu(folder: Path, data: Path, centred: bool) -> tuple[list[Path], object]:
    """DTU scan 24 views 12..26 through TRUE_LENS into folder; returns the paths and the calibration."""
    import numpy as np
    import torch
    from PIL import Image

    from surfsplat.data.load import load_scene

    scene = load_scene(data / "dtu_scan24", images="images_4", dtype=torch.float64)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for v in DTU_VIEWS:
        photo = np.asarray(Image.open(data / "dtu_scan24" / "images_4" / f"{v:06d}.png").convert("RGB"))
        paths.append(folder / f"{v:06d}.png")
        K = scene.cameras.K[v]
        Image.fromarray(distort_photo(photo, K.numpy(), lens_intrinsics(K, centred).numpy(), TRUE_LENS)).save(paths[-1])
    return paths, scene.cameras[torch.tensor(DTU_VIEWS)]


def run_lens(folder: Path, model: str, threads: int, centred: bool) -> dict:
    from surfsplat.poses import PoseConfig, aligned_pose_errors, estimate_cameras, relative_pose_errors

    truth = _dtu_truth()
    paths = [folder / f"{v:06d}.png" for v in DTU_VIEWS]
    start, start_cpu = time.perf_counter(), _cpu_seconds()
    cams, summary = estimate_cameras(paths, config=PoseConfig(camera_model=model, threads=threads))
    seconds, cpu = time.perf_counter() - start, _cpu_seconds() - start_cpu
    picked = [DTU_VIEWS.index(int(Path(n).stem)) for n in cams.names]
    rot, centre = aligned_pose_errors(cams.cameras.c2w, truth.c2w[picked])
    relative, _ = relative_pose_errors(cams.cameras.c2w, truth.c2w[picked])
    lens = summary.lens
    K_lens = lens_intrinsics(truth.K[0], centred)
    true = {"fx": float(K_lens[0, 0]), "fy": float(K_lens[1, 1]), "cx": float(K_lens[0, 2]), "cy": float(K_lens[1, 2])}
    return {
        "principal_point": "the image centre" if centred else "the calibration's",
        "camera_model": model,
        "fitted_model": lens.model,
        "fitted_params": dict(zip(lens.param_names, lens.params)),
        "true_params": {**true, **TRUE_LENS},
        "model_choice": summary.model_choice,
        "reprojection_error_px_by_model": summary.model_errors,
        "model_difference_px": summary.model_difference_px,
        "model_excess_px": summary.model_excess_px,
        "pinhole": summary.pinhole.to_dict(),
        "registered": len(summary.registered),
        "views": len(DTU_VIEWS),
        "points": summary.points,
        "reprojection_error_px": summary.reprojection_error,
        "rotation_error_deg": {Path(n).stem: float(r) for n, r in zip(cams.names, rot)},
        "max_rotation_error_deg": float(rot.max()),
        "max_centre_error_share": float(centre.max()),
        "max_relative_rotation_error_deg": float(relative.max()),
        "seconds": seconds,
        "cpu_s": cpu,
        "stages_s": summary.timings,
    }


def _dtu_truth():
    import torch

    from surfsplat.data.load import load_scene

    scene = load_scene(sample_data() / "dtu_scan24", images="images_4", dtype=torch.float64)
    return scene.cameras[torch.tensor(DTU_VIEWS)]


def run_repeat(folder: Path, threads: int, mapping_threads: int, repeats: int) -> dict:
    """`repeats` estimations of the same photos in this process: are the cameras equal bit for bit?"""
    import hashlib

    from surfsplat.poses import PoseConfig, estimate_cameras

    paths = [folder / f"{v:06d}.png" for v in DTU_VIEWS]
    digests, seconds = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        config = PoseConfig(threads=threads, mapping_threads=mapping_threads)
        cams, summary = estimate_cameras(paths, config=config)
        seconds.append(time.perf_counter() - start)
        blob = cams.cameras.c2w.numpy().tobytes() + cams.cameras.K.numpy().tobytes()
        blob += repr(summary.lens.params).encode() + repr(cams.names).encode()
        digests.append(hashlib.sha256(blob).hexdigest()[:16])
    return {
        "threads": threads,
        "mapping_threads": mapping_threads,
        "digests": digests,
        "identical": len(set(digests)) == 1,
        "seconds": seconds,
    }


MIXED_KINDS = ("one size", "resized", "portrait")


def write_mixed_dtu(folder: Path, data: Path, kind: str) -> list[Path]:
    """DTU scan 24 views 12..26 into folder as `kind` (see --mixed), with truth.pt: each view's true K and c2w."""
    import torch
    from PIL import Image

    from surfsplat.data.load import load_scene
    from surfsplat.geometry.orientation import displayed_camera

    scene = load_scene(data / "dtu_scan24", images="images_4", dtype=torch.float64)
    folder.mkdir(parents=True, exist_ok=True)
    paths, Ks, c2ws = [], [], []
    for k, v in enumerate(DTU_VIEWS):
        photo = Image.open(data / "dtu_scan24" / "images_4" / f"{v:06d}.png").convert("RGB")
        W, H = photo.size
        K, c2w = scene.cameras.K[v].clone(), scene.cameras.c2w[v].clone()
        K[0, 1] = 0.0  # the calibration's 5e-5 px skew: no turned pinhole keeps one
        if kind == "resized" and k % 2 == 1:
            w, h = round(0.75 * W), round(0.75 * H)
            photo = photo.resize((w, h), Image.Resampling.LANCZOS)
            K[:2] *= torch.tensor([w / W, h / H], dtype=K.dtype)[:, None]
        elif kind == "portrait" and k % 3 == 1:
            photo = photo.transpose(Image.Transpose.ROTATE_270)  # 90 degrees clockwise, as EXIF orientation 6 shows
            K, c2w, _ = displayed_camera(K, c2w, W, H, 6)
        paths.append(folder / f"{k:02d}_{v:06d}.png")
        photo.save(paths[-1])
        Ks.append(K)
        c2ws.append(c2w)
    torch.save({"names": [p.name for p in paths], "K": torch.stack(Ks), "c2w": torch.stack(c2ws)}, folder / "truth.pt")
    return paths


def run_mixed(folder: Path, kind: str, model: str, threads: int) -> dict:
    import torch

    from surfsplat.poses import PoseConfig, aligned_pose_errors, estimate_cameras

    truth = torch.load(folder / "truth.pt")
    paths = [folder / n for n in truth["names"]]
    start, start_cpu = time.perf_counter(), _cpu_seconds()
    cams, summary = estimate_cameras(paths, config=PoseConfig(camera_model=model, threads=threads))
    seconds, cpu = time.perf_counter() - start, _cpu_seconds() - start_cpu
    picked = [truth["names"].index(n) for n in cams.names]
    rot, centre = aligned_pose_errors(cams.cameras.c2w, truth["c2w"][picked])
    cameras = []
    for camera in summary.cameras:
        first = truth["names"].index(camera.images[0])
        true_f = float(truth["K"][first, 0, 0])
        cameras.append(
            {
                "size": f"{camera.width}x{camera.height}",
                "images": len(camera.images),
                "model": camera.lens.model,
                "params": dict(zip(camera.lens.param_names, camera.lens.params)),
                "true_f": true_f,
                "focal_error": camera.lens.params[0] / true_f - 1,
                "pinhole": camera.pinhole.to_dict(),
            }
        )
    return {
        "capture": kind,
        "camera_model": model,
        "model_choice": summary.model_choice,
        "registered": len(summary.registered),
        "views": len(paths),
        "points": summary.points,
        "reprojection_error_px": summary.reprojection_error,
        "cameras": cameras,
        "rotation_error_deg": {n: float(r) for n, r in zip(cams.names, rot)},
        "max_rotation_error_deg": float(rot.max()),
        "median_rotation_error_deg": float(statistics.median(rot.tolist())),
        "max_centre_error_share": float(centre.max()),
        "seconds": seconds,
        "cpu_s": cpu,
        "stages_s": summary.timings,
    }


def mixed_main(args) -> int:
    import pycolmap

    data = sample_data()
    if data != SHARED_DATA:
        print(f"--mixed needs DTU scan 24 at 400x300 from the full samples ({SHARED_DATA})", file=sys.stderr)
        return 1
    model = args.mixed_model
    rows = []
    with tempfile.TemporaryDirectory(prefix="poses-mixed-") as tmp:
        for kind in MIXED_KINDS:
            folder = Path(tmp) / kind.replace(" ", "_")
            write_mixed_dtu(folder, data, kind)
            cmd = [sys.executable, __file__, "--mixed-single", str(folder), kind, model, "--threads", str(args.threads)]
            done = subprocess.run(cmd, capture_output=True, text=True)
            if done.returncode != 0:
                print(f"mixed {kind}: failed\n{done.stderr.strip()[-2000:]}", file=sys.stderr)
                return 1
            rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
            print(f"mixed {kind}: done", file=sys.stderr)
    report = {
        "benchmark": "pose-free camera estimation of photos of several sizes (surfsplat.poses.estimate_cameras)",
        "images": f"DTU scan 24 views {DTU_VIEWS[0]}..{DTU_VIEWS[-1]} (images_4, 400x300): one size; every other "
        "view resized to 300x225; every third view turned 90 degrees clockwise to 300x400 (no EXIF)",
        "alignment": "rotations: the chordal mean rotation onto the calibration's (turned with the portraits)",
        "machine": {**machine(), "pycolmap": pycolmap.__version__},
        "results": rows,
    }
    out = write_results(args.out or "poses_mixed", report)
    headers = ["capture", "registered", "cameras: size, images, f (error)", "reproj px", "max rot deg"]
    headers += ["median rot deg", "CPU s", "seconds"]
    table = [
        [
            r["capture"],
            f"{r['registered']}/{r['views']}",
            "; ".join(
                f"{c['size']}, {c['images']}, {c['params']['f']:.1f} ({c['focal_error']:+.2%})" for c in r["cameras"]
            ),
            f"{r['reprojection_error_px']:.3f}",
            f"{r['max_rotation_error_deg']:.3f}",
            f"{r['median_rotation_error_deg']:.3f}",
            f"{r['cpu_s']:.0f}",
            f"{r['seconds']:.1f}",
        ]
        for r in rows
    ]
    print(text_table(headers, table))
    print(f"(load average at the end {os.getloadavg()[0]:.2f}; written to {out})")
    return 0


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", nargs="+", type=int, default=[2, 4, 8])
    parser.add_argument("--sizes", nargs="+", type=int, choices=sorted(SIZES), default=sorted(SIZES))
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--threads", type=int, default=-1, help="pycolmap threads (-1: every core)")
    parser.add_argument("--min-idle", type=float, default=0.0, help="wait for this idle CPU share before each run")
    parser.add_argument("--idle-timeout", type=float, default=1800.0)
    parser.add_argument("--single", nargs=3, help=argparse.SUPPRESS)  # internal: FOLDER VIEWS SIZE -> JSON
    parser.add_argument("--lens", action="store_true", help="fit lenses to DTU photos distorted with known values")
    parser.add_argument("--models", nargs="+", default=["SIMPLE_PINHOLE", "auto", "OPENCV"])
    parser.add_argument("--repeat", type=int, default=0, help="N runs of the same photos, compared bit for bit")
    parser.add_argument(
        "--repeat-threads",
        nargs="+",
        default=["all/all", "all/1", "1/1"],
        help="THREADS/MAPPING_THREADS settings of the --repeat runs (PoseConfig.threads, .mapping_threads; all: -1)",
    )
    parser.add_argument("--out", type=Path, default=None, help="JSON to write (default benchmarks/results/...)")
    parser.add_argument("--lens-single", nargs=3, help=argparse.SUPPRESS)  # internal: FOLDER MODEL CENTRED -> JSON
    parser.add_argument("--repeat-single", nargs=2, help=argparse.SUPPRESS)  # internal: FOLDER THREADS/MAPPING -> JSON
    parser.add_argument("--mixed", action="store_true", help="photos of several sizes: DTU views resized or turned")
    parser.add_argument("--mixed-model", default="auto", help="--mixed: the camera model fitted (default auto)")
    parser.add_argument("--mixed-single", nargs=3, help=argparse.SUPPRESS)  # internal: FOLDER KIND MODEL -> JSON
    args = parser.parse_args()

    if args.mixed_single:
        folder, kind, model = args.mixed_single
        print(json.dumps(run_mixed(Path(folder), kind, model, args.threads)))
        return 0
    if args.mixed:
        return mixed_main(args)

    if args.lens_single:
        folder, model, centred = args.lens_single
        print(json.dumps(run_lens(Path(folder), model, args.threads, centred == "centred")))
        return 0
    if args.repeat_single:
        threads, mapping = (-1 if v == "all" else int(v) for v in args.repeat_single[1].split("/"))
        print(json.dumps(run_repeat(Path(args.repeat_single[0]), threads, mapping, args.repeat)))
        return 0
    if args.lens or args.repeat:
        return lens_main(args)

    if args.single:
        folder, n, size = Path(args.single[0]), int(args.single[1]), int(args.single[2])
        result = run_one(folder, n, size, args.repeats, args.threads, args.min_idle, args.idle_timeout)
        print(json.dumps(result))
        return 0

    rows = []
    with tempfile.TemporaryDirectory(prefix="poses-bench-") as tmp:
        for size in args.sizes:
            for n in args.views:
                folder = Path(tmp) / f"{size}_{n}"
                write_views(folder, n, *SIZES[size])
                cmd = [sys.executable, __file__, "--single", str(folder), str(n), str(size)]
                cmd += ["--repeats", str(args.repeats), "--threads", str(args.threads)]
                cmd += ["--min-idle", str(args.min_idle), "--idle-timeout", str(args.idle_timeout)]
                done = subprocess.run(cmd, capture_output=True, text=True)
                if done.returncode != 0:
                    print(f"{n} views at {size}: failed\n{done.stderr.strip()[-2000:]}", file=sys.stderr)
                    return 1
                rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
                print(f"{n} views at {SIZES[size]}: {rows[-1]['median_s']:.2f} s", file=sys.stderr)

    import pycolmap

    report = {
        "benchmark": "camera estimation (surfsplat.poses.estimate_cameras)",
        "images": "procedural room, seed 0, ray-cast natively at each size, views 5.7 degrees apart on an arc",
        "machine": {**machine(), "pycolmap": pycolmap.__version__},
        "results": rows,
    }
    out = write_results("poses", report)

    headers = ["views", "size", "SIFT at", "method", "seconds (median, min)", "CPU s", "extract/match/solve s"]
    headers += ["peak MB", "points", "rot err deg", "idle before"]
    table = [
        [
            r["views"],
            f"{r['width']}x{r['height']}",
            "x".join(map(str, r["extraction_size"])),
            r["method"],
            f"{r['median_s']:.2f}, {min(r['seconds']):.2f}",
            round(statistics.median(r["cpu_s"]), 1),
            "/".join(f"{r['stages_s'][k]:.1f}" for k in ("extract", "match", "reconstruct")),
            round(r["peak_mb"]),
            r["points"],
            round(r["max_rotation_error_deg"], 3),
            ",".join("-" if x is None else f"{x:.2f}" for x in r["idle_before"]),
        ]
        for r in rows
    ]
    print(text_table(headers, table))
    print(f"(load average at the end {os.getloadavg()[0]:.2f}; written to {out})")
    return 0


def lens_main(args) -> int:
    import pycolmap

    data = sample_data()
    if data != SHARED_DATA:
        print(f"--lens and --repeat need DTU scan 24 at 400x300 from the full samples ({SHARED_DATA})", file=sys.stderr)
        return 1
    rows, repeats = [], []
    with tempfile.TemporaryDirectory(prefix="poses-lens-") as tmp:
        jobs = []
        for centred in ("calibrated", "centred"):
            folder = Path(tmp) / centred
            write_distorted_dtu(folder, data, centred == "centred")
            if args.lens:
                jobs += [("lens", m, ["--lens-single", str(folder), m, centred]) for m in args.models]
        folder = Path(tmp) / "calibrated"
        if args.repeat:
            jobs += [
                ("repeat", t, ["--repeat-single", str(folder), t, "--repeat", str(args.repeat)])
                for t in args.repeat_threads
            ]
        for kind, what, extra in jobs:
            cmd = [sys.executable, __file__, *extra, "--threads", str(args.threads)]
            done = subprocess.run(cmd, capture_output=True, text=True)
            if done.returncode != 0:
                print(f"{kind} {what}: failed\n{done.stderr.strip()[-2000:]}", file=sys.stderr)
                return 1
            (rows if kind == "lens" else repeats).append(json.loads(done.stdout.strip().splitlines()[-1]))
            print(f"{kind} {what}: done", file=sys.stderr)
    report = {
        "benchmark": "lens fitted by pose-free camera estimation (surfsplat.poses.estimate_cameras)",
        "images": f"DTU scan 24 views {DTU_VIEWS[0]}..{DTU_VIEWS[-1]} (images_4, 400x300) distorted through OPENCV "
        f"{TRUE_LENS} with the calibration's focal length and principal point",
        "alignment": "rotations: the chordal mean rotation onto the calibration's; centres: Umeyama similarity",
        "machine": {**machine(), "pycolmap": pycolmap.__version__},
        "results": rows,
        "repeats": repeats,
    }
    out = write_results(args.out or "poses_lens", report)
    if rows:
        headers = [
            "lens centre",
            "model asked",
            "fitted",
            "parameters",
            "registered",
            "reproj px",
            "max rot deg",
            "max rel rot deg",
        ]
        headers += ["max centre err", "CPU s"]
        table = [
            [
                "centre" if r["principal_point"] == "the image centre" else "DTU's",
                r["camera_model"],
                r["fitted_model"],
                ", ".join(f"{k} {v:.4g}" for k, v in r["fitted_params"].items() if k not in ("cx", "cy")),
                f"{r['registered']}/{r['views']}",
                f"{r['reprojection_error_px']:.3f}",
                f"{r['max_rotation_error_deg']:.3f}",
                f"{r['max_relative_rotation_error_deg']:.3f}",
                f"{r['max_centre_error_share']:.2%}",
                f"{r['cpu_s']:.0f}",
            ]
            for r in rows
        ]
        print(text_table(headers, table))
        print(
            "true: "
            + ", ".join(f"{k} {v:.4g}" for k, v in rows[0]["true_params"].items())
            + " (cx, cy: DTU's or the centre)"
        )
    for r in repeats:
        print(
            f"threads {r['threads']}, mapping threads {r['mapping_threads']}: {len(r['digests'])} runs, identical: {r['identical']} ({', '.join(r['digests'])})"
        )
    print(f"(written to {out})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
