"""Per-scene optimization benchmark: held-out quality against seconds, beside the unrefined fusion
and the refinement, on real captures; geometry before and after on the procedural rooms.

    python benchmarks/optimize.py                                   # fern, dtu, rooms; every point
    python benchmarks/optimize.py --parts fern --fern-size 176 240  # fern at half the working size
    python benchmarks/optimize.py --points '[{"steps": 50}]'        # other OptimizeConfig points

Parts (each writes its entry of benchmarks/results/optimize.json as soon as it is measured, and
prints a table):
- fern: LLFF fern, cameras from poses_bounds.npy, 17 context views (all but 0, 8, 16: IMG_4026,
  IMG_4034, IMG_4042 held out, `holdout_every=8`), at `--fern-size` (the working size `reconstruct`
  picks is 368x496). One fused scene (no refinement), then from it: the refinement with its
  defaults, and each optimization point of POINTS. Held-out PSNR / SSIM (and LPIPS where its
  weights are) and the seconds of each, the network and fusion's seconds apart.
- dtu: DTU scan 24, views 13..25 with `holdout_every=2` (13, 15, ..., 25 held out; 6 context
  views), at `--dtu-size`; the same rows.
- rooms: procedural rooms (`surfsplat.data.synthetic`), 25 frames at 64x64 along a 1 m path with
  exact cameras, every 4th held out: held-out PSNR, depth AbsRel and the median normal error
  (degrees) against the exact truth, over pixels the scene covers, before and after each point.
The model is `tiny-synthetic` (64x64 rooms): on real photos it starts far from the truth, which is
what the optimization has to make up.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import torch

from common import machine, sample_data, text_table, write_results

# OptimizeConfig fields of each point (the steps' budget first, then one change at a time at 100 steps)
POINTS = [
    {"steps": 25},
    {"steps": 50},
    {"steps": 100},
    {"steps": 200},
    {"steps": 100, "views_per_step": 1},
    {"steps": 100, "views_per_step": 4},
    {"steps": 100, "scale": 0.5},
    {"steps": 100, "lr_scale": 3.0},
    {"steps": 100, "normal_weight": 0.0},
    {"steps": 100, "prunings": 0},
    {"steps": 100, "parameters": ["scales", "opacities", "sh"]},
]


def held_out(scene_gaussians, fused, cameras, images) -> dict:
    """PSNR / SSIM / LPIPS (where available) of surfels from held-out cameras, as `reconstruct` scores them."""
    from surfsplat.reconstruction.scene import HeldOut

    scene = dataclasses.replace(fused, gaussians=scene_gaussians, holdout=None)
    h = HeldOut(["held"] * len(cameras), cameras, images)
    h.score(scene.render(cameras))
    scores = h.scores()
    return {k: scores[k] for k in ("mean_psnr", "mean_ssim", "mean_lpips", "mean_coverage")}


def real_capture(args, name: str, folder, images: str, indices: list[int], every: int, size) -> dict:
    """One fused scene of the context views, then the refinement and each point from it."""
    import surfsplat
    from surfsplat.capture import OptimizeConfig, RefineConfig, optimize_on_views, refine_on_views
    from surfsplat.data.cameras import load_cameras
    from surfsplat.data.images import list_images

    photos = [list_images(folder / images)[i] for i in indices]
    cameras = load_cameras(folder, images=images)
    options = surfsplat.CaptureOptions(holdout_every=every, refine=RefineConfig(steps=0))
    start = time.perf_counter()
    fused = surfsplat.reconstruct(photos, "tiny-synthetic", cameras=cameras, size=size, capture=options, progress=False)
    network_seconds = time.perf_counter() - start
    h = fused.holdout
    context_images = _context_images(fused, photos, size)
    result = {
        "context": fused.names,
        "held_out": h.names,
        "size": [fused.height, fused.width],
        "surfels": len(fused.gaussians),
        "seconds_network_and_fusion": network_seconds,
        "stages": fused.seconds,
        "lpips": h.lpips_note or "computed",
        "rows": [],
    }

    def add(row: dict) -> None:
        result["rows"].append(row)
        print(f"{name} {json.dumps(row)}", flush=True)
        args.save()

    add({"what": "fusion (unrefined)", "seconds": 0.0, **held_out(fused.gaussians, fused, h.cameras, h.images)})
    refined, stats = refine_on_views(
        fused.gaussians,
        fused.cameras,
        context_images,
        fused.width,
        fused.height,
        RefineConfig(),
        mode=fused.mode,
        alpha_threshold=fused.alpha_threshold,
    )
    add(
        {
            "what": "refinement (defaults)",
            "steps": stats["steps"],
            "seconds": stats["seconds"],
            **held_out(refined, fused, h.cameras, h.images),
        }
    )
    args.results[args.key] = result
    for point in args.points:
        config = OptimizeConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in point.items()})
        fitted, stats = optimize_on_views(
            fused.gaussians,
            fused.cameras,
            context_images,
            fused.width,
            fused.height,
            config,
            mode=fused.mode,
            alpha_threshold=fused.alpha_threshold,
        )
        add(
            {
                "what": "optimize",
                **point,
                "seconds": stats["seconds"],
                "surfels_after": stats["surfels_after"],
                "context_psnr_after": -10 * torch.log10(torch.tensor(stats["mse_after"])).item(),
                **held_out(fitted, fused, h.cameras, h.images),
            }
        )
    return result


def _context_images(fused, photos, size) -> torch.Tensor:
    """The context photos at the scene's working size, as `reconstruct` gave them to the network."""
    from surfsplat.data.images import read_image
    from surfsplat.data.transforms import rescale_and_crop

    by_name = {p.name: p for p in photos}
    stack = torch.stack([read_image(by_name[n], background=(0.0, 0.0, 0.0))[0] for n in fused.names])
    out, _, _ = rescale_and_crop(stack, torch.eye(3).expand(len(stack), 3, 3), (fused.height, fused.width))
    return out.clamp(0, 1)


