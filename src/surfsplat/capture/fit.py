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
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..utils.checks import SurfSplatInputError

logger = logging.getLogger(__name__)

# The tensors a plan may free, each fitted in the space Adam moves it well in:
# positions as they are, quaternions unnormalized (normalized when rendered), the two tangent scales
# as logarithms, opacities as logits, and the SH's DC and higher-degree coefficients apart (3DGS gives
# them different rates).
TENSORS = ("means", "quats", "log_scales", "logits", "sh_dc", "sh_rest")


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
    means_final_rate: float | None = None  # the position rate decays exponentially to this (None: constant)
    sh_degree_every: int | None = None  # steps between raising the SH degree used from 0 (None: all at once)
    prune_every: int | None = None  # steps between prunings of faint surfels (None: never)
    prune_opacity: float = 0.005  # a pruning removes the surfels below this opacity
    patience: int | None = None  # steps per window of the early stop (None: every step runs)
    min_improvement: float = 0.01  # stop when a window's mean loss fell by less than this share
    extra: dict = field(default_factory=dict)  # figures the plan's owner adds to the stats

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
) -> tuple[Gaussians, dict[str, float]]:
    """The surfels fitted as `plan` says, and the fit's figures: {"steps", "max_steps", "mse_before",
    "mse_after", "kept", "scale", "width", "height", "seconds"} (colour errors over every view at the
    full size; a fit that raised it is not kept and the given surfels come back)."""
    from ..render import render
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

    fit_w, fit_h = max(1, round(width * plan.scale)), max(1, round(height * plan.scale))
    if plan.loss == "l1_dssim" and plan.ssim_weight > 0 and min(fit_w, fit_h) < 11:
        raise SurfSplatInputError(
            f"{plan.name}: the D-SSIM term needs renders of at least 11x11 pixels, got {fit_w}x{fit_h} "
            "(raise the render scale or set the SSIM weight to 0)"
        )
    resize = torch.tensor([fit_w / width, fit_h / height, 1.0], dtype=cameras.K.dtype, device=cameras.K.device)
    fit_cameras = Cameras(cameras.c2w, cameras.K * resize[:, None], validate=False)
    fit_images = images if plan.scale == 1 else F.interpolate(images, size=(fit_h, fit_w), mode="area")

    def draw(g: Gaussians, cams: Cameras, w: int, h: int):
        return render(g, cams, w, h, mode=mode, backend=backend, alpha_threshold=alpha_threshold)

    def mse(g: Gaussians) -> float:
        with torch.no_grad():
            chunks = torch.arange(v, device=images.device).split(plan.views_per_step)
            sums = torch.stack([(draw(g, cameras[c], width, height).color - images[c]).square().sum() for c in chunks])
        # read once; the chunks' float32 sums are added in Python's double precision, as they always were
        return sum(sums.tolist()) / images.numel()

    total = plan.steps
    figures = {"max_steps": total, "scale": plan.scale, "width": fit_w, "height": fit_h}
    before = mse(g0)
    if total == 0:
        seconds = time.perf_counter() - start
        return g0, {"steps": 0, "mse_before": before, "mse_after": before, "kept": 1.0, **figures, "seconds": seconds}

    free = _Free(g0, plan)
    optimizer = adam(free.groups(), g0.means.device)
    # Every step's views drawn up front on the host's generator (the same draws on every device)
    # and moved to the device once: [steps, views rendered a step].
    generator = torch.Generator().manual_seed(plan.seed)
    draws = [torch.randperm(v, generator=generator)[: plan.views_per_step].sort().values for _ in range(total)]
    draws = torch.stack(draws).to(images.device)
    normal_start = math.ceil(plan.normal_from * total) if plan.normal_weight > 0 else None
    # Each step's loss stays on the device until a window of the early stop ends (never without
    # one): reading it every step would make the host wait for the device every step.
    losses: list[float] = []
    pending: list[Tensor] = []
    with step_threads(g0.means.device), progress_bar(total=total, desc=plan.name, unit="step", enabled=progress) as bar:
        for step in range(total):
            free.schedule(optimizer, step)
            which = draws[step]
            out = draw(free.current(step), fit_cameras[which], fit_w, fit_h)
            loss = colour_loss(out.color, fit_images[which], plan.loss, plan.ssim_weight)
            if normal_start is not None and step >= normal_start:
                loss = loss + plan.normal_weight * depth_normal_error(
                    out.depth, out.normal, out.alpha, fit_cameras[which]
                )
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            pending.append(loss.detach())
            bar.update(1)
            if plan.prune_every and (step + 1) % plan.prune_every == 0 and step + 1 < total:
                free.prune(optimizer, plan.prune_opacity)
            if plan.patience is not None and (step + 1) % plan.patience == 0:
                losses += torch.stack(pending).tolist()
                pending = []
                if _stalled(losses, plan.patience, plan.min_improvement):
                    break
    steps = len(losses) + len(pending)
    with torch.no_grad():
        fitted = free.current(steps - 1).detach()
    after = mse(fitted)
    stats = {"steps": steps, "mse_before": before, "mse_after": after, "kept": float(after <= before), **figures}
    stats["seconds"] = time.perf_counter() - start
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


