"""One fit step on the CPU, broken down: render (compiled backend) + (1 - w) L1 + w D-SSIM + backward + Adam.

The step of `capture/fit.py` at one view: the fitted tensors (means, quaternions, log-scales,
opacity logits, SH) activated, rendered with `render(backend="cpu")` (forced alpha blending on),
the 3DGS loss against a fixed target, backward, one Adam step. Timed phases come from wrapping
the kernels the backend calls (so each is its wall time as the step sees it) plus the loss,
normalisation and Adam; "rest" is whatever the step took beyond them (autograd's own work, the
tensor hand-over, Python).

The scene is synthetic and seeded: N surfels scattered in the frustum of a camera looking down +z,
depths 2-6, random orientations facing roughly the camera, SH degree 3, opacities 0.2-0.9, sizes
set so that about `--overlap` surfels' 3-sigma discs cover each pixel whatever N.

    python benchmarks/fit_step.py                                  # 92x124..368x496, 10k..500k
    python benchmarks/fit_step.py --sizes 368x496 --surfels 100000 --ref HEAD~3   # side by side
    python benchmarks/fit_step.py --sizes 368x496 --surfels 100000 --beside-job   # with a busy neighbour

`--ref REV` runs the same steps with the renderer of git revision REV (its `src` exported once to a
temporary folder) in a second worker process, the two workers taking turns step batch by step batch
so that both see the same machine load; the table then gives both and their ratio. `--beside-job`
also measures every configuration while another process keeps the cores busy (torch matrix
products on as many threads as the step uses), and reports the slowdown.
"""

from __future__ import annotations

import argparse
import contextlib
import inspect
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from common import machine, text_table, write_results

PHASES = (
    "activation",
    "projection",
    "binning",
    "composite_fwd",
    "normalize",
    "loss",
    "composite_bwd",
    "projection_bwd",
    "adam",
    "rest",
)
# Kernel entry points (of this or an older revision) and the phase each belongs to; names a
# revision lacks are skipped.
KERNEL_PHASES = {
    "quats_to_rotations": "projection",
    "project": "projection",
    "depth_order": "binning",
    "gather_rows": "binning",
    "bin_tiles": "binning",
    "composite_forward": "composite_fwd",
    "composite_backward": "composite_bwd",
    "sum_pair_rows": "projection_bwd",
    "project_backward": "projection_bwd",
    "quats_backward": "projection_bwd",
    "normalize_forward": "normalize",
    "normalize_backward": "normalize",
}


def cpu_model() -> str:
    """The CPU's model name and whether it has AVX-512 (the float32 pixel loops' vector width)."""
    name, flags = platform.processor(), ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and name in ("", platform.machine()):
                name = line.split(":", 1)[1].strip()
            if line.startswith("flags"):
                flags = line
    except OSError:
        pass
    return f"{name}{' (AVX-512)' if 'avx512f' in flags else ''}"


def make_scene(n: int, width: int, height: int, overlap: float, seed: int = 0):
    """Seeded surfels in the view's frustum and a camera at the origin looking down +z (float32)."""
    from surfsplat import Cameras, Gaussians

    gen = torch.Generator().manual_seed(seed)
    f = 0.9 * width
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    c2w = torch.eye(4)[None]
    z = 2.0 + 4.0 * torch.rand(n, generator=gen)
    # uniform over the image, a little beyond its border
    px = (torch.rand(n, generator=gen) * 1.1 - 0.05) * width
    py = (torch.rand(n, generator=gen) * 1.1 - 0.05) * height
    means = torch.stack(((px - width / 2) * z / f, (py - height / 2) * z / f, z), -1)
    # tilted at most ~60 degrees away from the camera
    axis = torch.randn(n, 3, generator=gen)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = (torch.rand(n, generator=gen) * 2.1)[:, None] / 2
    quats = torch.cat((angle.cos(), axis * angle.sin()), -1)
    opacities = 0.2 + 0.7 * torch.rand(n, generator=gen)
    # a 3-sigma disc covers pi (3 s f / z)^2 pixels; n of them `overlap` times the image
    sigma_px = (overlap * width * height / (n * torch.pi * 9.0)) ** 0.5
    s = sigma_px * z / f * (0.5 + torch.rand(n, generator=gen))
    scales = torch.stack((s, s * (0.5 + 0.5 * torch.rand(n, generator=gen))), -1)
    sh = 0.3 * torch.randn(n, 3, 16, generator=gen)
    sh[..., 1:] *= 0.2
    target = torch.rand(1, 3, height, width, generator=gen)
    gaussians = Gaussians(means=means, quats=quats, scales=scales, opacities=opacities, sh=sh)
    return gaussians, Cameras(c2w, K[None]), target


