"""Bake surfels for standard 3D Gaussian splatting viewers.

Our picture is the forced-alpha-blended surfel render (paper Sec. 3.4): the composited colour is
divided by the accumulated alpha, so faint surfels (the adapter caps opacity at 0.6; the shipped
model's median on a DTU pair is 0.10) that cover a pixel to alpha 0.6 still show its full colour. Standard 3DGS viewers
(SuperSplat, gsplat's viewers, ...) composite the same Gaussians without that division, on their
background: they show a faint, see-through version of the scene. Their compositing is our
renderer's `mode="ewa"` with `alpha_threshold=None` (SuperSplat matches it to 43.8 dB, see the
README's viewer check).

`bake_for_viewers` returns Gaussians for such viewers (the 3DGS layout: explicit covariances with
a third axis) whose plain compositing on black reproduces our picture. Positions and rotations stay;
per Gaussian, the opacity logit, three log-scales (tangent u, v and a thin third axis) and the SH
are fitted by Adam against our renders (colour on black, and accumulated alpha 1 where our render
covers the pixel, 0 where it does not), from the context views (optionally also views
interpolated between them and slightly jittered copies of them, and at x2: `BakeConfig`), one
view per step; as the compaction
refit does, a better iterate is never left behind (see `bake_for_viewers`). Opacities start saturated: a surfel's opacity o becomes 1 - (1 - o)^m with
m chosen so that the pixels it covers, whose standard alpha averages A, would reach alpha 0.99
(1 - (1 - A)^m = 0.99 if every surfel there were raised alike), not bounded by the model's cap.
The third axis starts at a tenth of the smaller tangent scale: thin enough to keep the surface
sharp, thick enough that a surfel seen edge-on still covers something.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..geometry.pixels import pixel_footprints
from ..geometry.sh import SH_C0
from ..render.types import LOWPASS_RHO_SCALE, Backend, RenderMode, check_render_args
from ..utils.checks import SurfSplatInputError
from ..utils.log import progress

COVERED_ALPHA = 0.05  # pixels our render covers: the fit and its figures look only at these


@dataclass(frozen=True)
class BakeConfig:
    """How `bake_for_viewers` fits; every field has the default the export uses."""

    # Defaults chosen on cost curves of `benchmarks/bake.py --grid` (two DTU photos at 288x400): 20
    # steps on the context views at x1 keep standard alpha >= 0.95 and >= 30 dB against our render
    # from the context views at x1 and x2 for about a sixth of the cost of 60 steps on six views at
    # x1 and x2 (which raise the held-out views' alpha from 0.93 to 0.96). A capture of more views
    # needs more: on a clip of 7 DTU views (487,431 fused surfels) 20 steps reached 29.2 / 28.0 dB at
    # x1 / x2, 28 steps 31.4 / 29.1, 35 steps 33.2 / 29.9 and 40 steps 33.8 / 30.1, so the steps
    # follow the views: 6 fits of each, at least 20 steps.
    steps: int | None = None  # Adam steps, one view each (None: `steps_for`; 0: only the saturated initialisation)
    fits_per_view: float = 6.0  # with steps None: steps = max(min_steps, ceil(fits_per_view x fitted views))
    min_steps: int = 20  # with steps None: the fewest steps
    lr: float = 0.03  # Adam rate of SH and log-scales; opacity logits take 4x (0.01 scored 1-2 dB lower)
    factors: tuple[int, ...] = (1,)  # resolutions (times the context views') the fit compares at
    report_factors: tuple[int, ...] = (1, 2)  # resolutions the report's figures come from
    report_views: int = 4  # context views (evenly spread) the report's figures come from
    nearby_views: int = 0  # views interpolated between consecutive context views
    jittered_views: int = 0  # jittered copies of each context view
    jitter: float = 0.03  # jitter: translation as a fraction of the scene depth, rotation in radians
    alpha_weight: float = 0.5  # weight of the alpha term beside the colour term
    nearby_weight: float = 0.25  # weight of the interpolated and jittered views' loss beside the context views'
    target_alpha: float = 0.99  # alpha the saturated initialisation aims at
    thickness: float = 0.1  # initial third scale, relative to the smaller tangent scale
    seed: int = 0  # of the jitter (the bake is deterministic)

    def __post_init__(self) -> None:
        if (self.steps is not None and self.steps < 0) or not self.lr > 0:
            raise SurfSplatInputError(f"bake: steps >= 0 and lr > 0 expected, got {self.steps}, {self.lr}")
        if not self.fits_per_view > 0 or self.min_steps < 0:
            raise SurfSplatInputError(
                f"bake: fits_per_view > 0 and min_steps >= 0 expected, got {self.fits_per_view}, {self.min_steps}"
            )
        for name in ("factors", "report_factors"):
            factors = getattr(self, name)
            if not factors or not all(int(f) == f >= 1 for f in factors):
                raise SurfSplatInputError(f"bake.{name}: expected integer factors >= 1, got {factors}")
        if self.report_views < 1:
            raise SurfSplatInputError(f"bake.report_views: expected at least 1, got {self.report_views}")
        if self.nearby_views < 0 or self.jittered_views < 0 or self.jitter < 0 or self.nearby_weight < 0:
            raise SurfSplatInputError("bake: nearby_views, jittered_views, jitter and nearby_weight expected >= 0")
        if not 0 < self.target_alpha < 1 or not self.thickness > 0 or self.alpha_weight < 0:
            raise SurfSplatInputError(
                "bake: 0 < target_alpha < 1, thickness > 0 and alpha_weight >= 0 expected, got "
                f"{self.target_alpha}, {self.thickness}, {self.alpha_weight}"
            )

    def steps_for(self, views: int) -> int:
        """Adam steps of a fit over `views` cameras: `steps` when given, else `fits_per_view` of each
        view and at least `min_steps`."""
        if self.steps is not None:
            return self.steps
        return max(self.min_steps, math.ceil(self.fits_per_view * views))


@dataclass(frozen=True)
class ViewerFigures:
    """How a standard viewer's picture compares with ours over the pixels our render covers."""

    alpha: float | None  # mean standard-compositing alpha there (None: our render covers no pixel)
    psnr: float | None  # colour PSNR (dB) of the standard composite on black against our render there (mean over views)
    covered: float  # fraction of pixels our render covers (alpha >= COVERED_ALPHA)