@contextmanager
def step_threads(device: torch.device) -> Iterator[None]:
    """Torch's own ops on one thread while the fit's steps run on the CPU (the compiled renderer keeps
    its threads).

    A step is some hundred torch ops on a few hundred thousand values (activations, loss, their
    backward, Adam), each a parallel region that has to wake torch's other threads. Beside another
    busy process a woken thread waits for a core for up to the scheduler's latency, so at two threads
    the step's torch ops took several times the rest of the step; on one thread they cannot wait
    for each other, and the renderer's kernels, where the work is, still use every core.
    """
    if device.type != "cpu":
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def adam(groups: list[dict], device: torch.device) -> torch.optim.Adam:
    """The fit's Adam: on the CPU torch's fused step, one pass over each tensor (the default
    for-each step makes some ten whole-tensor passes, each a parallel region; it took 7x longer at
    100k surfels beside another busy process)."""
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

    def groups(self) -> list[dict]:
        return [{"params": [t], "lr": self.plan.rates[k], "name": k} for k, t in self.tensors.items()]

    def schedule(self, optimizer: torch.optim.Optimizer, step: int) -> None:
        """The position rate's exponential decay (3DGS's `get_expon_lr_func` without its delay)."""
        final = self.plan.means_final_rate
        if final is None or "means" not in self.tensors:
            return
        t = step / max(1, self.plan.steps - 1)
        first = self.plan.rates["means"]
        rate = math.exp((1 - t) * math.log(first) + t * math.log(final))
        for group in optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = rate

    def degree(self, step: int) -> int:
        """The SH degree rendered at `step`: raised by one every `sh_degree_every` steps from 0, as 3DGS does."""
        every = self.plan.sh_degree_every
        return self.max_degree if every is None else min(self.max_degree, step // every)

    def current(self, step: int) -> Gaussians:
        t, g0 = self.tensors, self.g0
        means = t.get("means", g0.means)
        quats = F.normalize(t["quats"], dim=-1) if "quats" in t else g0.quats
        scales = torch.cat((t["log_scales"].exp(), g0.scales[:, 2:]), -1) if "log_scales" in t else g0.scales
        opacities = torch.sigmoid(t["logits"]) if "logits" in t else g0.opacities
        if "sh_dc" in t or "sh_rest" in t:
            sh = torch.cat((t.get("sh_dc", g0.sh[..., :1]), t.get("sh_rest", g0.sh[..., 1:])), -1)
        else:
            sh = g0.sh
        degree = self.degree(step)
        if degree < self.max_degree:  # the higher degrees neither render nor learn until their turn
            sh = torch.cat((sh[..., : (degree + 1) ** 2], torch.zeros_like(sh[..., (degree + 1) ** 2 :])), -1)
        return replace(g0, means=means, quats=quats, scales=scales, opacities=opacities, sh=sh, validate=False)

    def prune(self, optimizer: torch.optim.Optimizer, threshold: float) -> None:
        """Remove the surfels whose opacity fell below `threshold` (3DGS's min_opacity pruning),
        from the tensors and from Adam's moments alike."""
        opacities = torch.sigmoid(self.tensors["logits"]) if "logits" in self.tensors else self.g0.opacities
        keep = opacities.detach() >= threshold
        if bool(keep.all()) or not bool(keep.any()):  # one sync per pruning, a few per fit
            return
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


def colour_loss(prediction: Tensor, target: Tensor, kind: str, ssim_weight: float = 0.2) -> Tensor:
    """The colour term of a fit: the mean squared error ("mse"), or 3DGS's (1 - w) L1 + w (1 - SSIM)
    ("l1_dssim"), SSIM being the project's metric (`surfsplat.metrics.ssim`, scikit-image's Gaussian
    window of 11 taps, sigma 1.5) so the fit climbs the figure it is scored on.
    prediction, target: [V, 3, H, W]."""
    if kind == "mse":
        return (prediction - target).square().mean()
    from ..metrics import ssim

    l1 = (prediction - target).abs().mean()
    if ssim_weight == 0:
        return l1
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - ssim(prediction, target).mean())