class Step:
    """One configuration's fit state (fitted tensors, Adam) and its timed step."""

    def __init__(
        self, n: int, width: int, height: int, overlap: float, ssim_weight: float, torch_threads: int = 0
    ) -> None:
        import surfsplat.render as render_module
        from surfsplat.render.cpu import backend

        self.g0, self.cameras, self.target = make_scene(n, width, height, overlap)
        self.width, self.height, self.ssim_weight = width, height, ssim_weight
        self.torch_threads = torch_threads
        g = self.g0
        self.tensors = {
            "means": g.means.clone(),
            "quats": g.quats.clone(),
            "log_scales": g.scales.log(),
            "logits": torch.logit(g.opacities),
            "sh_dc": g.sh[..., :1].contiguous(),
            "sh_rest": g.sh[..., 1:].contiguous(),
        }
        for t in self.tensors.values():
            t.requires_grad_(True)
        groups = [{"params": [t], "lr": 1e-3} for t in self.tensors.values()]
        try:  # the fit loop's own Adam, where the revision has one
            from surfsplat.capture.fit import adam

            self.optimizer = adam(groups, torch.device("cpu"))
        except ImportError:
            self.optimizer = torch.optim.Adam(groups)
        self.times = dict.fromkeys(PHASES, 0.0)
        self._wrap(backend.kernels, render_module)

    def _timed(self, fn, phase: str):
        def wrapper(*args, **kwargs):
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.times[phase] += time.perf_counter() - start

        return wrapper

    def _wrap(self, kernels, render_module) -> None:
        for name, phase in KERNEL_PHASES.items():
            if hasattr(kernels, name):
                setattr(kernels, name, self._timed(getattr(kernels, name), phase))
        render_module.normalize_by_alpha = self._timed(render_module.normalize_by_alpha, "normalize")

    def run(self) -> dict[str, float]:
        """One step, under the fit loop's thread setting where the revision has one; returns its
        phases' seconds (and "step", the whole)."""
        try:
            from surfsplat.capture.fit import step_threads
        except ImportError:
            return self._run()
        if self.torch_threads:  # an explicit count replaces the fit loop's
            before = torch.get_num_threads()
            torch.set_num_threads(self.torch_threads)
            try:
                return self._run()
            finally:
                torch.set_num_threads(before)
        with step_threads(torch.device("cpu")):
            return self._run()

    @staticmethod
    def _quats(F, quats):
        """As the fit loop hands them to a render: unnormalized where its revision does so (the
        backends normalize), else normalized."""
        try:
            from surfsplat.capture.fit import _Free
        except ImportError:
            return F.normalize(quats, dim=-1)
        return quats if "unit_quats" in inspect.signature(_Free.current).parameters else F.normalize(quats, dim=-1)

    def _run(self) -> dict[str, float]:
        import torch.nn.functional as F

        from surfsplat import Gaussians
        from surfsplat.metrics import ssim
        from surfsplat.render import render

        self.times = dict.fromkeys(PHASES, 0.0)
        start = time.perf_counter()
        t = self.tensors
        g = Gaussians(
            means=t["means"],
            quats=self._quats(F, t["quats"]),
            scales=t["log_scales"].exp(),
            opacities=torch.sigmoid(t["logits"]),
            sh=torch.cat((t["sh_dc"], t["sh_rest"]), -1),
            validate=False,
        )
        self.times["activation"] = time.perf_counter() - start
        out = render(g, self.cameras, self.width, self.height, backend="cpu")
        mark = time.perf_counter()
        loss = (out.color - self.target).abs().mean()
        if self.ssim_weight:
            loss = (1 - self.ssim_weight) * loss + self.ssim_weight * (1 - ssim(out.color, self.target).mean())
        self.times["loss"] = time.perf_counter() - mark
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        mark = time.perf_counter()
        self.optimizer.step()
        self.times["adam"] = time.perf_counter() - mark
        total = time.perf_counter() - start
        self.times["rest"] = total - sum(v for k, v in self.times.items() if k != "rest")
        return {**self.times, "step": total}