@dataclass
class BakeReport:
    """What `bake_for_viewers` did, from (up to `report_views` of) the context cameras at each report
    factor and over all fitted views."""

    before: dict[str, ViewerFigures]  # "context x1", "context x2", ...: the raw thin Gaussians
    after: dict[str, ViewerFigures]  # the same views, baked
    steps: int  # Adam steps run
    best_step: int  # the kept iterate (0: the saturated initialisation)
    fit_views: int  # cameras the fit compares at (each at every factor)
    seconds: float  # wall time of the bake
    losses: list[float] = field(default_factory=list)  # loss per step

    def to_dict(self) -> dict:
        return {
            "before": {k: asdict(v) for k, v in self.before.items()},
            "after": {k: asdict(v) for k, v in self.after.items()},
            "steps": self.steps,
            "best_step": self.best_step,
            "fit_views": self.fit_views,
            "seconds": self.seconds,
            "covered_alpha": COVERED_ALPHA,
            "losses": self.losses,
        }

    def summary(self) -> str:
        """One line: the context views' figures at x1, before and after."""
        key = next(iter(self.after))
        b, a = self.before[key], self.after[key]
        if b.alpha is None or a.alpha is None:
            return f"standard viewers ({key}): our render covers no pixel, nothing to compare ({self.seconds:.0f} s)"
        return (
            f"standard viewers ({key}): alpha {b.alpha:.2f} -> {a.alpha:.2f}, "
            f"PSNR {b.psnr:.1f} -> {a.psnr:.1f} dB against our render ({self.seconds:.0f} s)"
        )


def thin_gaussians(gaussians: Gaussians) -> Gaussians:
    """The surfels as 3DGS viewers read them unbaked: thin 3D Gaussians (explicit covariances)."""
    return gaussians.with_explicit_covariances(gaussians.covariances)


def viewer_figures(
    viewer: Gaussians,
    ours: Tensor,  # [C, 3, H, W] our render (on black)
    ours_alpha: Tensor,  # [C, 1, H, W] its accumulated alpha
    cameras: Cameras,
    width: int,
    height: int,
    *,
    backend: Backend = "auto",
) -> ViewerFigures:
    """Standard compositing (EWA, no normalisation, black) of `viewer` against our render `ours`."""
    from ..render import render

    with torch.no_grad():
        std = render(viewer, cameras, width, height, mode="ewa", backend=backend, alpha_threshold=None)
    return _figures(std.color, std.alpha, ours, ours_alpha)


