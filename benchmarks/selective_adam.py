"""Selective Adam against torch's fused Adam: the optimizer step alone, and a short fit of LLFF fern.

    python benchmarks/selective_adam.py                       # both parts
    python benchmarks/selective_adam.py --parts step --surfels 50000 --visible 0.2 0.9

Parts (results in benchmarks/results/selective_adam.json):
- step: one Adam step over the fit's six tensors of N surfels (SH degree 3), with a share of the
  rows visible (the rest with an exactly zero gradient), the visible rows found from the gradients
  as the fit finds them: milliseconds a step, dense fused and selective alternating, median of the
  repeats.
- fern: LLFF fern's 17 context views at 368x496 (held out IMG_4026, IMG_4034, IMG_4042), COLMAP's
  start triangulated once, then `--steps` steps of the default fit with each optimizer, alternating
  `--rounds` times: the fit's seconds, the step's mean, the held-out PSNR, the surfels.
Both alternate the two optimizers in one process: on a shared machine only their ratio means anything.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from common import machine, sample_data, text_table, write_results


def step_part(surfels: int, shares: list[float], repeats: int) -> list[dict]:
    from surfsplat.capture.adam import SelectiveAdam, visible_rows

    g = torch.Generator().manual_seed(0)
    shapes = [(3,), (4,), (2,), (), (3, 1), (3, 15)]  # means, quats, log scales, logits, SH DC, SH rest
    rows = []
    torch.set_num_threads(1)  # as the fit runs its torch ops (`fit.step_threads`)
    for share in shares:
        seen = torch.rand(surfels, generator=g) < share
        tensors = {}
        for kind in ("dense", "selective"):
            params = [torch.randn(surfels, *s, generator=g).requires_grad_(True) for s in shapes]
            for p in params:
                p.grad = torch.randn(p.shape, generator=g) * seen.reshape(-1, *[1] * (p.dim() - 1))
            groups = [{"params": [p], "lr": 1e-3} for p in params]
            optimizer = torch.optim.Adam(groups, fused=True) if kind == "dense" else SelectiveAdam(groups)
            tensors[kind] = (params, optimizer)
        times = {"dense": [], "selective": []}
        for _ in range(repeats):
            for kind, (params, optimizer) in tensors.items():
                tick = time.perf_counter()
                if kind == "dense":
                    optimizer.step()
                else:
                    optimizer.step(visible_rows(params))
                times[kind].append(time.perf_counter() - tick)
        dense, selective = (1000 * statistics.median(times[k]) for k in ("dense", "selective"))
        rows.append(
            {"surfels": surfels, "visible": share, "dense_ms": dense, "selective_ms": selective,
             "selective_over_dense": selective / dense}
        )  # fmt: skip
        print(rows[-1], flush=True)
    return rows


def fern_part(steps: int, rounds: int) -> dict:
    import surfsplat
    from optimize import context_photos, held_out_scores
    from surfsplat.capture import OptimizeConfig, optimize_on_views
    from surfsplat.capture.starts import StartConfig, choose_start
    from surfsplat.data.cameras import load_cameras
    from surfsplat.data.images import list_images

    folder = sample_data() / "llff_fern"
    photos = list_images(folder / "images_8")[:20]
    # the scene's cameras, working size and held-out views, without the network (a one-step fit from points)
    one = OptimizeConfig(steps=1, densify=None, start=StartConfig(kind="points"))
    options = surfsplat.CaptureOptions(holdout_every=8, optimize=one)
    cameras = load_cameras(folder, images="images_8")
    scene = surfsplat.reconstruct(photos, "tiny-synthetic", cameras=cameras, capture=options, progress=False)
    images = context_photos(scene, photos)
    choice = choose_start(StartConfig(kind="points"), images, scene.cameras)
    h = scene.holdout
    runs = []
    for round_ in range(rounds):
        for adam in ("dense", "selective"):
            config = OptimizeConfig(steps=steps, adam=adam, start=StartConfig(kind="points"))
            fitted, stats = optimize_on_views(
                None, scene.cameras, images, scene.width, scene.height, config, choice=choice
            )
            scores = held_out_scores(fitted, scene, h.cameras, h.images, stats["alpha_threshold"])
            runs.append(
                {"round": round_, "adam": adam, "steps": stats["steps"], "seconds": stats["seconds"],
                 "ms_per_step": 1000 * stats["seconds"] / stats["steps"], "held_out_psnr": scores["mean_psnr"],
                 "surfels": stats["surfels_after"]}
            )  # fmt: skip
            print(runs[-1], flush=True)
    mean = lambda kind, key: statistics.mean(r[key] for r in runs if r["adam"] == kind)  # noqa: E731
    return {
        "size": [scene.height, scene.width],
        "context": scene.names,
        "held_out": h.names,
        "points": len(choice.points.xyz),
        "runs": runs,
        "selective_over_dense_seconds": mean("selective", "seconds") / mean("dense", "seconds"),
        "held_out_psnr_dense": mean("dense", "held_out_psnr"),
        "held_out_psnr_selective": mean("selective", "held_out_psnr"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--parts", nargs="+", default=["step", "fern"], choices=["step", "fern"])
    parser.add_argument("--surfels", type=int, default=50_000)
    parser.add_argument("--visible", nargs="+", type=float, default=[0.1, 0.5, 0.9, 1.0])
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--out", default="selective_adam")
    args = parser.parse_args()
    results = {"machine": machine()}
    if "step" in args.parts:
        results["step"] = step_part(args.surfels, args.visible, args.repeats)
        print(text_table(list(results["step"][0]), [list(r.values()) for r in results["step"]]))
        write_results(args.out, results)
    if "fern" in args.parts:
        results["fern"] = fern_part(args.steps, args.rounds)
        write_results(args.out, results)
    results["machine_after"] = machine()
    print(f"wrote {write_results(args.out, results)}")


if __name__ == "__main__":
    main()
