"""Capture benchmark: one fused scene from many views against two-view reconstructions, and the
cost of a video against its length.

    python benchmarks/capture.py                          # rooms, DTU, fern, video 10 and 50 frames
    python benchmarks/capture.py --parts video --frames 10 50 300      # the 300-frame 1080p video too
    python benchmarks/capture.py --parts rooms --rooms 2 --no-room-video   # quicker: held-out scores only
    python benchmarks/capture.py --parts video --frames 300 --min-motion 0   # every frame of the video kept

Parts (each writes its entry of benchmarks/results/capture.json and prints a table):
- rooms: procedural rooms (`make_scene`), cameras on a straight path of `--path-length` metres
  through the room (the training paths are 0.15-0.6 m) rendered as 25 frames at 64x64 with the
  exact cameras; frames 0, 4, 8, ... are held out. The fused scene of the 18 others against the
  two-view reconstruction from the two context frames at the path's ends: held-out PSNR,
  coverage (alpha >= 0.5) and depth AbsRel against the exact depth (over pixels both cover).
  Beside them: the fused scene without its refinement on the context views, and the two-view
  scene refined the same way on its two photos (`refine_on_views`).
  Then the same frames as an MP4 at 256x256 with the cameras estimated from it (`reconstruct`
  on the video): pairwise rotation and translation-direction errors against the truth, and the
  held-out PSNR in the estimated frame. And surfels against the area covered: one path, 9 / 17 /
  33 frames, and paths of 0.5 / 1 / 1.5 / 2 m at one frame every 6 cm.
- dtu / fern: all views of DTU scan 24 (49) and LLFF fern (20) with their calibrations, every
  8th held out: held-out PSNR of the fused scene against the best pair of neighbouring context
  views (the pair whose two-view reconstruction scores best on the held-out views).
- video: a synthetic 1080p video (the room ray-cast at 480x270, upscaled by ffmpeg to 1920x1080,
  H.264) of 10 / 50 / 300 frames along a 2 m path, reconstructed with the cameras estimated from
  it: seconds per stage and peak memory, each size in a fresh process.
- refine-rooms / refine: held-out PSNR against the refinement's seconds over REFINE_GRID (steps,
  views per step, render scale, early stop), on one fused scene each: the rooms above (unrefined
  fusion, averaged over `--rooms`), and DTU scan 24's views 14, 16, ..., 26 at 288x400 with their
  calibration, scored on views 15, 17, ..., 25.
- e2e: `surfsplat reconstruct` with default settings and every default output, in a fresh process:
  a 3-second clip of DTU scan 24 (views 14, 16, ..., 26 held for 4 frames each at 10 fps,
  400x300), two 400x300 DTU photos (cameras estimated), and the 10-second 1080p video above
  (300 frames); wall seconds and the stage times `reconstruction.json` records. `dtu49` and
  `dtu49-posefree`: a 50-photo capture's whole `reconstruct --holdout-every 8 --formats ply --raw-3dgs`
  (all 49 views of DTU scan 24 at 400x300, with their calibration, then with the cameras estimated),
  CPU seconds and held-out PSNR beside the wall seconds.
    python benchmarks/capture.py --parts e2e --e2e clip photos video
    python benchmarks/capture.py --parts e2e --e2e dtu49 dtu49-posefree
The model is `tiny-synthetic` (64x64 rooms); on real photos it reconstructs poorly, which the
numbers show.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from common import RESULTS

SIZE = 64


# ----------------------------------------------------------------------------------------- rooms
def long_path(scene, generator, length: float):
    """A straight path of `length` metres inside the room, keeping the clearance of the training paths."""
    from surfsplat.data.synthetic import Trajectory, make_trajectory
    from surfsplat.data.synthetic.scene import _clearance

    for _ in range(500):
        t = make_trajectory(scene, generator)
        direction = (t.eye1 - t.eye0) / (t.eye1 - t.eye0).norm()
        end = t.eye0 + length * direction
        s = torch.linspace(0, 1, 40, dtype=torch.float64)[:, None]
        if bool((_clearance(scene, t.eye0 * (1 - s) + end * s) > 0.8).all()):
            return Trajectory(t.eye0, end, t.target0, t.target1, t.fov_deg)
    raise RuntimeError(f"no {length} m path fits in this room")


def held_out_scores(scene, cameras, images, depths):
    """PSNR, coverage and depth AbsRel of a scene's renders at cameras against exact images/depths."""
    from surfsplat.metrics import psnr

    out = scene.render(cameras)
    covered = out.alpha >= 0.5
    valid = covered & (depths > 0)
    absrel = ((out.depth - depths).abs() / depths.clamp_min(1e-6))[valid].mean()
    return {
        "psnr": float(psnr(out.color.clamp(0, 1), images).mean()),
        "coverage": float(covered.float().mean()),
        "depth_absrel": float(absrel),
    }