def rooms(args) -> dict:
    """Held-out PSNR, depth AbsRel and median normal error on the procedural rooms, before and after."""
    import capture as capture_benchmark  # the rooms' straight paths
    import surfsplat
    from surfsplat.capture import OptimizeConfig, RefineConfig, frame_name, optimize_on_views
    from surfsplat.data.cameras import CameraSet
    from surfsplat.data.synthetic import make_scene, render_synthetic
    from surfsplat.metrics import angular_error_deg, psnr
    from surfsplat.render import render

    size, n = 64, 25
    held = torch.tensor([i for i in range(n) if i % 4 == 0])
    ctx = torch.tensor([i for i in range(n) if i % 4])

    def scores(g, fused, cams, truth) -> dict:
        out = render(g, cams, size, size, mode=fused.mode, alpha_threshold=fused.alpha_threshold)
        covered = (out.alpha >= 0.5) & (truth.depth > 0)
        absrel = ((out.depth - truth.depth).abs() / truth.depth.clamp_min(1e-6))[covered].mean()
        angles = angular_error_deg(out.normal.permute(0, 2, 3, 1), truth.normal.permute(0, 2, 3, 1))[covered[:, 0]]
        return {
            "psnr": float(psnr(out.color.clamp(0, 1), truth.image).mean()),
            "depth_absrel": float(absrel),
            "normal_median_deg": float(angles.median()),
        }

    per_point: dict[str, list] = {}
    for seed in range(args.rooms):
        room = make_scene(1000 + seed)
        path = capture_benchmark.long_path(room, torch.Generator().manual_seed(seed), 1.0)
        cams = path.cameras(torch.linspace(0, 1, n), size, size)
        truth = render_synthetic(room, cams, size, size)
        every = CameraSet(cams, size, size, [frame_name(i) for i in range(n)], 0.5, 15.0)
        options = surfsplat.CaptureOptions(holdout_every=4, refine=RefineConfig(steps=0))
        fused = surfsplat.reconstruct(
            list(truth.image), "tiny-synthetic", cameras=every, capture=options, progress=False
        )
        held_truth = type(truth)(**{f.name: getattr(truth, f.name)[held] for f in dataclasses.fields(truth)})
        per_point.setdefault("network (fusion)", []).append(
            {"seconds": 0.0, **scores(fused.gaussians, fused, cams[held], held_truth)}
        )
        refined = surfsplat.reconstruct(
            list(truth.image),
            "tiny-synthetic",
            cameras=every,
            capture=dataclasses.replace(options, refine=RefineConfig()),
            progress=False,
        )
        per_point.setdefault("refinement (defaults)", []).append(
            {"seconds": refined.seconds.get("refine", 0.0), **scores(refined.gaussians, fused, cams[held], held_truth)}
        )
        for point in args.room_points:
            config = OptimizeConfig(**point)
            fitted, stats = optimize_on_views(
                fused.gaussians,
                fused.cameras,
                truth.image[ctx],
                size,
                size,
                config,
                mode=fused.mode,
                alpha_threshold=fused.alpha_threshold,
            )
            per_point.setdefault(json.dumps(point), []).append(
                {"seconds": stats["seconds"], **scores(fitted, fused, cams[held], held_truth)}
            )
        print(f"room {1000 + seed} measured", flush=True)
    rows = []
    for what, runs in per_point.items():
        rows.append({"what": what, **{k: sum(r[k] for r in runs) / len(runs) for k in runs[0]}})
        print(f"rooms {json.dumps(rows[-1])}", flush=True)
    return {"rooms": args.rooms, "size": [size, size], "frames": n, "held_out_every": 4, "rows": rows}


