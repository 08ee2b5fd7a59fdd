"""Per-scene optimizer benchmark: held-out PSNR against CPU seconds, by start, beside OpenSplat's point.

    python benchmarks/optimize.py                                   # fern, dtu, rooms; every start
    python benchmarks/optimize.py --parts fern --starts points      # one capture, one start
    python benchmarks/optimize.py --config '{"steps": 1000}'        # other OptimizeConfig fields
    python benchmarks/optimize.py --parts fern-cli                  # the whole `surfsplat reconstruct` process
    python benchmarks/optimize.py --parts fern --starts points --strategies 3dgs absgs mcmc   # by strategy

Parts (each writes its entry of benchmarks/results/optimize.json as soon as it is measured, prints a
table, and `--plot` draws every curve into one PNG):
- fern: LLFF fern, cameras from poses_bounds.npy, 17 context views (IMG_4026, IMG_4034, IMG_4042 held
  out: `holdout_every=8`) at the working size `reconstruct` picks (368x496). One `reconstruct` with
  the optimization off gives the network's fused surfels and the held-out views; the refinement (the
  `--optimize-steps 0` default) is scored, then each start (`--starts`) is optimized with the
  configuration given, its held-out PSNR recorded every tenth of the fit against the CPU seconds of
  the process so far (the network, fusion and the start's triangulation included, the scoring not).
  OpenSplat's held-out renders (`../shared/anchors/opensplat_fern`, where present) are scored on the
  same crop of the same photos, and its CPU seconds are its own record's. Each start runs once per
  densification strategy (`--strategies`, `OptimizeConfig.strategy`: 3dgs, absgs, mcmc), each row
  naming both; the plot draws NeRF's published 25.17 dB on fern (Mildenhall et al. 2020).
- dtu: DTU scan 24, views 12..26 at 400x300 with `holdout_every=3` (12, 15, 18, 21, 24 held out, 10
  fitted); the same rows.
- rooms: procedural rooms (`surfsplat.data.synthetic`), 25 frames at 64x64 with exact cameras, every
  4th held out: held-out PSNR, depth AbsRel and median normal error against the exact truth, for the
  network's fusion and each start.
- fern-cli / dtu-cli: the issue's end-to-end measure, `surfsplat reconstruct ... --formats ply
  --raw-3dgs` with the shipped defaults, as a child process: its CPU seconds (user + system, from the
  operating system) and the held-out PSNR its reconstruction.json reports.
The CPU model is recorded: the same fit costs 1.6x more CPU seconds on an AVX2-only EPYC than on an
AVX-512 Xeon (OpenSplat's record), so compare seconds on one model only.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import resource
import tempfile
from pathlib import Path

import torch

from common import ROOT, machine, reconstruct_cli, sample_data, text_table, write_results

STARTS = ("points", "network", "both", "auto")
STRATEGIES = ("3dgs", "absgs", "mcmc")
NERF_FERN_PSNR = 25.17  # NeRF's published held-out PSNR on fern (Mildenhall et al. 2020, per-scene table)
ANCHORS = ROOT.parent / "shared" / "anchors" / "opensplat_fern"


def cpu_model() -> str:
    """The processor's model name and whether it has AVX-512 (the figures depend on both)."""
    try:
        info = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor() or platform.machine()
    name = next((line.split(":", 1)[1].strip() for line in info.splitlines() if line.startswith("model name")), "")
    flags = next((line for line in info.splitlines() if line.startswith("flags")), "")
    return f"{name} ({'AVX-512' if 'avx512f' in flags else 'AVX2 only' if 'avx2' in flags else 'no AVX2'})"