def rooms(args, model) -> dict:
    import surfsplat
    from surfsplat.capture import RefineConfig, frame_name, refine_on_views
    from surfsplat.data.cameras import CameraSet
    from surfsplat.data.synthetic import make_scene, render_synthetic

    rows = []
    n = 25
    for seed in range(args.rooms):
        room = make_scene(1000 + seed)
        path = long_path(room, torch.Generator().manual_seed(seed), args.path_length)
        cams = path.cameras(torch.linspace(0, 1, n), SIZE, SIZE)
        truth = render_synthetic(room, cams, SIZE, SIZE)
        names = [frame_name(i) for i in range(n)]
        every = CameraSet(cams, SIZE, SIZE, names, 0.5, 15.0)
        options = surfsplat.CaptureOptions(holdout_every=4)
        start = time.perf_counter()
        fused = surfsplat.reconstruct(list(truth.image), model, cameras=every, capture=options, progress=False)
        seconds = time.perf_counter() - start
        held = [i for i in range(n) if i % 4 == 0]
        ctx = [i for i in range(n) if i % 4]
        ends = [ctx[0], ctx[-1]]
        two = surfsplat.reconstruct(
            [truth.image[i] for i in ends],
            model,
            cameras=CameraSet(cams[torch.tensor(ends)], SIZE, SIZE, ["a", "b"], 0.5, 15.0),
            progress=False,
        )
        h = torch.tensor(held)
        # the same fusion without the refinement, and the two-view scene refined the same way on its two photos
        unrefined = surfsplat.reconstruct(
            list(truth.image),
            model,
            cameras=every,
            capture=surfsplat.CaptureOptions(holdout_every=4, refine=RefineConfig(steps=0)),
            progress=False,
        )
        two_g, _ = refine_on_views(
            two.gaussians,
            two.cameras,
            truth.image[ends],
            SIZE,
            SIZE,
            mode=two.mode,
            alpha_threshold=two.alpha_threshold,
        )
        two_refined = dataclasses.replace(two, gaussians=two_g)
        row = {
            "seed": 1000 + seed,
            "fused": held_out_scores(fused, cams[h], truth.image[h], truth.depth[h]),
            "fused_unrefined": held_out_scores(unrefined, cams[h], truth.image[h], truth.depth[h]),
            "two_view": held_out_scores(two, cams[h], truth.image[h], truth.depth[h]),
            "two_view_refined": held_out_scores(two_refined, cams[h], truth.image[h], truth.depth[h]),
            "refine": fused.refine_stats,
            "surfels_fused": len(fused.gaussians),
            "surfels_two_view": len(two.gaussians),
            "predicted": fused.fusion_stats["predicted"],
            "seconds": seconds,
        }
        if not args.no_room_video:
            row["video_seconds"], row["video"] = room_video(room, cams, model)
        rows.append(row)
        print(f"room {1000 + seed}: {json.dumps(row)}", flush=True)
    result = {"path_length_m": args.path_length, "frames": n, "held_out_every": 4, "rooms": rows}
    if not args.no_room_video:  # the quick variant keeps the held-out scores only
        result["area"] = surfels_vs_area(model)
    return result