def serve(threads: int) -> None:
    """Worker loop: one JSON request a line on stdin ({"n", "width", "height", "overlap", "ssim",
    "steps"}), one JSON answer a line on stdout (the steps' phase seconds)."""
    import surfsplat
    from surfsplat.train.loop import cpu_threads

    try:  # held around all the steps, as the fit loop holds it (its heap setting lasts the whole fit)
        from surfsplat.capture.fit import step_threads

        held = step_threads(torch.device("cpu"))
    except ImportError:
        held = contextlib.nullcontext()
    steps: dict[tuple, Step] = {}
    with cpu_threads(threads), held:
        print(json.dumps({"ready": True, "source": surfsplat.__file__}), flush=True)
        for line in sys.stdin:
            req = json.loads(line)
            key = (req["n"], req["width"], req["height"], req["overlap"], req["ssim"], req.get("torch_threads", 0))
            if key not in steps:
                steps.clear()  # one configuration's buffers at a time
                steps[key] = Step(*key)
                for _ in range(2):  # compile / load the kernels, fault in the buffers
                    steps[key].run()
            runs = [steps[key].run() for _ in range(req["steps"])]
            print(json.dumps({"runs": runs}), flush=True)


class Worker:
    """A `serve` process on some `src` tree."""

    def __init__(self, src: Path, threads: int) -> None:
        env = {**os.environ, "PYTHONPATH": str(src)}
        cmd = [sys.executable, __file__, "--serve", "--threads", str(threads)]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
        hello = json.loads(self._read())
        if not hello["source"].startswith(str(src)):
            raise RuntimeError(f"worker imported {hello['source']}, not {src}")

    def _read(self) -> str:
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"worker exited with {self.proc.wait()}")
        return line

    def steps(self, request: dict) -> list[dict]:
        self.proc.stdin.write(json.dumps(request) + "\n")
        self.proc.stdin.flush()
        return json.loads(self._read())["runs"]

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait()


def export_revision(revision: str) -> Path:
    """The `src` of git revision `revision`, exported once into a temporary folder that persists,
    so numba's on-disk cache of its kernels survives between runs."""
    root = Path(__file__).resolve().parents[1]
    sha = subprocess.run(
        ["git", "-C", str(root), "rev-parse", revision], capture_output=True, text=True, check=True
    ).stdout.strip()
    folder = Path(tempfile.gettempdir()) / f"surfsplat_ref_{sha[:12]}"
    if not (folder / "src").is_dir():
        archive = subprocess.run(["git", "-C", str(root), "archive", "--format=tar", sha, "src"], capture_output=True)
        if archive.returncode != 0:
            raise RuntimeError(archive.stderr.decode().strip())
        folder.mkdir(parents=True, exist_ok=True)
        subprocess.run(["tar", "-x", "-C", str(folder)], input=archive.stdout, check=True)
    return folder / "src"


def busy_job(threads: int) -> subprocess.Popen:
    """Another CPU-bound process: torch matrix products on `threads` threads until killed."""
    code = (
        "import torch\n"
        f"torch.set_num_threads({threads})\n"
        "a = torch.randn(512, 512)\n"
        "while True:\n"
        "    a = torch.tanh(a @ a)\n"
    )
    return subprocess.Popen([sys.executable, "-c", code])


