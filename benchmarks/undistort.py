"""Lens benchmark: our COLMAP camera models against pycolmap, photos distorted and undistorted back,
and the seconds the undistortion maps of a photo take.

    python benchmarks/undistort.py                 # parts models, photos, timing
    python benchmarks/undistort.py --threads 2     # torch threads for the timing (default: torch's)
    python benchmarks/undistort.py --parts reconstruct   # DTU through two lenses, end to end (five runs, about 12 CPU min)

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
4. `reconstruct` (needs ../shared/data/dtu_scan24 with images_4, 400x300; skipped with a line saying so
   where absent): DTU scan 24's views 12..26 as benchmarks/optimize.py's dtu-cli runs them (`surfsplat
   reconstruct --holdout-every 3 --formats ply --raw-3dgs`, the shipped defaults, each a child process one
   after the other; 12, 15, 18, 21, 24 held out), (a) from the photos and their calibration, and from the
   same photos through an OPENCV lens (b: k1 -0.1, k2 0.05, p1 0.001, p2 -0.001) and an OPENCV_FISHEYE
   lens (c: part 2's coefficients), both at the calibration's principal point and 1.04 times its focal
   length (`--focal-scale`; the mean of the 15 views' K, which differ by 1e-3 px), each written by `surfsplat.testing.lens_capture` as a
   COLMAP model (pycolmap, binary, no 3D points: every run triangulates its start from the cameras alike)
   and as nerfstudio's transforms.json, and reconstructed from each. Per run: held-out PSNR per view and
   mean, the difference to (a), the pinhole and working crop the run reports, CPU seconds. At the
   calibration's own focal length (`--focal-scale 1`) a lens sees a little beyond the pinhole photo at its
   corners (those pixels are blank: counted per lens, none at 1.04), so (a)'s scene is also scored on the photos each lens's run is scored on
   (distorted, saved, undistorted: rendered with that run's held-out cameras), the comparison that
   separates what the lens costs from what the resampled and blank pixels cost. One held-out view of
   (b) is drawn as the photo through the lens, its undistorted pinhole photo and the render
   (`--figure`, default docs/images/lens_capture_held_out.jpg). Results go to
   benchmarks/results/lens_capture.json and a table is printed.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from common import ROOT, SHARED_DATA, machine, reconstruct_cli, text_table, write_results
from surfsplat.data.undistort import distort, distort_maps, undistort, undistort_maps
from surfsplat.geometry.lens import Lens, project, undistorted_pinhole, unproject
from surfsplat.testing.lenses import CALIBRATIONS, HEIGHT, WIDTH

W, H = WIDTH, HEIGHT
DTU_VIEWS = list(range(12, 27))  # benchmarks/optimize.py's dtu-cli
CLI_FLAGS = ["--holdout-every", "3", "--formats", "ply", "--raw-3dgs"]
RECONSTRUCT_LENSES = {"OPENCV": (-0.1, 0.05, 0.001, -0.001), "OPENCV_FISHEYE": (0.05, -0.01, 0.002, 0.0)}
TARGET_DB = 0.5  # every lens's run within this of the undistorted one (held-out mean PSNR)


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


def _run(name: str, images: list[Path], cameras: Path, out: Path, extra: list[str]) -> dict:
    print(f"reconstruct: {name} ...", flush=True)
    run = reconstruct_cli([str(p) for p in images], cameras, out, [*CLI_FLAGS, *extra])
    held = run["held_out"]
    return {"run": name, "out": str(out), **run, "held_out_names": held.get("names"), "psnr": held.get("psnr")}


def _compare(result: dict, run: dict) -> None:
    """`run` (a lens's) against (a), the first of result's runs: on their own photos, and (a)'s scene scored
    on the run's photos; appended to the runs, the worst difference updated."""
    original = result["runs"][0]
    fair = _scored_on(Path(original["out"]), Path(run["out"]), Path(run["capture"]))
    run["original_scored_on_these_photos"] = fair
    run["minus_original_db"] = run["held_out_psnr"] - original["held_out_psnr"]
    run["minus_original_on_these_photos_db"] = run["held_out_psnr"] - fair["mean_psnr"]
    valid = fair["valid_region"]
    run["minus_original_on_the_valid_region_db"] = valid["this_run_mean_psnr"] - valid["original_mean_psnr"]
    result["runs"].append(run)
    worst = min(r["minus_original_db"] for r in result["runs"][1:])
    result.update(worst_minus_original_db=worst, within_target=worst >= -TARGET_DB)


def _finished_run(name: str, out: Path) -> dict:
    """A run made before (`--reference`): its held-out scores, crop and lenses from its reconstruction.json
    (its CPU seconds are not known here)."""
    import json

    summary = json.loads((out / "reconstruction.json").read_text())
    held = summary["capture"]["held_out"]
    return {
        "run": name,
        "out": str(out),
        "reference": "made by an earlier process",
        "cpu_seconds": None,
        "held_out_psnr": held["mean_psnr"],
        "held_out": held,
        "size": summary.get("size"),
        "working_crop": summary.get("working_crop"),
        "lenses": summary.get("lenses"),
        "held_out_names": held["names"],
        "psnr": held["psnr"],
    }


def _valid_masks(capture: Path, crop: dict, names: list[str]) -> torch.Tensor:
    """[V, H, W] bool: the pixels of the named held-out photos (undistorted, at the working crop) that show
    the pinhole photo they were made from, none of the lens's blank border: the lens's photo of a white
    image, undistorted and cropped as the run did, at least 0.999."""
    import json

    from surfsplat.data.transforms import rescale_and_crop
    from surfsplat.geometry.lens import undistorted_pinhole as pinhole_of

    truth = json.loads((capture / "truth.json").read_text())
    lens = Lens.from_dict(truth["lens"])
    pinhole = pinhole_of(lens)
    by_name = {Path(v["image"]).name: v for v in truth["views"]}
    masks = []
    for name in names:
        source = Lens.from_dict(by_name[Path(name).name]["pinhole"])
        seen = undistort(distort(torch.ones(1, source.height, source.width), source, lens), lens, pinhole)
        cropped, _, _ = rescale_and_crop(
            seen.expand(3, -1, -1)[None], torch.eye(3)[None], (crop["height"], crop["width"])
        )
        masks.append(cropped[0, 0] >= 0.999)
    return torch.stack(masks)


def _masked_psnr(renders: torch.Tensor, photos: torch.Tensor, masks: torch.Tensor) -> list[float]:
    """PSNR per view over the pixels of `masks` (mean squared error over channels and those pixels)."""
    err = ((renders.clamp(0, 1) - photos) ** 2).mean(1)  # [V, H, W]
    mse = (err * masks).sum((1, 2)) / masks.sum((1, 2))
    return (-10 * torch.log10(mse)).tolist()


def _scored_on(reference: Path, lens_run: Path, capture: Path) -> dict:
    """The scene of the run in `reference` rendered from the held-out cameras of the run in `lens_run`
    and scored against that run's held-out photos (those photos through the lens, undistorted); and both
    scenes scored on the pixels of those photos that the lens saw of the pinhole photos (`_valid_masks`)."""
    from optimize import held_out_scores
    from surfsplat.reconstruction.scene_fit import load_reconstruction

    ref, _ = load_reconstruction(reference)
    other, _ = load_reconstruction(lens_run)
    held = other.holdout
    seen = dataclasses.replace(ref, width=other.width, height=other.height, holdout=None)
    scores = held_out_scores(ref.gaussians, seen, held.cameras, held.images)
    crop = other.crop.to_dict()
    masks = _valid_masks(capture, crop, held.names)
    photos = held.images.to(torch.float32)
    lens_psnr = _masked_psnr(other.render(held.cameras).color, photos, masks)
    ref_psnr = _masked_psnr(seen.render(held.cameras).color, photos, masks)
    scores["valid_region"] = {
        "share_of_pixels": masks.float().mean((1, 2)).tolist(),
        "this_run_psnr": lens_psnr,
        "this_run_mean_psnr": statistics.mean(lens_psnr),
        "original_psnr": ref_psnr,
        "original_mean_psnr": statistics.mean(ref_psnr),
    }
    return scores


def _figure(capture: Path, run: dict, path: Path) -> None:
    """One held-out view of a lens's run: the photo through the lens, its undistorted pinhole photo (the
    run's working crop) and the render, side by side on one row under their labels, as a JPEG."""
    from PIL import ImageDraw

    out = Path(run["out"]) / "capture"
    stem = Path(run["held_out_names"][1]).stem  # view 15: the second held out
    panels = [Image.open(capture / "images" / f"{stem}.png")]
    panels += [Image.open(out / f"{stem}_{what}.png") for what in ("photo", "render")]
    psnr = run["psnr"][1]
    labels = [
        f"{stem}: the photo through the lens ({panels[0].width}x{panels[0].height})",
        f"undistorted, working crop ({panels[1].width}x{panels[1].height})",
        f"render, held out ({psnr:.2f} dB)",
    ]
    gap, top = 6, 16
    height = max(p.height for p in panels) + top
    sheet = Image.new("RGB", (sum(p.width for p in panels) + gap * (len(panels) - 1), height), "white")
    draw = ImageDraw.Draw(sheet)
    x = 0
    for panel, label in zip(panels, labels):
        sheet.paste(panel.convert("RGB"), (x, top + (height - top - panel.height) // 2))
        draw.text((x + 2, 2), label, fill="black")
        x += panel.width + gap
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(path, quality=90)


def reconstruct(args, save) -> dict | None:
    """Part 4 (see the module doc): DTU through each lens, reconstructed end to end beside the original."""
    from surfsplat.data.formats.dtu import load_dtu
    from surfsplat.testing.lens_capture import PinholeView, blank_pixels, write_lens_capture

    folder = SHARED_DATA / "dtu_scan24"
    if not (folder / "images_4").is_dir():
        print(f"reconstruct: skipped: {folder / 'images_4'} (DTU scan 24 at 400x300) is absent")
        return None
    scene = load_dtu(folder, images="images_4", dtype=torch.float64)
    height, width = scene.images.shape[-2:]
    K = scene.cameras.K[DTU_VIEWS]
    calibration = tuple(float(v) for v in (K[:, 0, 0].mean(), K[:, 1, 1].mean(), K[:, 0, 2].mean(), K[:, 1, 2].mean()))
    views = []
    for i in DTU_VIEWS:
        k = scene.cameras.K[i]
        pinhole = Lens("PINHOLE", width, height, (float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])))
        views.append(
            PinholeView(
                scene.names[i], scene.images[i], pinhole, scene.cameras.c2w[i].numpy(), f"images_4/{scene.names[i]}"
            )
        )
    result = {
        "protocol": f"DTU scan 24 views {DTU_VIEWS[0]}..{DTU_VIEWS[-1]} at {width}x{height}, surfsplat reconstruct "
        + " ".join(CLI_FLAGS + args.cli_args)
        + " --device cpu, shipped defaults, one run after the other",
        "calibration": dict(zip(("fx", "fy", "cx", "cy"), calibration)),
        "lens_focal_scale": args.focal_scale,
        "lenses": [],
        "runs": [],
        "target_db": TARGET_DB,
    }
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.keep) if args.keep else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        photos = [folder / "images_4" / v.name for v in views]
        extra = ["--images-folder", "images_4", *args.cli_args]
        if not args.reference:
            result["runs"].append(_run("(a) DTU's photos and calibration", photos, folder, work / "a", extra))
            save(result)
        captures = []
        for letter, (model, coeffs) in zip("bc", RECONSTRUCT_LENSES.items()):
            if model not in args.lenses:
                continue
            fx, fy, cx, cy = calibration
            lens = Lens(model, width, height, (fx * args.focal_scale, fy * args.focal_scale, cx, cy) + coeffs)
            capture = work / f"capture_{model.lower()}"
            write_lens_capture(capture, views, lens, full_cover=False)
            blank = [blank_pixels(v, lens) for v in views]
            result["lenses"].append({"run": letter, "lens": lens.to_dict(), "blank_pixels_per_photo": blank})
            captures.append((letter, model, capture))
        # the COLMAP runs of both lenses first, then nerfstudio's: each run is saved as soon as it is measured
        lens_runs = []
        for dialect in args.dialects:
            for letter, model, capture in captures:
                cameras = capture / "sparse" / "0" if dialect == "COLMAP" else capture / "transforms.json"
                images = [capture / "images" / v.name for v in views]
                name = f"({letter}) {model} lens, {dialect}"
                run = _run(name, images, cameras, work / f"{letter}_{dialect.lower()}", args.cli_args)
                run["capture"] = str(capture)
                if letter == "b" and dialect == "COLMAP" and args.figure:
                    _figure(capture, run, Path(args.figure))
                lens_runs.append(run)
                if not args.reference:
                    _compare(result, run)
                    save(result)
                else:  # compared at the end, with (a) finished by then; saved as measured
                    save({**result, "runs": lens_runs})
        if args.reference:  # (a) made by another process, finished by now
            result["runs"].append(_finished_run("(a) DTU's photos and calibration", Path(args.reference)))
            for run in lens_runs:
                _compare(result, run)
            save(result)
        for run in result["runs"]:  # the folders are temporary (or --keep's)
            run["out"] = Path(run["out"]).name
            if "capture" in run:
                run["capture"] = Path(run["capture"]).name
    return result