def room_video(room, cams, model) -> tuple[float, dict]:
    """The room's path as an MP4, reconstructed with the cameras estimated from it: seconds, and the
    pose errors against the true cameras with the held-out scores in the estimated frame."""
    import surfsplat
    from surfsplat.capture import FrameConfig
    from surfsplat.data.synthetic import render_synthetic
    from surfsplat.export.video import write_video
    from surfsplat.poses.errors import relative_pose_errors

    with tempfile.TemporaryDirectory() as tmp:
        big = render_synthetic(room, cams.scaled(4), 4 * SIZE, 4 * SIZE).image
        write_video(Path(tmp) / "room.mp4", big, fps=10, quality=9)
        options = surfsplat.CaptureOptions(holdout_every=4, frames=FrameConfig(min_motion=0.0))
        start = time.perf_counter()
        video = surfsplat.reconstruct(Path(tmp) / "room.mp4", model, size=(SIZE, SIZE), capture=options, progress=False)
        seconds = time.perf_counter() - start
    used = [int(name.split("_")[1]) for name in video.pose_cameras.names]
    rot, trans = relative_pose_errors(video.pose_cameras.cameras.c2w, cams.c2w.double()[torch.tensor(used)])
    return seconds, {
        "registered": len(used),
        "rotation_error_max_deg": float(rot.max()),
        "translation_direction_error_max_deg": float(trans.max()),
        "held_out_psnr": video.holdout.to_dict()["mean_psnr"],
        "held_out_coverage": video.holdout.to_dict()["mean_coverage"],
    }


def surfels_vs_area(model) -> dict:
    import surfsplat
    from surfsplat.data.cameras import CameraSet
    from surfsplat.data.synthetic import make_scene, render_synthetic

    room = make_scene(1000)
    out = {"frames_on_one_path": [], "path_length": []}
    path = long_path(room, torch.Generator().manual_seed(0), 1.5)
    for n in (9, 17, 33):
        cams = path.cameras(torch.linspace(0, 1, n), SIZE, SIZE)
        images = render_synthetic(room, cams, SIZE, SIZE).image
        every = CameraSet(cams, SIZE, SIZE, [f"v{i}" for i in range(n)], 0.5, 15.0)
        scene = surfsplat.reconstruct(list(images), model, cameras=every, progress=False)
        out["frames_on_one_path"].append({"frames": n, "surfels": len(scene.gaussians)})
    for length in (0.5, 1.0, 1.5, 2.0):
        path = long_path(room, torch.Generator().manual_seed(0), length)
        n = max(3, round(length / 0.06) + 1)
        cams = path.cameras(torch.linspace(0, 1, n), SIZE, SIZE)
        images = render_synthetic(room, cams, SIZE, SIZE).image
        every = CameraSet(cams, SIZE, SIZE, [f"v{i}" for i in range(n)], 0.5, 15.0)
        scene = surfsplat.reconstruct(list(images), model, cameras=every, progress=False)
        out["path_length"].append({"metres": length, "frames": n, "surfels": len(scene.gaussians)})
    return out


# ----------------------------------------------------------------------------------------- real scenes
def real_scene(args, model, name: str, folder: Path, images: str, size: tuple[int, int]) -> dict:
    import surfsplat
    from surfsplat.data.cameras import load_cameras
    from surfsplat.data.images import list_images
    from surfsplat.metrics import psnr

    photos = list_images(folder / images)
    cameras = load_cameras(folder, images=images)
    options = surfsplat.CaptureOptions(holdout_every=8)
    start = time.perf_counter()
    fused = surfsplat.reconstruct(photos, model, cameras=cameras, size=size, capture=options, progress=False)
    seconds = time.perf_counter() - start
    h = fused.holdout
    ctx = [p for i, p in enumerate(photos) if i % 8]
    pairs = []
    for a, b in zip(ctx, ctx[1:]):
        two = surfsplat.reconstruct([a, b], model, cameras=cameras, size=size, progress=False)
        out = two.render(h.cameras)
        pairs.append(
            {
                "pair": [a.name, b.name],
                "psnr": float(psnr(out.color.clamp(0, 1), h.images).mean()),
                "coverage": float((out.alpha >= 0.5).float().mean()),
            }
        )
    best = max(pairs, key=lambda p: p["psnr"])
    result = {
        "views": len(photos),
        "held_out": h.names,
        "size": list(size),
        "fused": h.to_dict(),
        "surfels_fused": len(fused.gaussians),
        "best_pair": best,
        "pairs": pairs,
        "seconds": seconds,
    }
    print(f"{name}: fused {result['fused']['mean_psnr']:.2f} dB, best pair {best['psnr']:.2f} dB", flush=True)
    return result