def cpu_seconds() -> float:
    """User + system CPU seconds of this process so far (both cores count)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


_SCENE = object()  # held_out_scores: render with the scene's own forced-alpha threshold


def held_out_scores(surfels, scene, cameras, images, alpha_threshold=_SCENE, antialiased=False, zoom=False) -> dict:
    """PSNR / SSIM (and LPIPS where its weights are) of surfels seen from held-out cameras, as `reconstruct`
    scores them, rendered with the scene's forced-alpha threshold or `alpha_threshold` (and the antialiasing
    filter when `antialiased`); with `zoom` also the zoom scores (`surfsplat.metrics.zoom`: x1/2, x1/4 against
    the photos and the x1 render averaged down, x2, x4 against bicubic-upsampled photos, coverage)."""
    from surfsplat.reconstruction.scene import HeldOut

    h = HeldOut(["held"] * len(cameras), cameras, images)
    threshold = scene.alpha_threshold if alpha_threshold is _SCENE else alpha_threshold
    seen = dataclasses.replace(
        scene, gaussians=surfels, holdout=None, alpha_threshold=threshold, antialiased=antialiased
    )
    h.score(seen.render(cameras))
    s = h.scores()
    out = {k: s[k] for k in ("mean_psnr", "mean_ssim", "mean_lpips", "psnr")}
    if zoom:
        out["zoom"] = seen.zoom_scores(cameras, images).to_dict()
    return out


def real_capture(args, name: str, folder: Path, images: str, indices: list[int], every: int) -> dict:
    """The network's fused scene, the refinement, and each start optimized, with held-out curves."""
    import surfsplat
    from surfsplat.capture import OptimizeConfig, RefineConfig, optimize_on_views, refine_on_views
    from surfsplat.capture.densify import DensifyConfig
    from surfsplat.capture.mcmc import MCMCConfig
    from surfsplat.capture.starts import StartConfig
    from surfsplat.data.cameras import load_cameras
    from surfsplat.data.images import list_images

    photos = [list_images(folder / images)[i] for i in indices]
    cameras = load_cameras(folder, images=images)
    # the network's pass alone: the refinement and each optimization run below, timed apart
    options = surfsplat.CaptureOptions(
        holdout_every=every, refine=RefineConfig(steps=0), optimize=OptimizeConfig(steps=0)
    )
    cpu0 = cpu_seconds()
    fused = surfsplat.reconstruct(photos, "tiny-synthetic", cameras=cameras, capture=options, progress=False)
    network_cpu = cpu_seconds() - cpu0
    h = fused.holdout
    context_images = context_photos(fused, photos)
    result = {
        "context": fused.names,
        "held_out": h.names,
        "size": [fused.height, fused.width],
        "network_surfels": len(fused.gaussians),
        "network_and_fusion_cpu_seconds": network_cpu,
        "stages": fused.seconds,
        "rows": [],
    }
    args.results[args.key] = result

    def add(row: dict) -> None:
        result["rows"].append(row)
        print(f"{name} {json.dumps({k: v for k, v in row.items() if k != 'curve'})}", flush=True)
        args.save()

    add(
        {
            "what": "network (fusion)",
            "cpu_seconds": network_cpu,
            **held_out_scores(fused.gaussians, fused, h.cameras, h.images),
        }
    )
    if args.refinement:  # the --optimize-steps 0 default: on 531k fern surfels it costs minutes
        tick = cpu_seconds()
        refined, _ = refine_on_views(
            fused.gaussians, fused.cameras, context_images, fused.width, fused.height, RefineConfig(),
            mode=fused.mode, alpha_threshold=fused.alpha_threshold,
        )  # fmt: skip
        add(
            {
                "what": "refinement (--optimize-steps 0)",
                "cpu_seconds": network_cpu + cpu_seconds() - tick,
                **held_out_scores(refined, fused, h.cameras, h.images),
            }
        )
    if name == "fern" and ANCHORS.is_dir():
        add(opensplat_row(fused, h))
    for start, strategy in ((a, b) for a in args.starts for b in args.strategies):
        fields = {k: tuple(v) if isinstance(v, list) else v for k, v in args.config.items()}
        fields["start"] = StartConfig(kind=start, **args.start)
        fields["strategy"] = strategy
        for key, kind in (("densify", DensifyConfig), ("mcmc", MCMCConfig)):  # their fields as JSON objects
            if isinstance(fields.get(key), dict):
                fields[key] = kind(**fields[key])
        config = OptimizeConfig(**fields)
        curve = Curve(f"{name}/{start}/{strategy}", fused, network_cpu, config.antialiased)
        fitted, stats = optimize_on_views(
            fused.gaussians, fused.cameras, context_images, fused.width, fused.height, config,
            mode=fused.mode, alpha_threshold=fused.alpha_threshold, monitor=curve,
        )  # fmt: skip
        add(
            {
                "what": f"optimize from {start}, {strategy}",
                "start": start,
                "strategy": strategy,
                "config": args.config,
                "steps": stats["steps"],
                "cpu_seconds": curve.points[-1]["cpu_seconds"],
                "fit_wall_seconds": stats["seconds"],
                "start_surfels": stats["start_surfels"],
                "points": stats.get("points"),
                "surfels_after": stats["surfels_after"],
                "antialiased": stats["antialiased"],
                **held_out_scores(
                    fitted, fused, h.cameras, h.images, stats["alpha_threshold"], stats["antialiased"], zoom=True
                ),
                "start_reason": stats.get("start_reason"),
                "reached_opensplat_at_cpu_seconds": first_reaching(curve.points, result),
                "curve": curve.points,
            }
        )
    return result