def _figures(color: Tensor, alpha: Tensor, ours: Tensor, ours_alpha: Tensor) -> ViewerFigures:
    covered = ours_alpha >= COVERED_ALPHA  # [C, 1, H, W]
    if not bool(covered.any()):
        return ViewerFigures(alpha=None, psnr=None, covered=0.0)
    err = (color.clamp(0, 1) - ours.clamp(0, 1)).square().mean(1, keepdim=True)  # [C, 1, H, W]
    psnrs = []
    for c in range(len(err)):
        if bool(covered[c].any()):
            mse = float(err[c][covered[c]].double().mean())
            psnrs.append(-10 * math.log10(max(mse, 1e-12)))
    return ViewerFigures(
        alpha=float(alpha[covered].double().mean()),
        psnr=sum(psnrs) / len(psnrs),
        covered=float(covered.double().mean()),
    )


def fit_cameras(cameras: Cameras, config: BakeConfig, depth: float) -> Cameras:
    """The context cameras, `nearby_views` interpolated between consecutive ones, then
    `jittered_views` copies of each context camera moved by up to `jitter * depth` and turned by up
    to `jitter` radians (a seeded draw, so the bake is deterministic)."""
    from ..export.paths import interpolate_cameras
    from ..geometry.rotations import skew

    c2w, K = [cameras.c2w], [cameras.K]
    if config.nearby_views > 0:
        for i in range(len(cameras) - 1):
            between = interpolate_cameras(cameras[i : i + 2], config.nearby_views + 2)
            c2w.append(between.c2w[1:-1])
            K.append(between.K[1:-1])
    if config.jittered_views > 0 and config.jitter > 0:
        gen = torch.Generator().manual_seed(config.seed)
        n = len(cameras) * config.jittered_views
        base = cameras.c2w.repeat(config.jittered_views, 1, 1)
        # drawn on the host's generator (the same draws on every device), sent to the cameras' device once
        draws = [torch.rand(n, 3, generator=gen, dtype=torch.float64) for _ in range(2)]
        draws = torch.stack(draws).to(base.device)
        axis_angle = (draws[0] * 2 - 1) * config.jitter
        turn = torch.linalg.matrix_exp(skew(axis_angle)).to(base)
        move = (draws[1] * 2 - 1).to(base) * config.jitter * depth
        jittered = base.clone()
        jittered[:, :3, :3] = base[:, :3, :3] @ turn
        jittered[:, :3, 3] = base[:, :3, 3] + move
        c2w.append(jittered)
        K.append(cameras.K.repeat(config.jittered_views, 1, 1))
    return Cameras(torch.cat(c2w), torch.cat(K), validate=False)