# ----------------------------------------------------------------------------------------- refinement
REFINE_GRID = [  # RefineConfig fields of each point; the first is the refinement when fast captures were asked for
    {"steps": 100, "views_per_step": 16, "lr": 0.01},
    {"steps": 0},
    {"steps": 50, "views_per_step": 6, "lr": 0.02},
    {"steps": 25, "views_per_step": 6, "lr": 0.02},
    {"steps": 25, "views_per_step": 6, "lr": 0.04},
    {"steps": 20, "views_per_step": 16, "lr": 0.03},
    {"steps": 15, "views_per_step": 6, "lr": 0.05},
    {"steps": 50, "views_per_step": 6, "lr": 0.03, "patience": 5},
]


def _refine_fields(config) -> dict:
    """The knobs of a refinement point, for its row."""
    return {k: getattr(config, k) for k in ("steps", "views_per_step", "lr", "scale", "patience")}


def views_at(folder: Path, images: str, indices: list[int], shape: tuple[int, int]):
    """Calibrated views of a scene folder at the network's working size, as `reconstruct` gives them
    to the network: (Cameras with K in working-size pixels, images [V, 3, H, W])."""
    import imageio.v3 as iio

    from surfsplat import Cameras
    from surfsplat.data.cameras import load_cameras
    from surfsplat.data.images import list_images
    from surfsplat.data.transforms import rescale_and_crop

    paths = [list_images(folder / images)[i] for i in indices]
    stack = torch.stack([torch.from_numpy(iio.imread(p)[..., :3].copy()).permute(2, 0, 1).float() / 255 for p in paths])
    calibrated = load_cameras(folder, images=images).select([p.name for p in paths], str(folder))
    K = calibrated.resized(stack.shape[-1], stack.shape[-2], str(folder)).K
    stack, K_net, _ = rescale_and_crop(stack, K.to(torch.float32), shape)
    return Cameras(calibrated.cameras.c2w.to(torch.float32), K_net), stack.clamp(0, 1), paths


def refine_curve_rooms(args, model) -> dict:
    """Held-out PSNR against refinement seconds over REFINE_GRID on the rooms (the part `rooms`
    measures with the default refinement), averaged over `--rooms` rooms."""
    import surfsplat
    from surfsplat.capture import RefineConfig, frame_name, refine_on_views
    from surfsplat.data.cameras import CameraSet
    from surfsplat.data.synthetic import make_scene, render_synthetic
    from surfsplat.metrics import psnr
    from surfsplat.render import render

    n = 25
    held = torch.tensor([i for i in range(n) if i % 4 == 0])
    ctx = torch.tensor([i for i in range(n) if i % 4])
    per_config = [[] for _ in REFINE_GRID]
    for seed in range(args.rooms):
        room = make_scene(1000 + seed)
        path = long_path(room, torch.Generator().manual_seed(seed), args.path_length)
        cams = path.cameras(torch.linspace(0, 1, n), SIZE, SIZE)
        truth = render_synthetic(room, cams, SIZE, SIZE)
        every = CameraSet(cams, SIZE, SIZE, [frame_name(i) for i in range(n)], 0.5, 15.0)
        options = surfsplat.CaptureOptions(holdout_every=4, refine=RefineConfig(steps=0))
        fused = surfsplat.reconstruct(list(truth.image), model, cameras=every, capture=options, progress=False)
        for k, point in enumerate(REFINE_GRID):
            config = RefineConfig(**point)
            refined, stats = refine_on_views(
                fused.gaussians,
                fused.cameras,
                truth.image[ctx],
                SIZE,
                SIZE,
                config,
                mode=fused.mode,
                alpha_threshold=fused.alpha_threshold,
            )
            out = render(refined, cams[held], SIZE, SIZE, mode=fused.mode, alpha_threshold=fused.alpha_threshold)
            per_config[k].append(
                {
                    "steps_run": stats["steps"],
                    "seconds": stats["seconds"],
                    "held_out_psnr": float(psnr(out.color.clamp(0, 1), truth.image[held]).mean()),
                }
            )
    rows = []
    for point, runs in zip(REFINE_GRID, per_config):
        rows.append(
            {
                **_refine_fields(RefineConfig(**point)),
                "steps_run": sum(r["steps_run"] for r in runs) / len(runs),
                "seconds": sum(r["seconds"] for r in runs) / len(runs),
                "held_out_psnr": sum(r["held_out_psnr"] for r in runs) / len(runs),
            }
        )
        print(f"rooms refine {json.dumps(rows[-1])}", flush=True)
    return {"rooms": args.rooms, "context_views": len(ctx), "size": [SIZE, SIZE], "rows": rows}