class Curve:
    """A fit's monitor: held-out PSNR against the CPU seconds of the process so far (network and fusion
    included, the scoring left out)."""

    def __init__(self, label: str, fused, network_cpu: float, antialiased: bool = False) -> None:
        self.label, self.fused, self.network_cpu, self.antialiased = label, fused, network_cpu, antialiased
        self.points: list[dict] = []
        self.fit_cpu = cpu_seconds()  # made just before the fit starts
        self.scoring = 0.0

    def __call__(self, step: int, seconds: float, surfels, alpha_threshold: float | None) -> None:
        now = cpu_seconds()
        h = self.fused.holdout
        scores = held_out_scores(surfels, self.fused, h.cameras, h.images, alpha_threshold, self.antialiased)
        self.points.append(
            {
                "step": step,
                "wall_seconds": seconds,
                "cpu_seconds": self.network_cpu + now - self.fit_cpu - self.scoring,
                "surfels": len(surfels),
                "psnr": scores["mean_psnr"],
            }
        )
        self.scoring += cpu_seconds() - now
        print(f"  {self.label}: {json.dumps(self.points[-1])}", flush=True)


def first_reaching(curve: list[dict], result: dict) -> float | None:
    """CPU seconds at which the curve first reaches OpenSplat's held-out PSNR (None: never, or no anchor)."""
    anchor = next((r for r in result["rows"] if r["what"].startswith("OpenSplat")), None)
    if anchor is None:
        return None
    return next((p["cpu_seconds"] for p in curve if p["psnr"] >= anchor["mean_psnr"]), None)


def opensplat_row(fused, h) -> dict:
    """OpenSplat 1.1.5's held-out renders scored on the crop the scene's held-out photos went through."""
    from surfsplat.data.images import read_image
    from surfsplat.data.transforms import rescale_and_crop
    from surfsplat.metrics import psnr

    record = json.loads((ANCHORS / "result.json").read_text())
    renders = torch.stack([read_image(ANCHORS / f"{n.rsplit('.', 1)[0]}.png")[0] for n in h.names]).float()
    cropped, _, _ = rescale_and_crop(renders, torch.eye(3).expand(len(renders), 3, 3), (fused.height, fused.width))
    values = psnr(cropped.clamp(0, 1), h.images.cpu()).tolist()
    return {
        "what": "OpenSplat 1.1.5 (2,000 steps, its record)",
        "cpu_seconds": record["cpu_s"],
        "mean_psnr": sum(values) / len(values),
        "psnr": values,
        "surfels_after": record["num_gaussians"],
        "cpu": "AVX-512 Xeon of this machine kind (3,221 CPU s on an AVX2-only EPYC)",
    }


