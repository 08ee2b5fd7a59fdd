"""Lens benchmark: our COLMAP camera models against pycolmap, photos distorted and undistorted back,
and the seconds the undistortion maps of a photo take.

    python benchmarks/undistort.py                 # all three parts
    python benchmarks/undistort.py --threads 2     # torch threads for the timing (default: torch's)

1. Per COLMAP model 0-10 (`surfsplat.testing.lenses.CALIBRATIONS`, 640x480): the largest
   difference of `project` from pycolmap's `img_from_cam` (px), of `unproject` from `cam_from_img`
   (in pixels at the focal length), of project(unproject(p)) from p over every pixel centre, and
   whether `undistorted_pinhole` equals `pycolmap.undistort_camera` (size, parameters).
2. DTU scan 24's photos (400x300 from ../shared/data where present, else the fixture's 100x75), f = 0.8 W,
   distorted with OPENCV (k1 -0.1, k2 0.05, p1 0.001, p2 -0.001) and OPENCV_FISHEYE (k1 0.05,
   k2 -0.01, k3 0.002, k4 0) and undistorted back: MAE over the valid region (1/255 units), bilinear
   and bicubic, and a half-pixel shift and back (two bilinear resamplings, no lens) for scale.
3. Seconds to compute `undistort_maps` (and `distort_maps`) for a 1920x1080 OPENCV photo, median of
   repeats, cache cleared each time; and `undistort` of one photo with the maps cached.
Results go to benchmarks/results/undistort.json with the machine and its load, and a table is printed.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from common import ROOT, SHARED_DATA, machine, text_table, write_results
from surfsplat.data.undistort import distort, distort_maps, undistort, undistort_maps
from surfsplat.geometry.lens import Lens, project, undistorted_pinhole, unproject
from surfsplat.testing.lenses import CALIBRATIONS, HEIGHT, WIDTH

W, H = WIDTH, HEIGHT


def models() -> list[dict]:
    import pycolmap

    rows = []
    rng = np.random.default_rng(0)
    for model, params in CALIBRATIONS.items():
        lens = Lens(model, W, H, params)
        cam = pycolmap.Camera(model=model, width=W, height=H, params=list(params))
        pts = np.concatenate([rng.uniform(-0.65, 0.65, (4000, 2)), np.ones((4000, 1))], 1) * rng.uniform(
            0.2, 20, (4000, 1)
        )
        px = np.stack([rng.uniform(0, W, 4000), rng.uniform(0, H, 4000)], 1)
        f = float(np.mean(lens.focal_and_centre[:2]))
        ys, xs = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
        grid = torch.stack([xs, ys], -1).double()
        n = unproject(lens, grid)
        back = project(lens, torch.cat([n, torch.ones_like(n[..., :1])], -1))
        ref = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), cam)
        ours = undistorted_pinhole(lens)
        rows.append(
            {
                "model": model,
                "project_vs_pycolmap_px": float(
                    np.abs(project(lens, torch.from_numpy(pts)).numpy() - cam.img_from_cam(pts)).max()
                ),
                "unproject_vs_pycolmap_px": float(
                    np.abs(unproject(lens, torch.from_numpy(px)).numpy() - cam.cam_from_img(px)).max() * f
                ),
                "round_trip_px": float((back - grid).abs().max()),
                "undistorted_size": [ours.width, ours.height],
                "undistorted_equals_pycolmap": (ours.width, ours.height) == (ref.width, ref.height)
                and bool(np.abs(np.array(ours.params) / np.array(ref.params) - 1).max() <= 1e-6),
            }
        )
    return rows


def _photo(path: Path) -> torch.Tensor:
    return torch.from_numpy(np.array(Image.open(path).convert("RGB"))).permute(2, 0, 1).float() / 255


def photos(count: int) -> dict:
    import cv2

    folder = SHARED_DATA / "dtu_scan24" / "images_4"
    if not folder.is_dir():
        folder = ROOT / "tests" / "data" / "dtu_scan24" / "images_16"
    paths = sorted(folder.glob("*.png"))[:count]
    rows = []
    for model, coeffs in (("OPENCV", (-0.1, 0.05, 0.001, -0.001)), ("OPENCV_FISHEYE", (0.05, -0.01, 0.002, 0.0))):
        maes: dict[str, list[float]] = {"bilinear": [], "bicubic": [], "half_pixel_shift_bilinear": []}
        for path in paths:
            image = _photo(path)
            _, h, w = image.shape
            f = 0.8 * w
            K = (f, f, w / 2 + 0.3, h / 2 - 0.2)
            pinhole, lens = Lens("PINHOLE", w, h, K), Lens(model, w, h, K + coeffs)
            valid = undistort(distort(torch.ones(1, h, w), pinhole, lens), lens, pinhole)[0] >= 1 - 1e-6
            for mode in ("bilinear", "bicubic"):
                back = undistort(distort(image, pinhole, lens, mode), lens, pinhole, mode)
                maes[mode].append((back - image).abs().mean(0)[valid].mean().item() * 255)
            hwc = image.permute(1, 2, 0).numpy()
            mx, my = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
            a = cv2.remap(hwc, mx + 0.5, my + 0.5, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            b = cv2.remap(a, mx - 0.5, my - 0.5, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            maes["half_pixel_shift_bilinear"].append(float(np.abs(b - hwc)[2:-2, 2:-2].mean() * 255))
        rows.append(
            {
                "model": model,
                "size": [w, h],
                "photos": len(paths),
                **{f"mae_{k}_mean": statistics.mean(v) for k, v in maes.items()},
                **{f"mae_{k}_max": max(v) for k, v in maes.items()},
            }
        )
    return {"folder": str(folder.relative_to(folder.parents[2])), "rows": rows}


def timing(repeats: int) -> dict:
    lens = Lens("OPENCV", 1920, 1080, (1500.0, 1500.0, 960.0, 540.0, -0.1, 0.05, 0.001, -0.001))
    pinhole = undistorted_pinhole(lens)
    out = {"size": [1920, 1080], "pinhole_size": [pinhole.width, pinhole.height]}
    for name, fn, args in (
        ("undistort_maps_s", undistort_maps, (lens, pinhole)),
        ("distort_maps_s", distort_maps, (pinhole, lens)),
    ):
        times = []
        for _ in range(repeats):
            fn.cache_clear()
            t = time.perf_counter()
            fn(*args)
            times.append(time.perf_counter() - t)
        out[name] = statistics.median(times)
    image = torch.rand(3, 1080, 1920)
    undistort(image, lens, pinhole)  # maps cached
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        undistort(image, lens, pinhole)
        times.append(time.perf_counter() - t)
    out["undistort_photo_cached_maps_s"] = statistics.median(times)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photos", type=int, default=6, help="DTU photos per lens")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    result = {"machine": machine(), "models": models(), "photos": photos(args.photos), "timing": timing(args.repeats)}
    path = write_results("undistort", result)
    print(
        text_table(
            ["model", "project px", "unproject px", "round trip px", "pinhole", "= pycolmap"],
            [
                [
                    r["model"],
                    r["project_vs_pycolmap_px"],
                    r["unproject_vs_pycolmap_px"],
                    r["round_trip_px"],
                    "x".join(map(str, r["undistorted_size"])),
                    r["undistorted_equals_pycolmap"],
                ]
                for r in result["models"]
            ],
        )
    )
    print(
        text_table(
            ["lens", "size", "MAE bilinear", "MAE bicubic", "half-px shift (bilinear)"],
            [
                [
                    r["model"],
                    "x".join(map(str, r["size"])),
                    r["mae_bilinear_mean"],
                    r["mae_bicubic_mean"],
                    r["mae_half_pixel_shift_bilinear_mean"],
                ]
                for r in result["photos"]["rows"]
            ],
        )
    )
    print(result["timing"])
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