def refine_curve(model, name: str, folder: Path, images: str, context: list[int], held: list[int], size) -> dict:
    """Held-out PSNR against refinement seconds over REFINE_GRID, on one fused scene of the
    `context` views (cameras given), scored on the `held` views."""
    import surfsplat
    from surfsplat.capture import RefineConfig, refine_on_views
    from surfsplat.data.cameras import load_cameras
    from surfsplat.metrics import psnr
    from surfsplat.render import render

    context_cams, context_images, paths = views_at(folder, images, context, size)
    held_cams, held_images, _ = views_at(folder, images, held, size)
    options = surfsplat.CaptureOptions(refine=RefineConfig(steps=0))
    cameras = load_cameras(folder, images=images)
    start = time.perf_counter()
    fused = surfsplat.reconstruct(paths, model, cameras=cameras, size=size, capture=options, progress=False)
    seconds_unrefined = time.perf_counter() - start
    assert torch.allclose(fused.cameras.K, context_cams.K) and fused.names == [p.name for p in paths]
    rows = []
    for point in REFINE_GRID:
        config = RefineConfig(**point)
        refined, stats = refine_on_views(
            fused.gaussians,
            fused.cameras,
            context_images,
            fused.width,
            fused.height,
            config,
            mode=fused.mode,
            alpha_threshold=fused.alpha_threshold,
        )
        out = render(
            refined, held_cams, fused.width, fused.height, mode=fused.mode, alpha_threshold=fused.alpha_threshold
        )
        rows.append(
            {
                **_refine_fields(config),
                "steps_run": stats["steps"],
                "seconds": stats["seconds"],
                "held_out_psnr": float(psnr(out.color.clamp(0, 1), held_images).mean()),
                "kept": stats["kept"],
            }
        )
        print(f"{name} refine {json.dumps(rows[-1])}", flush=True)
    return {
        "context": [p.name for p in paths],
        "held_out": held,
        "surfels": len(fused.gaussians),
        "size": list(size),
        "seconds_without_refinement": seconds_unrefined,
        "rows": rows,
    }


# ----------------------------------------------------------------------------------------- video cost
def write_1080p_video(path: Path, frames: int) -> None:
    """The room along a 2 m path, ray-cast at 480x270 and upscaled by ffmpeg to 1920x1080 (H.264)."""
    import imageio_ffmpeg
    import numpy as np

    from surfsplat.data.synthetic import make_scene, render_synthetic

    room = make_scene(1000)
    trajectory = long_path(room, torch.Generator().manual_seed(0), 2.0)
    writer = imageio_ffmpeg.write_frames(
        str(path),
        (480, 270),
        fps=30,
        codec="libx264",
        quality=8,
        macro_block_size=2,
        output_params=["-vf", "scale=1920:1080:flags=bicubic"],
    )
    writer.send(None)
    for s in torch.linspace(0, 1, frames).split(10):
        images = render_synthetic(room, trajectory.cameras(s, 480, 270), 480, 270).image
        for image in images:
            writer.send(np.ascontiguousarray((image.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)))
    writer.close()


