"""The one loop that fits surfels to photos: the refinement and the per-scene optimization.

    fitted, stats = fit_on_views(gaussians, cameras, images, width, height, plan)

A `FitPlan` says what is fitted and how: which surfel attributes are free (each with its Adam
rate), the loss (the mean squared colour error, or 3DGS's (1 - w) L1 + w D-SSIM with 2DGS's
depth-normal consistency term), how the position rate decays, when higher SH degrees join, when
faint surfels are pruned, and the early stop. `RefineConfig` (`refine.py`) and `OptimizeConfig`
(`optimize.py`) each build a plan; neither has a loop of its own.

Every step renders at most `views_per_step` of the views (drawn by a seeded generator without
replacement, so every run is the same), with `render(backend=...)` on the surfels' device ("auto":
gsplat on CUDA, the compiled kernels on the CPU). The colour error over every view at the full
size is measured before and after; a fit that raised it is not kept.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..utils.checks import SurfSplatInputError
from ..utils.heap import reuse_freed_memory
from .adam import SelectiveAdam, visible_rows
from .densify import Densify, DensifyConfig
from .losses import colour_loss, depth_normal_error, distortion_error
from .mcmc import MCMC, MCMCConfig
from .per_view import PerView, PerViewConfig

logger = logging.getLogger(__name__)

# The tensors a plan may free, each fitted in the space Adam moves it well in:
# positions as they are, quaternions unnormalized (normalized when rendered), the two tangent scales
# as logarithms, opacities as logits, and the SH's DC and higher-degree coefficients apart (3DGS gives
# them different rates).
TENSORS = ("means", "quats", "log_scales", "logits", "sh_dc", "sh_rest")
MIN_LEVEL_SIZE = 32  # px: a coarse level whose short side would be smaller is skipped
_DRAW_BLOCK = 256
PSNR_EVERY = (
    50  # steps between the progress bar's PSNR readings  # steps whose views are drawn and moved to the device at once
)


@dataclass(frozen=True)
class FitPlan:
    """What one run of `fit_on_views` fits and how; built by RefineConfig and OptimizeConfig."""

    name: str  # "refine" or "optimize": the progress bar's label and the messages'
    steps: int  # Adam steps at most
    rates: dict[str, float]  # Adam rate of each fitted tensor (keys of TENSORS; the others stay as given)
    views_per_step: int = 8  # views rendered in one step (all of them when fewer)
    seed: int = 0  # which views each step renders
    scale: float = 1.0  # the fit's renders at this fraction of the working size (photos area-averaged)
    loss: Literal["mse", "l1_dssim"] = "mse"  # the colour term
    ssim_weight: float = 0.2  # "l1_dssim": the D-SSIM share (3DGS's lambda_dssim)
    normal_weight: float = 0.0  # 2DGS's depth-normal consistency term (0: off)
    normal_from: float = 0.0  # the share of the steps after which that term joins
    distortion_weight: float = 0.0  # 2DGS's depth-distortion term (0: off; the renders then skip its map)
    distortion_from: float = 0.0  # the share of the fit after which that term joins
    means_final_rate: float | None = None  # the position rate decays exponentially to this (None: constant)
    sh_degree_share: float | None = None  # share of the fit between raisings of the SH degree from 0 (None: all)
    prune_every: int | None = None  # steps between prunings of faint surfels (None: never)
    prune_opacity: float = 0.005  # a pruning removes the surfels below this opacity
    # coarse to fine: (until this share of the fit, render scale) pairs, in order; then `scale`
    levels: tuple[tuple[float, float], ...] = ()
    # the densification strategy: 3DGS's clone / split / prune / opacity reset (AbsGS with its absgrad),
    # or 3DGS-MCMC's relocation under a fixed budget (None: none)
    densify: DensifyConfig | MCMCConfig | None = None
    extent: float = 1.0  # the scene extent the densification's world sizes are shares of
    # a time budget: the fit runs until this many seconds have passed (or `steps`), and its progress,
    # which every schedule follows, is the share of the budget spent (None: the share of the steps)
    seconds: float | None = None
    patience: int | None = None  # steps per window of the early stop (None: every step runs)
    min_improvement: float = 0.01  # stop when a window's mean loss fell by less than this share
    extra: dict = field(default_factory=dict)  # figures the plan's owner adds to the stats
    # "selective": a step's Adam updates only the rows of the surfels its views saw (`adam.SelectiveAdam`)
    adam: Literal["dense", "selective"] = "dense"
    # each photo's exposure and camera correction, fitted beside the surfels (None: neither; per_view.py)
    per_view: PerViewConfig | None = None
    # every render of the fit with the antialiasing filter (`render(..., antialiased=True)`): the surfels
    # are fitted as they will be drawn at other sizes, their opacity compensated for the pixel's widening
    antialiased: bool = False

    def __post_init__(self) -> None:
        unknown = set(self.rates) - set(TENSORS)
        if unknown:
            raise SurfSplatInputError(f"{self.name}: unknown fitted tensors {sorted(unknown)}; expected {TENSORS}")


def fit_on_views(
    gaussians: Gaussians,  # [N] unbatched
    cameras: Cameras,  # [V] K in pixels of height x width
    images: Tensor,  # [V, 3, H, W] in [0, 1]
    width: int,
    height: int,
    plan: FitPlan,
    *,
    mode: str = "surfel",
    alpha_threshold: float | None = 0.001,
    backend: str = "auto",
    progress: bool = False,
    monitor: Callable[[int, float, Gaussians], None] | None = None,
    monitor_every: float = 0.1,
    per_view_out: dict | None = None,
) -> tuple[Gaussians, dict[str, float]]:
    """The surfels fitted as `plan` says, and the fit's figures: {"steps", "max_steps", "mse_before",
    "mse_after", "kept", "scale", "width", "height", "seconds"} (colour errors over every view at the
    full size; a fit that raised it is not kept and the given surfels come back).

    `monitor(step, seconds, surfels, alpha_threshold)` is called before the first step, each time the fit's progress
    passes another `monitor_every`, and after the last step, with the surfels as they then are and
    the seconds the fit has run; its own time is not counted in them (held-out scores along the way).

    With `plan.per_view`, each photo's exposure map and camera correction are fitted beside the surfels
    (`per_view.PerView`); `per_view_out` (a dict) then receives "cameras" (the refined context
    cameras) and "exposure" ([V, 3, 4] or None), and the colour errors before and after are those of
    the exposed renders from the refined cameras."""
    from ..render import render, resolve_backend
    from ..utils.log import progress as progress_bar

    start = time.perf_counter()
    v = len(cameras)
    if images.shape != (v, 3, height, width):
        raise SurfSplatInputError(
            f"{plan.name}: images expected [{v}, 3, {height}, {width}], got {tuple(images.shape)}"
        )
    g0 = gaussians.detach()
    if g0.explicit_covariances is not None:
        raise SurfSplatInputError(
            f"{plan.name}: surfels with explicit covariances (the release adapter) have no scales to fit"
        )
    images = images.to(g0.means.device, g0.means.dtype)
    cameras = cameras.to(device=g0.means.device, dtype=g0.means.dtype)
    if getattr(plan.densify, "absgrad", False) and resolve_backend(backend, g0.means.device, None, cameras) == "gsplat":
        raise SurfSplatInputError(
            f"{plan.name}: the absgs strategy needs the absolute screen gradient, which the gsplat backend cannot "
            "give for surfels; use backend='torch' or 'cpu', or another strategy"
        )

    def at_scale(scale: float) -> tuple[Cameras, Tensor, int, int]:
        """The cameras and photos (area-averaged) the fit renders at `scale` of the working size."""
        w, h = max(1, round(width * scale)), max(1, round(height * scale))
        if plan.loss == "l1_dssim" and plan.ssim_weight > 0 and min(w, h) < 11:
            raise SurfSplatInputError(
                f"{plan.name}: the D-SSIM term needs renders of at least 11x11 pixels, got {w}x{h} "
                "(raise the render scale or set the SSIM weight to 0)"
            )
        resize = torch.tensor([w / width, h / height, 1.0], dtype=cameras.K.dtype, device=cameras.K.device)
        cams = Cameras(cameras.c2w, cameras.K * resize[:, None], validate=False)
        return cams, (images if (w, h) == (width, height) else F.interpolate(images, size=(h, w), mode="area")), w, h

    # coarse levels too small to hold detail (or the D-SSIM window) are skipped: their steps render finer
    coarse = [(until, s) for until, s in plan.levels if min(width, height) * s >= MIN_LEVEL_SIZE]
    levels = [(until, at_scale(s)) for until, s in coarse] + [(None, at_scale(plan.scale))]
    fit_w, fit_h = levels[-1][1][2], levels[-1][1][3]

    def draw(g: Gaussians, cams: Cameras, w: int, h: int, distortion: bool = False, absgrad: bool = False):
        return render(
            g,
            cams,
            w,
            h,
            mode=mode,
            backend=backend,
            alpha_threshold=alpha_threshold,
            distortion=distortion,
            antialiased=plan.antialiased,
            absgrad=absgrad,
        )

    views = PerView(plan.per_view, cameras, plan.extent) if plan.per_view is not None and plan.per_view.active else None

    def colours(
        g: Gaussians, cams: Cameras, which: Tensor, w: int, h: int, distortion: bool = False, absgrad: bool = False
    ):
        """(RenderOutput, colour) of the views `which` of `cams`: with per-view terms each view renders
        the surfels moved by its camera correction, and its colour goes through its exposure map."""
        if views is None:
            out = draw(g, cams[which], w, h, distortion, absgrad)
            return out, out.color
        if views.config.cameras:
            parts = [draw(views.moved(g, int(i)), cams[int(i)], w, h, distortion, absgrad) for i in which.tolist()]
            out = concat_outputs(parts)
        else:
            out = draw(g, cams[which], w, h, distortion, absgrad)
        return out, views.expose(out.color, which)

    def mse(g: Gaussians) -> float:
        with torch.no_grad():
            chunks = torch.arange(v, device=images.device).split(plan.views_per_step)
            sums = torch.stack([(colours(g, cameras, c, width, height)[1] - images[c]).square().sum() for c in chunks])
        # read once; the chunks' float32 sums are added in Python's double precision, as they always were
        return sum(sums.tolist()) / images.numel()

    total = plan.steps
    figures = {"max_steps": total, "scale": plan.scale, "width": fit_w, "height": fit_h}
    before = mse(g0)
    if total == 0:
        seconds = time.perf_counter() - start
        return g0, {"steps": 0, "mse_before": before, "mse_after": before, "kept": 1.0, **figures, "seconds": seconds}

    free = _Free(g0, plan)
    selective = plan.adam == "selective"
    optimizer = SelectiveAdam(free.groups()) if selective else adam(free.groups(), g0.means.device)
    densify = make_strategy(plan.densify, plan.extent, len(g0), g0.means.device)
    split_generator = torch.Generator().manual_seed(plan.seed + 1)
    # Every step's views drawn on the host's generator (the same draws on every device) and moved to
    # the device a block of steps at a time: [block, views rendered a step].
    generator = torch.Generator().manual_seed(plan.seed)
    draws: list[Tensor] = []

    def views_of(step: int) -> Tensor:
        if step % _DRAW_BLOCK == 0:
            block = min(_DRAW_BLOCK, total - step)
            rows = [torch.randperm(v, generator=generator)[: plan.views_per_step].sort().values for _ in range(block)]
            draws[:] = list(torch.stack(rows).to(images.device))
        return draws[step % _DRAW_BLOCK]

    # Each step's loss stays on the device until a window of the early stop ends (never without
    # one): reading it every step would make the host wait for the device every step.
    losses: list[float] = []
    pending: list[Tensor] = []
    fit_start = time.perf_counter()
    watched = 0.0  # seconds spent in the monitor, not counted as the fit's
    marks = 0  # monitor calls so far after the first

    def watch(step: int, done: float) -> None:
        nonlocal watched
        if monitor is None:
            return
        tick = time.perf_counter()
        with torch.no_grad():
            monitor(step, tick - fit_start - watched, free.current(done).detach(), alpha_threshold)
        watched += time.perf_counter() - tick

    watch(0, 0.0)
    # the bar counts steps, or with a time budget seconds; it shows the fit's colour PSNR on the photos
    # of the last PSNR_EVERY steps (read then, not every step: each read makes a GPU host wait)
    timed = plan.seconds is not None
    errors: list[Tensor] = []
    shown = 0
    bar_total, unit = (round(plan.seconds), "s") if timed else (total, "step")
    with (
        step_threads(g0.means.device),
        progress_bar(total=bar_total, desc=plan.name, unit=unit, enabled=progress) as bar,
    ):
        for step in range(total):
            done = progress_of(plan, step, time.perf_counter() - fit_start - watched)
            if done >= 1:
                break
            if int(done / monitor_every) > marks:
                marks = int(done / monitor_every)
                watch(step, done)
            free.schedule(optimizer, done)
            if views is not None:
                views.schedule(done)
            which = views_of(step)
            fit_cameras, fit_images, fit_w, fit_h = next(lv for until, lv in levels if until is None or done < until)
            distorted = plan.distortion_weight > 0 and done >= plan.distortion_from
            absgrad = densify is not None and densify.wants_absgrad(done)
            out, colour = colours(
                free.current(done, unit_quats=False), fit_cameras, which, fit_w, fit_h, distorted, absgrad
            )
            loss = colour_loss(colour, fit_images[which], plan.loss, plan.ssim_weight)
            penalty = densify.penalty(free) if densify is not None else None
            if penalty is not None:
                loss = loss + penalty
            if distorted:
                loss = loss + plan.distortion_weight * distortion_error(out.distortion)
            if plan.normal_weight > 0 and done >= plan.normal_from:
                loss = loss + plan.normal_weight * depth_normal_error(
                    out.depth, out.normal, out.alpha, fit_cameras[which]
                )
            optimizer.zero_grad(set_to_none=True)
            if views is not None:
                views.zero_grad()
            loss.backward()
            if densify is not None:
                means = free.tensors["means"]
                screen = out.absgrad.grad if absgrad else None
                densify.observe(means, means.grad, fit_cameras[which], fit_w, fit_h, done, screen)
            if selective:
                optimizer.step(visible_rows(list(free.tensors.values())))
            else:
                optimizer.step()
            if views is not None:
                views.step()
            pending.append(loss.detach())
            if progress:
                errors.append((colour.detach() - fit_images[which]).square().mean())
                if len(errors) == PSNR_EVERY:
                    error = float(torch.stack(errors).mean())
                    bar.set_postfix(psnr=f"{-10 * math.log10(max(error, 1e-12)):.2f} dB", refresh=False)
                    errors = []
            if timed:
                now = min(bar_total, int(time.perf_counter() - fit_start - watched))
                bar.update(now - shown)
                shown = now
            else:
                bar.update(1)
            if densify is not None:
                densify.step(free, optimizer, step, done, split_generator)
            if plan.prune_every and (step + 1) % plan.prune_every == 0 and step + 1 < total:
                free.prune(optimizer, plan.prune_opacity)
            if plan.patience is not None and (step + 1) % plan.patience == 0:
                losses += torch.stack(pending).tolist()
                pending = []
                if _stalled(losses, plan.patience, plan.min_improvement):
                    break
    steps = len(losses) + len(pending)
    watch(steps, 1.0)
    with torch.no_grad():
        fitted = free.current(1.0).detach()
    after = mse(fitted)
    stats = {"steps": steps, "mse_before": before, "mse_after": after, "kept": float(after <= before), **figures}
    if densify is not None:
        stats["densify"] = densify.history
    if views is not None:
        stats["per_view"] = views.summary()
        if per_view_out is not None and after <= before:
            per_view_out["cameras"] = views.refined_cameras()
            per_view_out["exposure"] = views.tensors["exposure"].detach() if views.config.appearance else None
    stats["seconds"] = time.perf_counter() - start - watched
    if after > before:  # a rate too high for this scene: the photos are matched worse, so it is not used
        logger.warning(
            "%s: the fit raised the context views' colour error (%.3g -> %.3g); the surfels are kept as they were "
            "(lower the rates)",
            plan.name,
            before,
            after,
        )
        return g0, stats
    return fitted, stats


def make_strategy(
    config: DensifyConfig | MCMCConfig | None, extent: float, n: int, device: torch.device
) -> Densify | MCMC | None:
    """The densification strategy a plan names (None: none). Each is a plan of this loop, called at the
    same three places of a step: `penalty(free)` joins the loss, `observe(...)` reads the step's gradients
    after the backward, and `step(...)` changes the surfels (and Adam's rows) after the optimizer's step."""
    if config is None:
        return None
    if isinstance(config, MCMCConfig):
        return MCMC(config, extent, n, device)
    return Densify(config, extent, n, device)


@contextmanager
def step_threads(device: torch.device) -> Iterator[None]:
    """Torch's own ops on one thread while the fit's steps run on the CPU (the compiled renderer keeps
    its threads), and freed memory kept for the next step (`utils.heap.reuse_freed_memory`).

    A step is some hundred torch ops on a few hundred thousand values (activations, loss, their
    backward, Adam), each a parallel region that has to wake torch's other threads. Beside another
    busy process a woken thread waits for a core for up to the scheduler's latency, so at two threads
    the step's torch ops took several times the rest of the step; on one thread they cannot wait
    for each other, and the renderer's kernels, where the work is, still use every core. Every step
    also allocates and frees the same large buffers, which would otherwise come as fresh pages each
    time.
    """
    if device.type != "cpu":
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with reuse_freed_memory():
            yield
    finally:
        torch.set_num_threads(before)


def adam(groups: list[dict], device: torch.device) -> torch.optim.Adam:
    """The fit's Adam: on the CPU torch's fused step, one pass over each tensor (the default
    for-each step makes some ten whole-tensor passes, each a parallel region; it took 7x longer at
    100k surfels beside another busy process). `FitPlan.adam` "selective" takes `adam.SelectiveAdam`."""
    return torch.optim.Adam(groups, fused=True if device.type == "cpu" else None)


class _Free:
    """The fitted tensors of a plan and the surfels they make; the others stay the given surfels'."""

    def __init__(self, g0: Gaussians, plan: FitPlan) -> None:
        self.g0, self.plan = g0, plan
        start = {
            "means": lambda: g0.means,
            "quats": lambda: g0.quats,
            "log_scales": lambda: g0.scales[:, :2].log(),
            "logits": lambda: torch.logit(g0.opacities.clamp(1e-4, 1 - 1e-4)),
            "sh_dc": lambda: g0.sh[..., :1],
            "sh_rest": lambda: g0.sh[..., 1:],
        }
        self.tensors = {k: start[k]().clone().requires_grad_(True) for k in TENSORS if k in plan.rates}
        self.max_degree = g0.sh_degree
        # the schedule raises the degree from the start's own: a start that already has view-dependent
        # colour (the network's surfels) keeps it, one without (points) begins at the DC term
        # (read once, where a schedule runs: each read is a host wait on a GPU)
        self.start_degree = 0
        if plan.sh_degree_share is not None and self.max_degree > 0:
            used = (g0.sh[..., 1:] != 0).flatten(0, 1).any(0).tolist()  # per coefficient past the DC term
            self.start_degree = max((math.isqrt(k + 1) for k, u in enumerate(used) if u), default=0)

    def groups(self) -> list[dict]:
        return [{"params": [t], "lr": self.plan.rates[k], "name": k} for k, t in self.tensors.items()]

    def schedule(self, optimizer: torch.optim.Optimizer, done: float) -> None:
        """The position rate's exponential decay over the fit's progress `done` in [0, 1] (3DGS's
        `get_expon_lr_func` without its delay)."""
        final = self.plan.means_final_rate
        if final is None or "means" not in self.tensors:
            return
        first = self.plan.rates["means"]
        rate = math.exp((1 - done) * math.log(first) + done * math.log(final))
        for group in optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = rate

    def degree(self, done: float) -> int:
        """The SH degree rendered at progress `done`: raised by one every `sh_degree_share` of the fit
        from 0, as 3DGS raises it every 1,000 of its 30,000 steps, and never below the start's own."""
        share = self.plan.sh_degree_share
        if share is None:
            return self.max_degree
        return max(self.start_degree, min(self.max_degree, int(done / share + 1e-9)))

    def current(self, done: float, unit_quats: bool = True) -> Gaussians:
        """The surfels at progress `done`. `unit_quats=False` hands the fitted quaternions over
        unnormalized, for a render: every backend normalizes them itself (`quat_to_matrix`, the CPU
        kernels, gsplat), so a normalization here would only cost a pass forward and two backward."""
        t, g0 = self.tensors, self.g0
        means = t.get("means", g0.means)
        if "quats" not in t:
            quats = g0.quats
        else:
            quats = F.normalize(t["quats"], dim=-1) if unit_quats else t["quats"]
        scales = torch.cat((t["log_scales"].exp(), g0.scales[:, 2:]), -1) if "log_scales" in t else g0.scales
        opacities = torch.sigmoid(t["logits"]) if "logits" in t else g0.opacities
        if "sh_dc" in t or "sh_rest" in t:
            sh = torch.cat((t.get("sh_dc", g0.sh[..., :1]), t.get("sh_rest", g0.sh[..., 1:])), -1)
        else:
            sh = g0.sh
        degree = self.degree(done)
        if degree < self.max_degree:  # the higher degrees neither render nor learn until their turn
            sh = torch.cat((sh[..., : (degree + 1) ** 2], torch.zeros_like(sh[..., (degree + 1) ** 2 :])), -1)
        return replace(g0, means=means, quats=quats, scales=scales, opacities=opacities, sh=sh, validate=False)

    def append(self, optimizer: torch.optim.Optimizer, new: dict[str, Tensor]) -> None:
        """Add rows to every fitted tensor, all of TENSORS (the rows a new surfel came from are not known
        here, so an unfitted attribute could not follow); Adam's moments of the new rows start at zero
        (3DGS's `cat_tensors_to_optimizer`)."""
        if set(new) != set(self.tensors) or set(self.tensors) != set(TENSORS):
            raise SurfSplatInputError(f"{self.plan.name}: densification needs every surfel attribute fitted")
        count = len(next(iter(new.values())))
        if count == 0:
            return
        for group in optimizer.param_groups:
            old = group["params"][0]
            grown = torch.cat((old.detach(), new[group["name"]].to(old))).requires_grad_(True)
            state = optimizer.state.pop(old, None)
            if state:
                state = {
                    k: (
                        torch.cat((v, torch.zeros(count, *v.shape[1:], dtype=v.dtype, device=v.device)))
                        if isinstance(v, Tensor) and v.shape[:1] == old.shape[:1]
                        else v
                    )
                    for k, v in state.items()
                }
                optimizer.state[grown] = state
            group["params"] = [grown]
            self.tensors[group["name"]] = grown
        self.g0 = self._grown_base(count)

    def _grown_base(self, count: int) -> Gaussians:
        """The given surfels with `count` rows appended (their values are never read: every attribute is fitted)."""
        g0 = self.g0
        pad = lambda t: torch.cat((t, t[:1].expand(count, *t.shape[1:])))  # noqa: E731
        return replace(
            g0,
            means=pad(g0.means),
            quats=pad(g0.quats),
            scales=pad(g0.scales),
            opacities=pad(g0.opacities),
            sh=pad(g0.sh),
            validate=False,
        )

    def keep(self, optimizer: torch.optim.Optimizer, keep: Tensor) -> None:
        """Keep the rows `keep` selects, in the tensors and in Adam's moments alike."""
        self.g0 = self.g0.subset(keep)
        for group in optimizer.param_groups:
            old = group["params"][0]
            new = old.detach()[keep].clone().requires_grad_(True)
            state = optimizer.state.pop(old, None)
            if state:
                state = {
                    k: (v[keep] if isinstance(v, Tensor) and v.shape[:1] == old.shape[:1] else v)
                    for k, v in state.items()
                }
                optimizer.state[new] = state
            group["params"] = [new]
            self.tensors[group["name"]] = new

    def prune(self, optimizer: torch.optim.Optimizer, threshold: float) -> None:
        """Remove the surfels whose opacity fell below `threshold` (3DGS's min_opacity pruning),
        from the tensors and from Adam's moments alike."""
        opacities = torch.sigmoid(self.tensors["logits"]) if "logits" in self.tensors else self.g0.opacities
        keep = opacities.detach() >= threshold
        if bool(keep.all()) or not bool(keep.any()):  # one sync per pruning, a few per fit
            return
        self.keep(optimizer, keep)


def concat_outputs(parts: list) -> object:
    """One RenderOutput of several renders' (each of one or more cameras), camera by camera."""
    first = parts[0]
    if len(parts) > 1 and first.absgrad is not None:  # each render's probe is a leaf of its own
        raise SurfSplatInputError(
            "fit: the absolute screen gradient (absgs) with camera refinement needs one view a step (views_per_step=1)"
        )
    joined = {
        name: None if getattr(first, name) is None else torch.cat([getattr(p, name) for p in parts])
        for name in ("color", "alpha", "depth", "normal", "distortion")
    }
    return replace(first, **joined)


def progress_of(plan: FitPlan, step: int, elapsed: float) -> float:
    """How far the fit has come when `step` starts, in [0, 1): the share of the steps run, or with a
    time budget the larger of that and the share of the seconds spent (1: the fit is over)."""
    done = step / plan.steps if plan.steps > 0 else 1.0
    if plan.seconds is not None:
        done = max(done, elapsed / plan.seconds)
    return min(done, 1.0)


def _stalled(losses: list[float], patience: int | None, min_improvement: float) -> bool:
    """Whether the last window of `patience` steps lowered the mean loss by less than
    `min_improvement` of the window before it (windows end at the current step)."""
    if patience is None or len(losses) < 2 * patience or len(losses) % patience:
        return False
    last = sum(losses[-patience:]) / patience
    previous = sum(losses[-2 * patience : -patience]) / patience
    return last > previous * (1 - min_improvement)