def depth_normal_error(
    depth: Tensor,  # [V, 1, H, W] camera z, rendered
    normal: Tensor,  # [V, 3, H, W] world frame, facing the camera, rendered
    alpha: Tensor,  # [V, 1, H, W]
    cameras: Cameras,  # [V] K in pixels of W x H
) -> Tensor:
    """2DGS's depth-normal consistency (its Eq. 14): 1 - n . N, where n is the rendered normal and N
    the normal of the surface the rendered depth describes (the cross product of its central
    differences, in the world frame, facing the camera), weighted by alpha as 2DGS does; the mean
    over the inner pixels. Differentiable in both maps."""
    v, _, h, w = depth.shape
    rows = torch.arange(h, dtype=depth.dtype, device=depth.device) + 0.5
    cols = torch.arange(w, dtype=depth.dtype, device=depth.device) + 0.5
    pixels = torch.stack(
        (
            cols[None, :].expand(h, w),
            rows[:, None].expand(h, w),
            torch.ones(h, w, dtype=depth.dtype, device=depth.device),
        )
    )
    # inv_ex: no error flag read on the host (a GPU would wait for it every step)
    rays = torch.einsum("vij,jhw->vihw", torch.linalg.inv_ex(cameras.K.to(depth)).inverse, pixels)  # z = 1
    c2w = cameras.c2w.to(depth)
    points = torch.einsum("vij,vjhw->vihw", c2w[:, :3, :3], rays * depth) + c2w[:, :3, 3, None, None]
    right = points[..., 1:-1, 2:] - points[..., 1:-1, :-2]
    down = points[..., 2:, 1:-1] - points[..., :-2, 1:-1]
    # down x right faces the camera: for a fronto-parallel plane (0, 1, 0) x (1, 0, 0) = (0, 0, -1)
    surface = F.normalize(torch.cross(down, right, dim=1), dim=1)
    agreement = (normal[..., 1:-1, 1:-1] * surface).sum(1, keepdim=True)
    return ((1 - agreement) * alpha[..., 1:-1, 1:-1]).mean()


def _stalled(losses: list[float], patience: int | None, min_improvement: float) -> bool:
    """Whether the last window of `patience` steps lowered the mean loss by less than
    `min_improvement` of the window before it (windows end at the current step)."""
    if patience is None or len(losses) < 2 * patience or len(losses) % patience:
        return False
    last = sum(losses[-patience:]) / patience
    previous = sum(losses[-2 * patience : -patience]) / patience
    return last > previous * (1 - min_improvement)