def _median_phases(runs: list[dict]) -> dict[str, float]:
    return {k: statistics.median(r[k] for r in runs) for k in runs[0]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["92x124", "184x248", "368x496"], help="HxW")
    parser.add_argument("--surfels", nargs="+", type=int, default=[10_000, 50_000, 100_000, 200_000, 500_000])
    parser.add_argument("--overlap", type=float, default=15.0, help="surfels covering a pixel (3-sigma discs)")
    parser.add_argument("--ssim-weight", type=float, default=0.2)
    parser.add_argument("--steps", type=int, default=3, help="steps per turn")
    parser.add_argument("--turns", type=int, default=3, help="turns per worker (interleaved with --ref)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--torch-threads", type=int, default=0, help="torch's threads during the step (0: as the fit loop sets them)"
    )
    parser.add_argument("--ref", default=None, metavar="REV", help="also run git revision REV, side by side")
    parser.add_argument("--beside-job", action="store_true", help="also measure beside a busy process")
    parser.add_argument("--out", default="fit_step")
    parser.add_argument("--serve", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve:
        serve(args.threads)
        return

    here = Path(__file__).resolve().parents[1] / "src"
    workers = {"new": Worker(here, args.threads)}
    if args.ref:
        workers["ref"] = Worker(export_revision(args.ref), args.threads)
    configs = [(tuple(map(int, s.split("x"))), n) for s in args.sizes for n in args.surfels]
    rows = []
    try:
        for (height, width), n in configs:
            request = {
                "n": n,
                "width": width,
                "height": height,
                "overlap": args.overlap,
                "ssim": args.ssim_weight,
                "steps": args.steps,
                "torch_threads": args.torch_threads,
            }
            settings = [False, True] if args.beside_job else [False]
            for beside in settings:
                job = busy_job(args.threads) if beside else None
                try:
                    runs = {name: [] for name in workers}
                    for turn in range(args.turns):
                        # alternate who goes first, so neither always follows the other's cache misses
                        order = list(workers) if turn % 2 == 0 else list(reversed(workers))
                        for name in order:
                            runs[name] += workers[name].steps(request)
                finally:
                    if job is not None:
                        job.kill()
                        job.wait()
                for name, measured in runs.items():
                    phases = _median_phases(measured)
                    rows.append(
                        {
                            "code": name if name == "new" else f"ref {args.ref}",
                            "height": height,
                            "width": width,
                            "surfels": n,
                            "beside_job": beside,
                            "steps": len(measured),
                            "us_per_pixel": 1e6 * phases["step"] / (width * height),
                            **{f"{k}_s": v for k, v in phases.items()},
                            "step_all_s": [r["step"] for r in measured],
                            "load_average": os.getloadavg()[0],
                        }
                    )
                print(_line(rows, args.ref, beside), flush=True)
    finally:
        for w in workers.values():
            w.close()

    cpu = cpu_model()
    headers = ["code", "HxW", "N", "job", "step ms", "us/px", *[p[:9] for p in PHASES]]
    table = [
        [
            r["code"],
            f"{r['height']}x{r['width']}",
            r["surfels"],
            "busy" if r["beside_job"] else "",
            round(1e3 * r["step_s"], 1),
            round(r["us_per_pixel"], 3),
            *[round(1e3 * r[f"{p}_s"], 1) for p in PHASES],
        ]
        for r in rows
    ]
    print(f"\nCPU: {cpu}, {args.threads} threads; phase columns in ms (medians)")
    print(text_table(headers, table))
    document = {
        "cpu": cpu,
        "machine": machine(),
        "threads": args.threads,
        "overlap": args.overlap,
        "ssim_weight": args.ssim_weight,
        "ref": args.ref,
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "results": rows,
    }
    print(f"wrote {write_results(args.out, document)}")


def _line(rows: list[dict], ref: str | None, beside: bool) -> str:
    new = next(r for r in reversed(rows) if r["code"] == "new" and r["beside_job"] == beside)
    text = (
        f"{new['height']}x{new['width']} {new['surfels']:>7} {'busy ' if beside else ''}"
        f"new {1e3 * new['step_s']:8.1f} ms"
    )
    if ref:
        old = next(r for r in reversed(rows) if r["code"] != "new" and r["beside_job"] == beside)
        text += f"  ref {1e3 * old['step_s']:8.1f} ms  x{old['step_s'] / new['step_s']:.2f}"
    return text


if __name__ == "__main__":
    main()