def print_reconstruct(result: dict) -> None:
    rows = []
    for r in result["runs"]:
        pinhole = (r["lenses"] or [{}])[0].get("pinhole")
        crop = r["working_crop"] or {}
        crop = {k: crop[k] for k in ("scaled_width", "scaled_height", "left", "top") if k in crop}
        fair = r.get("original_scored_on_these_photos")
        rows.append(
            [
                r["run"],
                *r["psnr"],
                r["held_out_psnr"],
                r.get("minus_original_db"),
                fair["mean_psnr"] if fair else None,
                r.get("minus_original_on_these_photos_db"),
                f"{pinhole['width']}x{pinhole['height']}" if pinhole else "",
                ",".join(f"{k}={v}" for k, v in crop.items()),
                r["cpu_seconds"],
            ]
        )
    names = [Path(n).stem for n in result["runs"][0]["held_out_names"]]
    headers = ["run", *names, "mean", "- (a)", "(a) on these", "- (a) on these", "pinhole", "crop", "CPU s"]
    print(text_table(headers, rows))
    worst = result.get("worst_minus_original_db")
    print(
        f"worst lens run - (a): {worst if worst is None else round(worst, 3)} dB (target within {result['target_db']})"
    )


PARTS = ("models", "photos", "timing", "reconstruct")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", nargs="+", default=list(PARTS[:3]), choices=PARTS)
    parser.add_argument("--photos", type=int, default=6, help="DTU photos per lens")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads")
    parser.add_argument("--keep", default="", help="reconstruct: keep the captures and runs under this folder")
    parser.add_argument("--figure", default=str(ROOT / "docs" / "images" / "lens_capture_held_out.jpg"))
    parser.add_argument("--dialects", nargs="+", default=["COLMAP", "nerfstudio"], choices=["COLMAP", "nerfstudio"])
    parser.add_argument("--lenses", nargs="+", default=list(RECONSTRUCT_LENSES), choices=list(RECONSTRUCT_LENSES))
    parser.add_argument(
        "--focal-scale",
        type=float,
        default=1.04,
        help="reconstruct: the lenses' focal length times the calibration's (default 1.04: both lenses then see "
        "only within the DTU photos, as a real lens sees the scene; at 1 the lens photos hold a blank border "
        "that no fit of the scene reproduces)",
    )
    parser.add_argument("--reference", default="", help="reconstruct: a finished (a) run folder, not run again")
    parser.add_argument("--out", default="lens_capture", help="reconstruct: results file (a name or a path)")
    parser.add_argument("--cli-args", nargs=argparse.REMAINDER, default=[], help="more reconstruct flags (last)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if "reconstruct" in args.parts:
        written = []

        def save(partial: dict) -> None:
            written[:] = [write_results(args.out, {"machine": machine(), "cli_args": args.cli_args, **partial})]

        result = reconstruct(args, save)
        if result is not None:
            print_reconstruct(result)
            print(f"wrote {written[0]}")
    quick = [p for p in args.parts if p != "reconstruct"]
    if not quick:
        return
    result = {"machine": machine()}
    if "models" in quick:
        result["models"] = models()
    if "photos" in quick:
        result["photos"] = photos(args.photos)
    if "timing" in quick:
        result["timing"] = timing(args.repeats)
    path = write_results("undistort", result)
    if "models" in result:
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
    if "photos" in result:
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
    if "timing" in result:
        print(result["timing"])
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