def video_cost(frames: int, min_motion: float | None) -> dict:
    """Run in a fresh process: seconds per stage and peak memory of reconstructing the video
    (`min_motion`: the frame filter's motion threshold, None: its default)."""
    import surfsplat
    from surfsplat.capture import FrameConfig
    from surfsplat.evaluation import peak_rss_bytes

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "capture.mp4"
        start = time.perf_counter()
        write_1080p_video(path, frames)
        made = time.perf_counter() - start
        base = peak_rss_bytes()
        start = time.perf_counter()
        frame_config = FrameConfig() if min_motion is None else FrameConfig(min_motion=min_motion)
        capture = surfsplat.CaptureOptions(frames=frame_config)
        scene = surfsplat.reconstruct(path, "tiny-synthetic", size=(SIZE, 112), capture=capture, progress=False)
        seconds = time.perf_counter() - start
    video = scene.video
    return {
        "frames": frames,
        "min_motion": frame_config.min_motion,
        "used": len(video.indices),
        "registered": len(scene.names),
        "dropped": video.dropped(),
        "seconds": seconds,
        "stages": scene.seconds,
        "seconds_writing_the_video": made,
        "peak_rss_bytes": peak_rss_bytes(),
        "peak_rss_bytes_before": base,
        "surfels": len(scene.gaussians),
    }


# ----------------------------------------------------------------------------------------- end to end
CLIP_VIEWS = list(range(14, 27, 2))  # seven neighbouring DTU views, each held for 4 frames at 10 fps


def write_dtu_clip(data: Path, path: Path, views: list[int] = CLIP_VIEWS, hold: int = 4, fps: int = 10) -> None:
    """A short clip of a DTU scan as a person with a phone makes one: each view held for `hold` frames."""
    import imageio.v3 as iio
    import imageio_ffmpeg
    import numpy as np

    from surfsplat.data.images import list_images

    photos = [list_images(data / "dtu_scan24" / "images_4")[i] for i in views]
    frames = [np.ascontiguousarray(iio.imread(p)[..., :3]) for p in photos]
    height, width = frames[0].shape[:2]
    writer = imageio_ffmpeg.write_frames(str(path), (width, height), fps=fps, codec="libx264", quality=8)
    writer.send(None)
    for frame in frames:
        for _ in range(hold):
            writer.send(frame)
    writer.close()


def run_cli(arguments: list[str], out: Path) -> dict:
    """`surfsplat reconstruct ARGUMENTS --out OUT` in a fresh process: wall seconds, exit code and the
    stage times `reconstruction.json` records."""
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    child = subprocess.run(
        [sys.executable, "-m", "surfsplat", "reconstruct", *arguments, "--out", str(out)],
        capture_output=True,
        text=True,
        check=False,
    )
    seconds = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    record = {"arguments": arguments, "seconds": seconds, "cpu_seconds": cpu, "exit_code": child.returncode}
    # the largest child's peak so far: the run's own where it is the largest process this benchmark started
    record["peak_rss_mb_children"] = after.ru_maxrss / 1024
    summary = out / "reconstruction.json"
    if child.returncode != 0 or not summary.is_file():
        record["error"] = (child.stderr.strip().splitlines() or ["no output"])[-1]
        return record
    document = json.loads(summary.read_text())
    record["stages"] = document.get("seconds", {})
    record["surfels"] = document.get("surfels")
    record["refine"] = document.get("capture", {}).get("refine")  # the fit's colour error before and after
    record["outputs"] = sorted(p.name for p in out.iterdir())
    held = document.get("capture", {}).get("held_out")
    if held:
        record["held_out_psnr"] = held.get("mean_psnr")
    return record