def bake_for_viewers(
    gaussians: Gaussians,
    cameras: Cameras,
    height: int,
    width: int,
    config: BakeConfig = BakeConfig(),
    *,
    mode: RenderMode = "surfel",
    alpha_threshold: float | None = 0.001,
    backend: Backend = "auto",
    show_progress: bool = False,
    antialiased: bool = False,
) -> tuple[Gaussians, BakeReport]:
    """Gaussians whose standard 3DGS compositing (EWA, no normalisation, on black) reproduces our
    render of `gaussians` (see the module docstring).

    gaussians: [N] unbatched, as the model (or a compaction) returns them
    cameras:   the context cameras, K in pixels of height x width
    mode, alpha_threshold, antialiased: how we render `gaussians` (the picture to reproduce; with the
        antialiasing filter its compensations are baked into the viewer's opacities at the bake's factors,
        since standard viewers render without it)
    show_progress: a progress bar (or log lines) over the Adam steps
    Returns the baked Gaussians (explicit covariances: write them with `save_ply`, 3DGS layout) and
    a BakeReport with the figures before and after, from up to `config.report_views` context cameras
    at each of `config.report_factors`.
    """
    from ..render import render

    _validate(gaussians, cameras, height, width, mode, backend)
    start = time.perf_counter()
    g = gaussians.detach()
    cameras = cameras.to(device=g.means.device, dtype=g.means.dtype)

    def ours_of(cams: Cameras, w: int, h: int):
        with torch.no_grad():
            return render(
                g, cams, w, h, mode=mode, backend=backend, alpha_threshold=alpha_threshold, antialiased=antialiased
            )

    def plain(viewer: Gaussians, cams: Cameras, w: int, h: int):
        return render(viewer, cams, w, h, mode="ewa", backend=backend, alpha_threshold=None)

    # Our renders of every context view at the fit's factors, each made once: the fit's targets when
    # it looks at the context views alone, and the report's figures at those factors.
    ours = {f: ours_of(cameras.scaled(float(f)), width * f, height * f) for f in sorted({1, *config.factors})}
    n = len(cameras)
    # which views: a few integers, chosen on the host and sent once
    picked = torch.linspace(0, n - 1, min(n, config.report_views)).round().long().unique().to(cameras.device)
    contexts = {}
    for f in config.report_factors:
        cams = cameras[picked].scaled(float(f))
        if f in ours:
            color, alpha = ours[f].color[picked], ours[f].alpha[picked]
        else:
            out = ours_of(cams, width * f, height * f)
            color, alpha = out.color, out.alpha
        contexts[f"context x{f}"] = (cams, width * f, height * f, color, alpha)
    depth = _scene_depth(ours[1].alpha, ours[1].depth)
    probes = fit_cameras(cameras, config, depth)
    views = []
    for f in config.factors:
        cams = probes.scaled(float(f))
        out = ours[f] if len(probes) == len(cameras) and f in ours else ours_of(cams, width * f, height * f)
        covered = (out.alpha >= COVERED_ALPHA).to(out.color.dtype)
        views.append((cams, width * f, height * f, out.color * covered, covered))

    thin = thin_gaussians(g)
    before = {k: viewer_figures(thin, o, a, c, w, h, backend=backend) for k, (c, w, h, o, a) in contexts.items()}

    R, scales = _axes(g)
    logits = _saturated_logits(thin, cameras, width, height, config, backend).requires_grad_(True)
    # Tangent scales start at least at the low-pass size of their pixel footprint (as compaction's
    # floored surfels): the adapter's tangent clamp leaves many smaller than their pixel spacing,
    # which the surfel renderer's screen-space filter hides at x1 and ours normalises away, but a
    # standard viewer shows as gaps at x2.
    tangent = torch.maximum(
        scales[:, :2], pixel_footprints(g, cameras, width, height)[:, None] / math.sqrt(LOWPASS_RHO_SCALE)
    )
    third = (tangent.amin(-1, keepdim=True) * config.thickness).clamp_min(1e-12)
    log_scales = torch.cat((tangent.clamp_min(1e-12), third), dim=-1).log().requires_grad_(True)
    sh = g.sh.clone().requires_grad_(True)
    optimizer = torch.optim.Adam(
        [{"params": [sh, log_scales], "lr": config.lr}, {"params": [logits], "lr": 4 * config.lr}]
    )

    def current() -> Gaussians:
        var = (2 * log_scales).exp()
        cov = (R * var[:, None, :]) @ R.transpose(1, 2)
        return replace(
            g,
            scales=log_scales[:, :2].exp(),
            opacities=torch.sigmoid(logits),
            sh=sh,
            explicit_covariances=cov,
            validate=False,
        )

    def loss_of(viewer: Gaussians, view: int) -> Tensor:
        """The loss at probe camera `view`, at every factor."""
        total = 0
        for cams, w, h, target, covered in views:
            out = plain(viewer, cams[view], w, h)
            total = total + (out.color - target[view]).square().mean()
            total = total + config.alpha_weight * (out.alpha - covered[view]).square().mean()
        return total if view < len(cameras) else config.nearby_weight * total

    def full_loss(viewer: Gaussians) -> float:
        with torch.no_grad():
            per_view = torch.stack([loss_of(viewer, v) for v in range(len(probes))])
        return sum(per_view.tolist())  # read once, added on the host as one float per view

    # One probe camera per step, in a seeded order that visits every camera once per cycle (as 3DGS
    # trains: a step costs one view, not all). Adam keeps a step size near its rate however small
    # the gradient, so, as the compaction refit does, a better iterate is never left behind: the
    # iterate ending the cycle of lowest mean loss is scored on every camera against the
    # initialisation, and the lower of the two is returned.
    order = torch.randperm(len(probes), generator=torch.Generator().manual_seed(config.seed)).tolist()
    steps = config.steps_for(len(probes))
    initial = current().detach()
    # A step's loss stays on the device until its cycle ends, when the cycle's losses are read at
    # once: reading each step's would make the host wait for the device every step.
    best, best_cycle, best_step, losses, pending = initial, math.inf, 0, [], []
    for step in progress(range(steps), desc="bake for 3DGS viewers", unit="step", enabled=show_progress):
        loss = loss_of(current(), order[step % len(order)])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        pending.append(loss.detach())
        if len(pending) == len(order) or step == steps - 1:
            cycle = torch.stack(pending).tolist()
            losses += cycle
            pending = []
            mean = sum(cycle) / len(cycle)
            if mean < best_cycle:
                best_cycle, best_step, best = mean, step + 1, current().detach()
    if best_step > 0 and full_loss(best) >= full_loss(initial):
        best, best_step = initial, 0
    best = replace(best, validate=False)
    after = {k: viewer_figures(best, o, a, c, w, h, backend=backend) for k, (c, w, h, o, a) in contexts.items()}
    report = BakeReport(
        before=before,
        after=after,
        steps=steps,
        best_step=best_step,
        fit_views=len(probes),
        seconds=time.perf_counter() - start,
        losses=losses,
    )
    return best, report