def context_photos(fused, photos) -> torch.Tensor:
    """The context photos at the scene's working size, as `reconstruct` gave them to the network."""
    from surfsplat.data.images import read_image
    from surfsplat.data.transforms import rescale_and_crop

    by_name = {p.name: p for p in photos}
    stack = torch.stack([read_image(by_name[n], background=(0.0, 0.0, 0.0))[0] for n in fused.names])
    out, _, _ = rescale_and_crop(stack, torch.eye(3).expand(len(stack), 3, 3), (fused.height, fused.width))
    return out.clamp(0, 1)


def rooms(args) -> dict:
    """Held-out PSNR, depth AbsRel and median normal error on the procedural rooms, by start."""
    import capture as capture_benchmark  # the rooms' straight paths
    import surfsplat
    from surfsplat.capture import OptimizeConfig, RefineConfig, frame_name, optimize_on_views
    from surfsplat.capture.starts import StartConfig
    from surfsplat.data.cameras import CameraSet
    from surfsplat.data.synthetic import make_scene, render_synthetic
    from surfsplat.metrics import angular_error_deg, psnr
    from surfsplat.render import render

    size, n = 64, 25
    held = torch.tensor([i for i in range(n) if i % 4 == 0])
    ctx = torch.tensor([i for i in range(n) if i % 4])

    def scores(g, fused, cams, truth, alpha_threshold) -> dict:
        out = render(g, cams, size, size, mode=fused.mode, alpha_threshold=alpha_threshold)
        covered = (out.alpha >= 0.5) & (truth.depth > 0)
        absrel = ((out.depth - truth.depth).abs() / truth.depth.clamp_min(1e-6))[covered].mean()
        angles = angular_error_deg(out.normal.permute(0, 2, 3, 1), truth.normal.permute(0, 2, 3, 1))[covered[:, 0]]
        return {
            "psnr": float(psnr(out.color.clamp(0, 1), truth.image).mean()),
            "depth_absrel": float(absrel),
            "normal_median_deg": float(angles.median()),
        }

    per_row: dict[str, list] = {}
    for seed in range(args.rooms):
        room = make_scene(1000 + seed)
        path = capture_benchmark.long_path(room, torch.Generator().manual_seed(seed), 1.0)
        cams = path.cameras(torch.linspace(0, 1, n), size, size)
        truth = render_synthetic(room, cams, size, size)
        every = CameraSet(cams, size, size, [frame_name(i) for i in range(n)], 0.5, 15.0)
        options = surfsplat.CaptureOptions(
            holdout_every=4, refine=RefineConfig(steps=0), optimize=OptimizeConfig(steps=0)
        )
        fused = surfsplat.reconstruct(
            list(truth.image), "tiny-synthetic", cameras=every, capture=options, progress=False
        )
        held_truth = type(truth)(**{f.name: getattr(truth, f.name)[held] for f in dataclasses.fields(truth)})
        per_row.setdefault("network (fusion)", []).append(
            {"seconds": 0.0, **scores(fused.gaussians, fused, cams[held], held_truth, fused.alpha_threshold)}
        )
        for start in args.starts:
            fields = {k: tuple(v) if isinstance(v, list) else v for k, v in args.room_config.items()}
            config = OptimizeConfig(**fields, start=StartConfig(kind=start, **args.start))
            try:
                fitted, stats = optimize_on_views(
                    fused.gaussians, fused.cameras, truth.image[ctx], size, size, config, mode=fused.mode,
                    alpha_threshold=fused.alpha_threshold,
                )  # fmt: skip
            except surfsplat.SurfSplatInputError as error:  # 64x64 renders of flat colours: too few SIFT points
                print(f"room {1000 + seed}, start {start}: {error}", flush=True)
                per_row.setdefault(f"optimize from {start}", []).append({"failed": str(error)})
                continue
            per_row.setdefault(f"optimize from {start}", []).append(
                {"seconds": stats["seconds"], **scores(fitted, fused, cams[held], held_truth, stats["alpha_threshold"])}
            )
        print(f"room {1000 + seed} measured", flush=True)
    rows = []
    for what, runs in per_row.items():
        ok = [r for r in runs if "failed" not in r]
        row = {"what": what, "rooms": len(ok), "failed": len(runs) - len(ok)}
        if ok:
            row.update({k: sum(r[k] for r in ok) / len(ok) for k in ok[0]})
        rows.append(row)
        print(f"rooms {json.dumps(row)}", flush=True)
    return {
        "rooms": args.rooms,
        "size": [size, size],
        "frames": n,
        "held_out_every": 4,
        "config": args.room_config,
        "rows": rows,
    }


