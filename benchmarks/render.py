"""Renderer benchmark: 131,072 surfels (two 256x256 views of a textured scene) rendered to a nearby view.

For each backend, mode and resolution it measures the forward time, the forward+backward time
(median of repeats after a warm-up) and the peak resident memory of a fresh process, and counts
the contributing (Gaussian, pixel) pairs (alpha >= 1/255). Writes JSON and prints a table.
Each row also carries the process CPU time (all threads) and the 1-minute load average: on a
shared machine wall time alone says little.

    python benchmarks/render.py                       # every backend that runs here, surfel + ewa, 256/512/1024
    python benchmarks/render.py --backends cpu --modes surfel --resolutions 256
    python benchmarks/render.py --multiview 16 --resolutions 64 128 256   # one 16-view call vs 16 calls
    python benchmarks/render.py --backends cpu --modes surfel --resolutions 1024 --passes forward_backward \
        --precisions float32 float64                                         # float32 against float64

`--precisions`: the Gaussians and cameras are given to the renderer in each of these dtypes (the
compiled CPU backend composites in float32 for float32 inputs and in float64 for float64 ones);
the table ends with each configuration's float32 / float64 throughput ratio.

`--multiview V`: the compiled CPU backend's forward+backward of one call rendering V cameras (a
fan of views around the target) against V calls of one camera each, in the same process, at each
resolution and precision: seconds of both and their ratio, and each against V float64 one-camera
calls of today's float64 path. `--baseline REV` also times V one-camera calls of the renderer at
git revision REV (its `src` exported to a temporary folder, run in a subprocess in the same run, on
the same surfels and cameras), and gives every row's ratio against it. Without `--multiview`,
`--baseline REV` runs every configuration on REV's source too, just before this tree's:

    python benchmarks/render.py --multiview 16 --resolutions 128 256 --precisions float32 float64 \
        --baseline a533a7b       # the renderer when fast captures were asked for
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from common import RESULTS, write_results


def _scene():
    from surfsplat.data.synthetic.surfel_scene import make_scene

    return make_scene(resolution=256, views=2, opacity=0.5)


def contributing_pairs(gaussians, cameras, width: int, height: int, mode: str) -> int:
    """(Gaussian, pixel) pairs with alpha >= 1/255, counted with the torch backend's own pipeline."""
    from surfsplat.render import torch_backend as tb

    settings = tb.TorchRenderSettings()
    g = gaussians
    w2c, K, center = cameras.w2c[0], cameras.K[0], cameras.centers[0]
    with torch.no_grad():
        if mode == "surfel":
            proj = tb.project_surfels(
                g.means, g.rotations, g.scales, g.opacities, g.sh, w2c, K, center, width, height, settings
            )
        else:
            proj = tb.project_ewa(
                g.means, g.covariances, g.rotations[:, :, 2], g.opacities, g.sh, w2c, K, center, width, height, settings
            )
        bins = tb.bin_tiles(proj.pixel_box, width, height, settings.tile_size)
        tile = settings.tile_size
        basis = tb._tile_basis(mode, tile, g.means.dtype, g.means.device)
        total = 0
        tiles = bins.count.nonzero().squeeze(1)
        for chunk in tiles.split(256):
            k = int(bins.count[chunk].max())
            slot = torch.arange(k)
            valid = slot[None] < bins.count[chunk][:, None]
            pair = (bins.start[chunk][:, None] + slot[None]).clamp_max(bins.gaussian.shape[0] - 1)
            gi = torch.where(valid, bins.gaussian[pair], 0)
            origin = torch.stack((chunk % bins.tiles_x * tile, chunk // bins.tiles_x * tile), -1).double()
            offset = (origin[:, None] - proj.center[gi]).float()
            log_o = torch.where(valid, torch.log(proj.opacity[gi]), -torch.inf)
            coef, depth_params = tb._pair_coefficients(mode, proj.geometry.float()[gi], offset)
            ones = torch.ones(chunk.shape[0], tile * tile)
            st = tb._block_state(coef, depth_params, log_o, ones, torch.zeros_like(ones, dtype=torch.bool), basis)
            # Only pixels inside the image count.
            px = (origin[:, None, 0] + basis[1][None]).long()
            py = (origin[:, None, 1] + basis[2][None]).long()
            inside = (px < width) & (py < height)
            total += int(((st["alpha"] > 0) & inside[:, None, :]).sum())
    return total


def available_backends() -> list[str]:
    """torch always; the compiled CPU backend when it loads; gsplat with CUDA."""
    from surfsplat.render import cpu_backend_unavailable, gsplat_available

    names = ["torch"]
    if cpu_backend_unavailable() is None:
        names.append("cpu")
    if torch.cuda.is_available() and gsplat_available(torch.device("cuda")):
        names.append("gsplat")
    return names


DTYPES = {"float32": torch.float32, "float64": torch.float64}


def worker(backend: str, mode: str, res: int, passes: str, repeats: int, precision: str = "float32") -> dict:
    """Measure one configuration in this process (threads are set by the caller)."""
    from surfsplat import Gaussians
    from surfsplat.evaluation import peak_rss_bytes
    from surfsplat.render import render

    scene = _scene()
    g = scene.gaussians.to(DTYPES[precision])
    cam = scene.target.to(DTYPES[precision]).scaled(res / 256)
    base_rss = peak_rss_bytes() / 2**20
    threads = torch.get_num_threads()

    def run_once() -> tuple[float, float]:
        if passes == "forward":
            t, c = time.perf_counter(), time.process_time()
            with torch.no_grad():
                render(g, cam, res, res, mode=mode, backend=backend)
            return time.perf_counter() - t, time.process_time() - c
        params = {
            k: getattr(g, k).detach().clone().requires_grad_(True)
            for k in ("means", "quats", "scales", "opacities", "sh")
        }
        gaussians = Gaussians(**params)  # input validation is not renderer work: outside the timer
        t, c = time.perf_counter(), time.process_time()
        out = render(gaussians, cam, res, res, mode=mode, backend=backend)
        (out.color.sum() + out.depth.sum() + out.normal.sum()).backward()
        return time.perf_counter() - t, time.process_time() - c

    warm = run_once()[0]  # includes compiling (or loading the compiled cache of) the cpu kernels
    runs = [run_once() for _ in range(repeats)]
    times = [r[0] for r in runs]
    peak_rss = peak_rss_bytes() / 2**20  # this process's own peak (ru_maxrss would include the parent's)
    return {
        "backend": backend,
        "mode": mode,
        "resolution": res,
        "passes": passes,
        "precision": precision,
        "seconds": statistics.median(times),
        "seconds_all": times,
        "warmup_seconds": warm,
        "cpu_seconds": statistics.median(r[1] for r in runs),
        "load_average": os.getloadavg()[0],
        "peak_rss_mb": peak_rss,
        "scene_rss_mb": base_rss,
        "threads": threads,
    }


def camera_fan(cameras, views: int):
    """`views` cameras around the first of `cameras`: shifted sideways and up by up to 5 cm."""
    from surfsplat import Cameras

    c2w = cameras.c2w[:1].repeat(views, 1, 1)
    angle = torch.linspace(0, 2 * torch.pi, views + 1, dtype=c2w.dtype)[:-1]
    c2w[:, :3, 3] += 0.05 * torch.stack((angle.cos(), angle.sin(), torch.zeros_like(angle)), -1) @ c2w[0, :3, :3].T
    return Cameras(c2w, cameras.K[:1].repeat(views, 1, 1))


def _render_and_backward(render, gaussians, cams, res: int) -> None:
    """Forward+backward of a sum of colour, depth and normal (the multiview workload's loss)."""
    out = render(gaussians, cams, res, res, backend="cpu")
    (out.color.sum() + out.depth.sum() + out.normal.sum()).backward()


def _median_seconds(fn, params: dict, repeats: int) -> float:
    """Median wall seconds of `fn` over `repeats` calls after one warm-up, gradients cleared before each."""
    fn()
    times = []
    for _ in range(repeats):
        for p in params.values():
            p.grad = None
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def multiview_worker(views: int, res: int, repeats: int, precision: str = "float64") -> dict:
    """One V-camera forward+backward call against V one-camera calls (compiled CPU backend)."""
    from surfsplat import Gaussians
    from surfsplat.render import render

    scene = _scene()
    g = scene.gaussians.to(DTYPES[precision])
    cams = camera_fan(scene.target.to(DTYPES[precision]).scaled(res / 256), views)
    params = {
        k: getattr(g, k).detach().clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "sh")
    }
    gaussians = Gaussians(**params)

    def together() -> None:
        _render_and_backward(render, gaussians, cams, res)

    def one_by_one() -> None:
        for c in range(views):
            _render_and_backward(render, gaussians, cams[c : c + 1], res)

    timings = {
        name: _median_seconds(fn, params, repeats)
        for name, fn in (("one_call", together), ("separate_calls", one_by_one))
    }
    return {
        "views": views,
        "resolution": res,
        "precision": precision,
        "seconds_one_call": timings["one_call"],
        "seconds_separate_calls": timings["separate_calls"],
        "speedup": timings["separate_calls"] / timings["one_call"],
        "threads": torch.get_num_threads(),
        "load_average": os.getloadavg()[0],
    }


def baseline_case(views: int, res: int, path: Path) -> None:
    """The multiview workload's float64 surfels and cameras as plain tensors, for another revision."""
    scene = _scene()
    g = scene.gaussians.to(torch.float64)
    cams = camera_fan(scene.target.to(torch.float64).scaled(res / 256), views)
    fields = {k: getattr(g, k) for k in ("means", "quats", "scales", "opacities", "sh")}
    torch.save({**fields, "c2w": cams.c2w, "K": cams.K, "res": res, "views": views}, path)


def baseline_worker(path: Path, repeats: int) -> dict:
    """V one-camera float64 forward+backward calls of whatever `surfsplat` this process imports
    (only its top-level Gaussians, Cameras and render.render, which every revision has)."""
    import surfsplat
    from surfsplat.render import render

    case = torch.load(path)
    params = {k: case[k].clone().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "sh")}
    gaussians = surfsplat.Gaussians(**params)
    cams = surfsplat.Cameras(case["c2w"], case["K"])
    res = case["res"]

    def one_by_one() -> None:
        for c in range(case["views"]):
            _render_and_backward(render, gaussians, cams[c : c + 1], res)

    # the warm-up call also compiles the revision's kernels
    return {"seconds_separate_calls": _median_seconds(one_by_one, params, repeats), "source": surfsplat.__file__}