def print_table(results: dict) -> None:
    for key in ("fern", "dtu_scan24"):
        if key not in results:
            continue
        r = results[key]
        print(
            f"\n{key}: {len(r['context'])} context views at {r['size'][1]}x{r['size'][0]}, {r['surfels']:,} surfels; "
            f"network and fusion {r['seconds_network_and_fusion']:.1f} s; LPIPS: {r['lpips']}"
        )
        rows = [
            [
                row["what"],
                json.dumps({k: v for k, v in row.items() if k not in _COLUMNS})[1:-1],
                row["seconds"],
                row["mean_psnr"],
                row["mean_ssim"],
                row["mean_lpips"],
            ]
            for row in r["rows"]
        ]
        print(text_table(["what", "point", "seconds", "PSNR", "SSIM", "LPIPS"], rows))
    if "rooms" in results:
        rows = [
            [r["what"], r["seconds"], r["psnr"], r["depth_absrel"], r["normal_median_deg"]]
            for r in results["rooms"]["rows"]
        ]
        print(f"\nrooms ({results['rooms']['rooms']}), held-out views")
        print(text_table(["what", "seconds", "PSNR", "depth AbsRel", "normal median (deg)"], rows))


_COLUMNS = {
    "what",
    "seconds",
    "mean_psnr",
    "mean_ssim",
    "mean_lpips",
    "mean_coverage",
    "surfels_after",
    "context_psnr_after",
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--parts", nargs="+", default=["fern", "dtu", "rooms"], choices=["fern", "dtu", "rooms"])
    parser.add_argument("--fern-size", nargs=2, type=int, default=[368, 496], metavar=("H", "W"))
    parser.add_argument("--dtu-size", nargs=2, type=int, default=[288, 400], metavar=("H", "W"))
    parser.add_argument("--points", type=json.loads, default=POINTS, help="a JSON list of OptimizeConfig fields")
    parser.add_argument(
        "--room-points", type=json.loads, default=[{"steps": 50}, {"steps": 100}, {"steps": 100, "normal_weight": 0.0}]
    )
    parser.add_argument("--rooms", type=int, default=2)
    parser.add_argument("--out", default="optimize", help="results file (a name under benchmarks/results or a path)")
    args = parser.parse_args()
    torch.manual_seed(0)
    data = sample_data()
    args.results = {"machine": machine(), "parts": args.parts}

    def save() -> None:
        write_results(args.out, args.results)

    args.save = save
    runs = {
        "fern": lambda: real_capture(
            args, "fern", data / "llff_fern", "images_8", list(range(20)), 8, tuple(args.fern_size)
        ),
        "dtu": lambda: real_capture(
            args, "dtu", data / "dtu_scan24", "images_4", list(range(13, 26)), 2, tuple(args.dtu_size)
        ),
        "rooms": lambda: rooms(args),
    }
    for part in args.parts:  # in the order asked for
        args.key = {"dtu": "dtu_scan24"}.get(part, part)
        args.results[args.key] = runs[part]()
        save()
    print_table(args.results)


if __name__ == "__main__":
    main()