def cli_run(args, name: str, folder: Path, images_folder: str, holdout_every: int, views: list[int] | None) -> dict:
    """`surfsplat reconstruct` with the shipped defaults as a child process: CPU seconds and held-out PSNR."""
    from surfsplat.data.images import list_images

    with tempfile.TemporaryDirectory() as tmp:
        images = [str(p) for p in list_images(folder / images_folder)]
        if views is not None:
            images = [images[i] for i in views]
        out = Path(args.keep) / name if args.keep else Path(tmp) / "out"
        flags = ["--images-folder", images_folder, "--holdout-every", str(holdout_every), "--formats", "ply"]
        return reconstruct_cli(images, folder, out, [*flags, "--raw-3dgs", *args.cli_args])


def plot(results: dict, path: Path) -> None:
    """Every capture's held-out PSNR against CPU seconds, one panel a capture, OpenSplat's point marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [k for k in ("fern", "dtu_scan24") if k in results]
    if not keys:
        return
    figure, axes = plt.subplots(1, len(keys), figsize=(6.5 * len(keys), 4.5), squeeze=False)
    # one colour a start, one line style a strategy, and single points in colours no curve uses (so no
    # two entries look alike)
    curve_colours = {"points": "tab:blue", "network": "tab:orange", "both": "tab:green", "auto": "tab:purple"}
    strategy_styles = {"3dgs": ("-", "."), "absgs": ("--", "^"), "mcmc": (":", "s")}
    point_styles = {"OpenSplat": ("*", "tab:red"), "network": ("o", "tab:gray"), "refinement": ("s", "tab:brown")}
    for ax, key in zip(axes[0], keys):
        for row in results[key]["rows"]:
            if "curve" in row:
                xs = [p["cpu_seconds"] for p in row["curve"]]
                ys = [p["psnr"] for p in row["curve"]]
                line, marker = strategy_styles.get(row.get("strategy", "3dgs"), ("-", "."))
                ax.plot(
                    xs, ys, linestyle=line, marker=marker, markersize=4, color=curve_colours.get(row.get("start")),
                    label=row["what"],
                )  # fmt: skip
            else:
                marker, colour = next(
                    (style for name, style in point_styles.items() if row["what"].startswith(name)), ("o", "black")
                )
                ax.scatter(
                    [row["cpu_seconds"]],
                    [row["mean_psnr"]],
                    marker=marker,
                    s=90,
                    color=colour,
                    label=row["what"],
                    zorder=3,
                )
        for cli in ("fern-cli", "dtu-cli"):
            entry = results.get(cli)
            if entry and key.startswith(cli.split("-")[0]) and entry.get("held_out_psnr") is not None:
                ax.scatter(
                    [entry["cpu_seconds"]],
                    [entry["held_out_psnr"]],
                    marker="D",
                    s=70,
                    color="black",
                    label="surfsplat reconstruct (whole process)",
                    zorder=4,
                )
        if key == "fern":
            ax.axhline(NERF_FERN_PSNR, color="tab:red", linestyle="-.", linewidth=1, label="NeRF (published), 25.17 dB")
        ax.set_title(f"{key}: held-out PSNR ({results[key]['size'][1]}x{results[key]['size'][0]})")
        ax.set_xlabel(f"CPU seconds, {results['machine']['cpu_model']}")
        ax.set_ylabel("held-out PSNR (dB)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)
    print(f"plot: {path}")


def print_table(results: dict) -> None:
    print(f"\nCPU: {results['machine']['cpu_model']}")
    for key in ("fern", "dtu_scan24"):
        if key not in results:
            continue
        r = results[key]
        print(
            f"\n{key}: {len(r['context'])} context views at {r['size'][1]}x{r['size'][0]}, held out {r['held_out']}; "
            f"network and fusion {r['network_and_fusion_cpu_seconds']:.1f} CPU s"
        )
        rows = [
            [row["what"], row.get("steps"), row["cpu_seconds"], row["mean_psnr"], row.get("mean_ssim"), row.get("surfels_after"), row.get("reached_opensplat_at_cpu_seconds")]
            for row in r["rows"]
        ]  # fmt: skip
        print(text_table(["what", "steps", "CPU s", "PSNR", "SSIM", "surfels", "OpenSplat's PSNR at CPU s"], rows))
    for cli in ("fern-cli", "dtu-cli"):
        if cli in results:
            e = results[cli]
            print(
                f"\n{cli}: {e['cpu_seconds']:.1f} CPU s ({e['wall_seconds']:.1f} s wall), held-out PSNR {e['held_out_psnr_before']} -> {e['held_out_psnr']}"
            )
    if "rooms" in results:
        rows = [
            [
                r["what"],
                r.get("rooms"),
                r.get("failed"),
                r.get("psnr"),
                r.get("depth_absrel"),
                r.get("normal_median_deg"),
            ]
            for r in results["rooms"]["rows"]
        ]
        print(f"\nrooms ({results['rooms']['rooms']}), held-out views")
        print(text_table(["what", "rooms", "failed", "PSNR", "depth AbsRel", "normal median (deg)"], rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parts = ["fern", "dtu", "rooms", "fern-cli", "dtu-cli"]
    parser.add_argument("--parts", nargs="+", default=["fern", "dtu", "rooms"], choices=parts)
    parser.add_argument("--starts", nargs="+", default=list(STARTS[:3]), choices=STARTS)
    parser.add_argument(
        "--strategies", nargs="+", default=["3dgs"], choices=STRATEGIES, help="densification strategies"
    )
    parser.add_argument(
        "--config", type=json.loads, default={}, help="OptimizeConfig fields (JSON; default: the shipped ones)"
    )
    parser.add_argument("--start", type=json.loads, default={}, help="StartConfig fields besides kind (JSON)")
    parser.add_argument("--room-config", type=json.loads, default={"steps": 300})
    parser.add_argument("--rooms", type=int, default=2)
    parser.add_argument("--no-refinement", dest="refinement", action="store_false", help="skip the refinement row")
    parser.add_argument("--keep", default="", help="keep each -cli run's output folder under this folder")
    parser.add_argument("--cli-args", nargs=argparse.REMAINDER, default=[], help="more reconstruct flags (last)")
    parser.add_argument("--out", default="optimize", help="results file (a name under benchmarks/results or a path)")
    parser.add_argument("--plot", default=str(ROOT / "docs" / "optimize_curve.png"), help="the PNG ('' for none)")
    args = parser.parse_args()
    torch.manual_seed(0)
    data = sample_data()
    args.results = {"machine": {**machine(), "cpu_model": cpu_model()}, "parts": args.parts}

    def save() -> None:
        write_results(args.out, args.results)

    args.save = save
    runs = {
        "fern": lambda: real_capture(args, "fern", data / "llff_fern", "images_8", list(range(20)), 8),
        "dtu": lambda: real_capture(args, "dtu", data / "dtu_scan24", "images_4", list(range(12, 27)), 3),
        "rooms": lambda: rooms(args),
        "fern-cli": lambda: cli_run(args, "fern", data / "llff_fern", "images_8", 8, None),
        "dtu-cli": lambda: cli_run(args, "dtu", data / "dtu_scan24", "images_4", 3, list(range(12, 27))),
    }
    for part in args.parts:  # in the order asked for
        args.key = {"dtu": "dtu_scan24"}.get(part, part)
        args.results[args.key] = runs[part]()
        save()
    print_table(args.results)
    if args.plot:
        plot(args.results, Path(args.plot))


if __name__ == "__main__":
    main()