def export_source(revision: str, folder: Path) -> Path:
    """The `src` of git revision `revision`, exported into `folder` unless already there."""
    src = folder / "src"
    if not src.is_dir():
        root = Path(__file__).resolve().parents[1]
        archive = subprocess.run(
            ["git", "-C", str(root), "archive", "--format=tar", revision, "src"], capture_output=True, check=True
        )
        subprocess.run(["tar", "-x", "-C", str(folder)], input=archive.stdout, check=True)
    return src


def run_baseline(revision: str, views: int, res: int, repeats: int, threads: int, folder: Path) -> dict:
    """`baseline_worker` on the revision's source tree (exported once into `folder`)."""
    src = export_source(revision, folder)
    case = folder / f"case_{views}_{res}.pt"
    baseline_case(views, res, case)
    env = {**os.environ, "PYTHONPATH": str(src)}
    cmd = [sys.executable, __file__, "--baseline-worker", str(case), "--repeats", str(repeats)]
    cmd += ["--threads", str(threads)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"baseline {revision}: {proc.stderr.strip().splitlines()[-1]}")
    row = json.loads(proc.stdout.strip().splitlines()[-1])
    if not row["source"].startswith(str(src)):
        raise RuntimeError(f"baseline {revision}: imported {row['source']}, not the exported revision")
    return {"revision": revision, "views": views, "resolution": res, "precision": "float64", **row}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backends", nargs="+", default=None, help="default: every backend that runs here")
    parser.add_argument("--modes", nargs="+", default=["surfel", "ewa"])
    parser.add_argument("--resolutions", nargs="+", type=int, default=[256, 512, 1024])
    parser.add_argument("--passes", nargs="+", default=["forward", "forward_backward"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULTS / "render.json")
    parser.add_argument("--precisions", nargs="+", default=["float32"], choices=sorted(DTYPES))
    parser.add_argument(
        "--worker", nargs=5, metavar=("BACKEND", "MODE", "RES", "PASSES", "PRECISION"), help=argparse.SUPPRESS
    )
    parser.add_argument("--multiview", type=int, default=None, metavar="V", help="one V-camera call vs V calls")
    parser.add_argument(
        "--baseline", default=None, metavar="REV", help="also revision REV, side by side (--multiview: V calls of it)"
    )
    parser.add_argument("--baseline-worker", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()

    if args.baseline_worker:
        from surfsplat.train.loop import cpu_threads

        with cpu_threads(args.threads):
            print(json.dumps(baseline_worker(args.baseline_worker, args.repeats)))
        return

    if args.multiview:
        import tempfile

        from surfsplat.train.loop import cpu_threads

        rows, baselines = [], []
        folder = Path(tempfile.mkdtemp(prefix="surfsplat_baseline_"))
        with cpu_threads(args.threads):
            for res in args.resolutions:
                if args.baseline:
                    baselines.append(
                        run_baseline(args.baseline, args.multiview, res, args.repeats, args.threads, folder)
                    )
                    print(
                        f"{args.multiview} float64 calls of {args.baseline} at {res}^2: "
                        f"{baselines[-1]['seconds_separate_calls']:.3f} s",
                        flush=True,
                    )
                # float64 first: its separate calls are the baseline of every precision's row.
                for precision in sorted(args.precisions, key=lambda p: p != "float64"):
                    rows.append(multiview_worker(args.multiview, res, args.repeats, precision))
                    r = rows[-1]
                    baseline = next((b for b in rows if b["resolution"] == res and b["precision"] == "float64"), None)
                    if baseline is not None:
                        r["speedup_vs_float64_separate_calls"] = (
                            baseline["seconds_separate_calls"] / r["seconds_one_call"]
                        )
                    versus = (
                        f", x{r['speedup_vs_float64_separate_calls']:.2f} vs {r['views']} float64 calls"
                        if baseline is not None
                        else ""
                    )
                    if args.baseline:
                        then = baselines[-1]["seconds_separate_calls"]
                        r["speedup_vs_baseline_separate_calls"] = then / r["seconds_one_call"]
                        versus += f", x{r['speedup_vs_baseline_separate_calls']:.2f} vs {args.baseline}'s"
                    print(
                        f"{r['views']} views at {res}^2 {precision}: one call {r['seconds_one_call']:.3f} s, "
                        f"{r['views']} calls {r['seconds_separate_calls']:.3f} s, x{r['speedup']:.2f}{versus}",
                        flush=True,
                    )
        out = args.out.with_name("render_multiview.json")
        document = {"date": time.strftime("%Y-%m-%d %H:%M:%S"), "results": rows, "baseline": baselines}
        write_results(out, document)
        print(f"wrote {out}")
        return

    if args.worker:
        from surfsplat.train.loop import cpu_threads

        backend, mode, res, passes, precision = args.worker
        with cpu_threads(args.threads):  # torch's and the compiled renderer's
            print(json.dumps(worker(backend, mode, int(res), passes, args.repeats, precision)))
        return

    torch.set_num_threads(args.threads)
    args.backends = args.backends or available_backends()
    baseline_src = None
    if args.baseline:
        import tempfile

        folder = Path(tempfile.gettempdir()) / f"surfsplat_baseline_{args.baseline}"
        folder.mkdir(exist_ok=True)
        baseline_src = export_source(args.baseline, folder)
    scene = _scene()
    rows = []
    for mode in args.modes:
        for res in args.resolutions:
            pairs = contributing_pairs(scene.gaussians, scene.target.scaled(res / 256), res, res, mode)
            configurations = [(b, p, d) for b in args.backends for p in args.passes for d in args.precisions]
            # With --baseline, each configuration also runs on the revision's source, right before this one's.
            sources = [(args.baseline, baseline_src)] if baseline_src is not None else []
            sources.append((None, None))
            for (backend, passes, precision), (revision, src) in ((c, s) for c in configurations for s in sources):
                # A fresh process per measurement, so peak memory belongs to this configuration.
                cmd = [
                    sys.executable,
                    __file__,
                    "--worker",
                    backend,
                    mode,
                    str(res),
                    passes,
                    precision,
                    "--repeats",
                    str(args.repeats),
                    "--threads",
                    str(args.threads),
                ]
                env = {**os.environ, "PYTHONPATH": str(src)} if src is not None else None
                proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
                if proc.returncode != 0:
                    row = {
                        "backend": backend,
                        "mode": mode,
                        "resolution": res,
                        "passes": passes,
                        "precision": precision,
                        "error": proc.stderr.strip().splitlines()[-1]
                        if proc.stderr.strip()
                        else f"exit {proc.returncode}",
                    }
                else:
                    row = json.loads(proc.stdout.strip().splitlines()[-1])
                    row["pairs_per_second"] = pairs / row["seconds"]
                row["contributing_pairs"] = pairs
                if revision is not None:
                    row["revision"] = revision
                rows.append(row)
                print(_format_row(row), flush=True)

    ratios = _precision_ratios(rows)
    for r in ratios:
        print(
            f"{r['backend']:>7} {r['mode']:>6} {r['resolution']:>5}^2 {r['passes']:>16}  "
            f"float32 / float64 throughput x{r['float32_over_float64']:.2f}"
        )

    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "scene": "surfsplat.data.synthetic.surfel_scene.make_scene(256, views=2, opacity=0.5): 131,072 surfels, target view scaled",
        "machine": {
            "cpus": torch.get_num_threads(),
            "platform": platform.platform(),
            "torch": torch.__version__,
            "processor": platform.processor(),
        },
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }
    args.out.write_text(json.dumps({"meta": meta, "results": rows, "precision_ratios": ratios}, indent=2))
    print(f"\nwrote {args.out}")


def _precision_ratios(rows: list[dict]) -> list[dict]:
    """Per configuration measured in both precisions, float32 pairs per second over float64's."""
    timed = {
        (r["backend"], r["mode"], r["resolution"], r["passes"], r["precision"]): r["seconds"]
        for r in rows
        if "error" not in r and "revision" not in r
    }
    return [
        {
            "backend": b,
            "mode": m,
            "resolution": res,
            "passes": p,
            "float32_over_float64": timed[(b, m, res, p, "float64")] / seconds,
        }
        for (b, m, res, p, precision), seconds in timed.items()
        if precision == "float32" and (b, m, res, p, "float64") in timed
    ]


def _format_row(r: dict) -> str:
    head = f"{r.get('revision', 'this'):>8} {r['backend']:>7} {r['mode']:>6} {r['resolution']:>5}^2 {r['passes']:>16} {r['precision']:>7}"
    if "error" in r:
        return f"{head}  ERROR {r['error']}"
    return (
        f"{head}  {r['seconds']:8.3f} s  (cpu {r['cpu_seconds']:7.3f} s, load {r['load_average']:4.1f})  "
        f"peak {r['peak_rss_mb']:7.0f} MB  "
        f"pairs {r['contributing_pairs'] / 1e6:6.2f} M  {r['pairs_per_second'] / 1e6:6.2f} M pairs/s"
    )


if __name__ == "__main__":
    main()