def end_to_end(args) -> dict:
    """Default settings, every default output: the DTU clip, two DTU photos, a 10-second 1080p video."""
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if "clip" in args.e2e:
            clip = tmp / "clip.mp4"
            write_dtu_clip(args.data, clip)
            results["clip"] = run_cli(["--video", str(clip), "--checkpoint", "tiny-synthetic"], tmp / "clip")
            print(f"clip: {json.dumps(results['clip'])}", flush=True)
        if "photos" in args.e2e:
            from surfsplat.data.images import list_images

            every = list_images(args.data / "dtu_scan24" / "images_4")
            photos = [str(every[33]), str(every[31])]
            results["photos"] = run_cli(["--images", *photos, "--checkpoint", "tiny-synthetic"], tmp / "photos")
            print(f"photos: {json.dumps(results['photos'])}", flush=True)
        if "dtu49" in args.e2e or "dtu49-posefree" in args.e2e:
            # a 50-photo capture: all 49 views of DTU scan 24 at 400x300, every 8th held out, as a phone capture's
            # whole reconstruct is measured (its cameras given, then estimated from the photos)
            from surfsplat.data.images import list_images

            every = [str(p) for p in list_images(args.data / "dtu_scan24" / "images_4")]
            flags = ["--holdout-every", "8", "--formats", "ply", "--raw-3dgs"]
            given = ["--cameras", str(args.data / "dtu_scan24"), "--images-folder", "images_4"]
            for name, extra in (("dtu49", given), ("dtu49-posefree", [])):
                if name in args.e2e:
                    results[name] = run_cli(["--images", *every, *extra, *flags], tmp / name)
                    print(f"{name}: {json.dumps(results[name])}", flush=True)
        if "video" in args.e2e:
            video = tmp / "phone.mp4"
            write_1080p_video(video, 300)
            results["video_1080p_10s"] = run_cli(["--video", str(video), "--checkpoint", "tiny-synthetic"], tmp / "v")
            print(f"video: {json.dumps(results['video_1080p_10s'])}", flush=True)
    return results


# ----------------------------------------------------------------------------------------- main
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", nargs="+", default=["rooms", "dtu", "fern", "video"])
    parser.add_argument("--rooms", type=int, default=4)
    parser.add_argument("--path-length", type=float, default=1.5)
    parser.add_argument("--no-room-video", action="store_true", help="rooms: held-out scores only (no video, no area)")
    parser.add_argument("--frames", nargs="+", type=int, default=[10, 50], help="video lengths (300: the long one)")
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    parser.add_argument("--out", type=Path, default=RESULTS / "capture.json", help="results JSON (parts are merged in)")
    parser.add_argument(
        "--min-motion", type=float, default=None, help="video frame filter's motion threshold (0: every frame)"
    )
    parser.add_argument("--e2e", nargs="+", default=["clip", "photos", "video"], help="end-to-end runs of the e2e part")
    parser.add_argument(
        "--refine-points",
        type=json.loads,
        default=None,
        help="refine-rooms / refine: a JSON list of RefineConfig fields instead of REFINE_GRID, e.g. '[{\"steps\": 30}]'",
    )
    parser.add_argument("--one-video", type=int, default=None, help=argparse.SUPPRESS)  # child process
    args = parser.parse_args()
    if args.refine_points is not None:
        REFINE_GRID[:] = args.refine_points
    if args.one_video is not None:
        print(json.dumps(video_cost(args.one_video, args.min_motion)))
        return

    from surfsplat.model.loading import ModelSpec, load_model

    out_path = args.out
    out_path.parent.mkdir(parents=True, exist_ok=True)
    results = json.loads(out_path.read_text()) if out_path.is_file() else {}
    results["machine"] = {"platform": platform.platform(), "cpus": os.cpu_count(), "load": os.getloadavg()}
    model, _ = load_model(ModelSpec("tiny-synthetic"))

    def save() -> None:  # after every part, so a long run keeps what it measured
        results["machine"]["load_after"] = os.getloadavg()
        out_path.write_text(json.dumps(results, indent=1) + "\n")

    if "rooms" in args.parts:
        results["rooms"] = rooms(args, model)
        save()
    if "dtu" in args.parts:
        results["dtu_scan24"] = real_scene(args, model, "DTU scan 24", args.data / "dtu_scan24", "images_4", (64, 80))
        save()
    if "fern" in args.parts:
        results["llff_fern"] = real_scene(args, model, "LLFF fern", args.data / "llff_fern", "images_8", (64, 80))
        save()
    if "refine-rooms" in args.parts:
        results["refine_rooms"] = refine_curve_rooms(args, model)
        save()
    if "refine" in args.parts:
        dtu = args.data / "dtu_scan24"
        results["refine_dtu"] = refine_curve(
            model, "DTU scan 24", dtu, "images_4", list(range(14, 27, 2)), list(range(15, 26, 2)), (288, 400)
        )
        save()
    if "e2e" in args.parts:
        results["end_to_end"] = end_to_end(args)
        save()
    if "video" in args.parts:
        results["video"] = []
        for frames in args.frames:
            command = [sys.executable, __file__, "--one-video", str(frames)]
            if args.min_motion is not None:
                command += ["--min-motion", str(args.min_motion)]
            child = subprocess.run(command, capture_output=True, text=True, check=False)
            if child.returncode != 0:
                results["video"].append({"frames": frames, "error": child.stderr.strip().splitlines()[-1]})
                continue
            results["video"].append(json.loads(child.stdout.strip().splitlines()[-1]))
            print(f"video {frames} frames: {json.dumps(results['video'][-1])}", flush=True)
            save()
    save()
    print_table(results)