def _validate(g: Gaussians, cameras: Cameras, height: int, width: int, mode: str, backend: str) -> None:
    check_render_args("bake", g, cameras, width, height, mode, backend)
    if len(cameras) < 1:
        raise SurfSplatInputError("bake: cameras: expected at least one camera")
    if len(g) == 0:
        raise SurfSplatInputError("bake: no Gaussians to bake")


def _axes(g: Gaussians) -> tuple[Tensor, Tensor]:
    """[N, 3, 3] rotations (columns: tangent u, v, normal) and [N, 3] scales of each Gaussian: the
    surfel's own, or, for explicit covariances, their eigenvectors and roots, largest first."""
    if g.explicit_covariances is None:
        return g.rotations, torch.cat((g.scales, torch.zeros_like(g.scales[:, :1])), dim=-1)
    evals, evecs = torch.linalg.eigh(g.explicit_covariances.double())
    return evecs.flip(-1).to(g.means.dtype), evals.flip(-1).clamp_min(0).sqrt().to(g.means.dtype)


def _scene_depth(alpha: Tensor, depth: Tensor) -> float:
    """Median rendered depth over covered pixels (the jitter's length unit); 1 when nothing is covered."""
    covered = alpha >= COVERED_ALPHA
    return float(depth[covered].median()) if bool(covered.any()) else 1.0


def _saturated_logits(
    thin: Gaussians, cameras: Cameras, width: int, height: int, config: BakeConfig, backend: Backend
) -> Tensor:
    """[N] opacity logits of the saturated start: o -> 1 - (1 - o)^m with 1 - (1 - A)^m = target,
    A the standard alpha of the pixels the Gaussian covers, averaged with its blending weights.

    The weights come from one backward pass per view, as compaction's blending weights do: with
    every colour 1 (DC = 0.5 / SH_C0), d(sum_p colour_p * x_p) / d(DC_i) = SH_C0 * sum_p w_ip x_p for
    any x held fixed; x = A gives the weighted alpha sum, x = 1 the weights' sum. The colour channels
    blend independently, so one backward gives both: the red channel weighted by A, the green by 1."""
    from ..render import render

    dc = torch.full_like(thin.sh[:, :, :1], 0.5 / SH_C0).requires_grad_(True)
    probe = replace(thin, sh=dc, validate=False)
    weighted = torch.zeros(len(thin), dtype=thin.means.dtype, device=thin.means.device)
    total = torch.zeros_like(weighted)
    with torch.enable_grad():
        for c in range(len(cameras)):
            out = render(probe, cameras[c], width, height, mode="ewa", backend=backend, alpha_threshold=None)
            alpha = out.alpha.detach()
            (grad,) = torch.autograd.grad((out.color[:, 0] * alpha[:, 0]).sum() + out.color[:, 1].sum(), dc)
            weighted += grad[:, 0, 0] / SH_C0
            total += grad[:, 1, 0] / SH_C0
    seen = total > 1e-8
    pixel_alpha = torch.where(seen, weighted / total.clamp_min(1e-12), torch.zeros_like(total)).clamp(1e-3, 1 - 1e-6)
    power = math.log(1 - config.target_alpha) / torch.log1p(-pixel_alpha)  # m >= 1 where A < target
    o = thin.opacities.detach().clamp(1e-6, 1 - 1e-6)
    raised = -torch.expm1(power.clamp_min(1.0) * torch.log1p(-o))  # 1 - (1 - o)^m
    raised = torch.where(seen, raised, o).clamp(1e-4, config.target_alpha)
    return torch.logit(raised)