def print_table(results: dict) -> None:
    if "rooms" in results:
        print("\nrooms (held-out frames)       PSNR dB   coverage   depth AbsRel   surfels")
        rows = results["rooms"]["rooms"]
        for key in ("fused", "fused_unrefined", "two_view", "two_view_refined"):
            if key not in rows[0]:
                continue

            def mean(k: str, key: str = key) -> float:
                return sum(r[key][k] for r in rows) / len(rows)

            surfels = sum(r["surfels_" + key.removesuffix("_refined").removesuffix("_unrefined")] for r in rows)
            print(
                f"  {key:<27} {mean('psnr'):7.2f}   {mean('coverage'):8.3f}   {mean('depth_absrel'):12.3f}"
                f"   {surfels / len(rows):7.0f}"
            )
        if "area" in results["rooms"]:  # absent in the quick variant (--no-room-video)
            worst_rot = max(r["video"]["rotation_error_max_deg"] for r in rows)
            worst_dir = max(r["video"]["translation_direction_error_max_deg"] for r in rows)
            print(f"  poses from the video: rotation error <= {worst_rot:.2f} deg, direction <= {worst_dir:.2f} deg")
            area = results["rooms"]["area"]
            print(
                "  surfels vs frames on one path: "
                + ", ".join(f"{a['frames']}: {a['surfels']}" for a in area["frames_on_one_path"])
            )
            print(
                "  surfels vs path length: "
                + ", ".join(f"{a['metres']} m: {a['surfels']}" for a in area["path_length"])
            )
    for key in ("dtu_scan24", "llff_fern"):
        if key in results:
            r = results[key]
            print(
                f"{key}: fused {r['fused']['mean_psnr']:.2f} dB (coverage {r['fused']['mean_coverage']:.3f}) vs best pair "
                f"{r['best_pair']['psnr']:.2f} dB ({', '.join(r['best_pair']['pair'])})"
            )
    for v in results.get("video", []):
        if "error" in v:
            print(f"video {v['frames']} frames: failed: {v['error']}")
        else:
            print(
                f"video {v['frames']} frames of 1080p: {v['used']} used, {v['seconds']:.1f} s, "
                f"peak {v['peak_rss_bytes'] / 2**30:.2f} GiB, stages {json.dumps({k: round(s, 1) for k, s in v['stages'].items()})}"
            )
    if "machine" in results:
        print(f"load average before/after: {results['machine']['load']} / {results['machine'].get('load_after')}")


if __name__ == "__main__":
    main()
