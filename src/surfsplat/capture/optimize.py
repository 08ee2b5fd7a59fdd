"""The per-scene optimizer: a scene fitted to its context photos from a start, grown and pruned, coarse to fine.

    optimized, stats = optimize_on_views(fused, context_cameras, context_images, width, height, OptimizeConfig())

The 3DGS / 2DGS per-scene fit, as one plan of the loop the refinement also runs (`fit.fit_on_views`).
Its parts are modules of their own beside that loop, each named for what it is:

* the start (`starts.py`): COLMAP's points triangulated from the context photos with the cameras held
  fixed (3DGS's start), the network's fused surfels thinned to a budget, or both; "auto" takes the
  points and falls back to the network's surfels where COLMAP finds too few; "continue" takes the
  given surfels as they are (a saved fit continued);
* densification, a strategy chosen by name (`strategy`, `STRATEGIES`): "3dgs" (`densify.py`), 3DGS's
  clone / split by the screen-space gradient, pruning by opacity and size, opacity resets, under a
  surfel budget; "absgs", the same with AbsGS's absolute screen gradient; "mcmc" (`mcmc.py`),
  3DGS-MCMC's relocation of dead surfels under a fixed budget, position noise and its regularizers;
* the losses (`losses.py`): (1 - 0.2) L1 + 0.2 D-SSIM, 2DGS's depth-normal consistency and its depth
  distortion;
* the schedule (`fit.progress_of` and the plan's shares): every schedule follows the fit's progress,
  the share of its steps or of a time budget (`seconds`): coarse to fine (a quarter, then half the
  working size for the first tenths), the position rate's exponential decay, the SH degree's rise,
  when densification runs and when the terms join. One view a step, as 3DGS.

Rates (3DGS `arguments/__init__.py` OptimizationParams, the same in 2DGS): position 1.6e-4 times the
scene extent, decayed exponentially to 1.6e-6 times it over the fit; SH DC 2.5e-3, higher degrees
2.5e-3 / 20; opacity 0.05; scaling 5e-3; rotation 1e-3. The scene extent is 3DGS's: 1.1 times the
largest distance of a context camera from their mean centre.

The cameras stay fixed (only the torch backend differentiates them, at several times the compiled
backend's cost).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Literal

from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..utils.checks import SurfSplatInputError
from .densify import DensifyConfig
from .fit import FitPlan, fit_on_views
from .mcmc import MCMCConfig
from .per_view import PerViewConfig
from .starts import StartChoice, StartConfig, make_start

NETWORK_NORMAL_WEIGHT = 0.05  # the depth-normal term's weight from the network's surfels (2DGS's)
# The fit's length where none is given: one step per VIEW_PIXELS_PER_STEP pixels of the context views
# (their number times the working size's pixels), between MIN_STEPS and MAX_STEPS (`steps_for`;
# the curves it comes from are in docs/optimize.md, "The budget").
VIEW_PIXELS_PER_STEP = 768
MIN_STEPS = 1000
MAX_STEPS = 3000

Strategy = Literal["auto", "3dgs", "absgs", "mcmc"]
# OptimizeConfig.strategy -> the plan's densification, from the configuration's `densify` and `mcmc`;
# "auto" is absgs where the renderer gives the absolute screen gradient (torch, cpu), 3dgs on gsplat,
# whose 2DGS kernel cannot (`optimize_on_views` decides, knowing the backend)
STRATEGIES = {
    "auto": lambda config: replace(config.densify, absgrad=True),
    "3dgs": lambda config: config.densify,
    "absgs": lambda config: replace(config.densify, absgrad=True),
    "mcmc": lambda config: config.mcmc,
}

# OptimizeConfig.parameters names -> the fit's tensors (`fit.TENSORS`)
PARAMETERS = {
    "means": ("means",),
    "quats": ("quats",),
    "scales": ("log_scales",),
    "opacities": ("logits",),
    "sh": ("sh_dc", "sh_rest"),
}


@dataclass(frozen=True)
class OptimizeConfig:
    """How a scene is optimized on its context photos (steps 0: not at all).

    The defaults come from `benchmarks/optimize.py` (docs/optimize.md has its curves).
    """

    # Adam steps at most (0: no optimization; None: `steps_for` the context views and their pixels where
    # there are more than two context views, none for two, whose pass the network alone makes best)
    steps: int | None = None
    seconds: float | None = None  # a time budget: the fit runs this long (at most `steps`), its schedules follow it
    start: StartConfig = field(default_factory=StartConfig)  # the network's surfels, SfM points, or both
    # None: the surfels neither grow nor go (the fit of the network's start alone)
    densify: DensifyConfig | None = field(default_factory=DensifyConfig)
    # how the surfels grow (`STRATEGIES`): 3DGS's densification, AbsGS's (3DGS's with the absolute screen
    # gradient), or 3DGS-MCMC's relocation (`mcmc`). "auto": absgs, from the curves (docs/optimize.md: at
    # 3,000 steps on fern 24.62 dB held out against 3dgs 24.52 and mcmc, relocation every 10 steps, 24.18),
    # and 3dgs on the gsplat backend, which cannot give surfels' absolute screen gradient
    strategy: Strategy = "auto"
    mcmc: MCMCConfig = field(default_factory=MCMCConfig)  # the "mcmc" strategy's schedule and constants
    views_per_step: int = 1  # context views rendered in one step (3DGS: 1)
    scale: float = 1.0  # the fit renders at this fraction of the working size (photos area-averaged)
    # coarse to fine: until 10 % of the fit at a quarter of the size, until 20 % at half
    # (OpenSplat's --num-downscales 2 --resolution-schedule 200 of 2,000 steps)
    levels: tuple[tuple[float, float], ...] = ((0.1, 0.25), (0.2, 0.5))
    parameters: tuple[str, ...] = ("means", "quats", "scales", "opacities", "sh")  # what is fitted
    means_lr: float = 1.6e-4  # position rate at the first step, times the scene extent (3DGS)
    means_lr_final: float = 1.6e-6  # ... decayed exponentially to this at the end (3DGS)
    quats_lr: float = 1e-3  # rotation (3DGS, 2DGS)
    scales_lr: float = 5e-3  # log tangent scales (3DGS, 2DGS)
    opacities_lr: float = 0.05  # opacity logits (3DGS, 2DGS)
    sh_lr: float = 2.5e-3  # SH DC; the higher degrees at sh_lr / 20 (3DGS)
    # every rate above times this: 3DGS's rates are made for 30,000 steps, and a fit of 1,000 to 3,000 climbs
    # faster at three times them (held out: fern 24.78 -> 25.45 dB, DTU scan 24 seeds 0 and 1 +1.7 and +0.8 dB;
    # 2x and 4x: fern 25.22 and 25.38; docs/optimize.md)
    lr_scale: float = 3.0
    ssim_weight: float = 0.2  # loss (1 - w) L1 + w D-SSIM (3DGS's lambda_dssim)
    # 2DGS's depth-normal consistency (0: off), or "auto": 2DGS's 0.05 from the network's surfels, whose
    # surfaces it keeps straight (2 rooms, 3,000 steps without it: median normal error 20.1 -> 24.0
    # degrees), none from COLMAP's points, where it costs colour and there is no surface to keep yet
    normal_weight: float | Literal["auto"] = "auto"
    normal_from: float = 7 / 30  # ... from this share of the fit on (2DGS: step 7,000 of 30,000)
    # 2DGS's depth distortion as gsplat defines it (|z_i - z_j| of centre depths; its trainer's weight 0.01)
    distortion_weight: float = 0.0  # (0: off)
    distortion_from: float = 0.1  # ... from this share of the fit on (2DGS, gsplat: step 3,000 of 30,000)
    # the SH degree rises from 0 every this share of the fit (3DGS: 1,000 of 30,000 steps; OpenSplat: 1,000 of
    # 2,000): 0.1 reaches degree 3 at 30 % of the fit (0.5, OpenSplat's, reached degree 1 only; fern 24.59 against
    # 24.52 dB held out at 3,000 steps)
    sh_degree_share: float | None = 0.1
    sh_degree: int = 3  # the fitted surfels' SH degree (a start of another degree is padded or cut)
    prunings: int = 0  # times faint surfels are pruned, evenly over the fit, besides the densification's (0: never)
    prune_opacity: float = 0.005  # ... those below this opacity (3DGS's min_opacity)
    seed: int = 0  # which views each step renders, the splits' samples
    # "selective": each step's Adam updates only the surfels its view saw (Taming 3DGS, gsplat's
    # SelectiveAdam; `adam.py`); "dense", torch's fused Adam: a 300-step fern fit took 1.16x its seconds
    # with "selective" for 0.07 dB less held out (docs/optimize.md)
    adam: Literal["dense", "selective"] = "dense"
    # forced alpha blending of the fitted scene (SurfSplat's tau_alpha), None for plain 2DGS compositing,
    # or "auto": plain from COLMAP's points, as the per-scene methods fit (fern at 184x248, 1,000 steps:
    # held out 23.69 dB plain, 22.86 dB with tau_alpha 0.001), and the network's own from its surfels,
    # whose opacities it made for it (a room: 27.2 dB before, 26.1 dB after 30 steps fitted plain).
    # The fit renders with it and the optimized scene keeps it.
    alpha_threshold: float | None | Literal["auto"] = "auto"
    # per-photo terms fitted beside the surfels (capture/per_view.py): an affine exposure map per photo
    # (3DGS's exposure; held-out views then scored by its train_test_exp protocol), and a rigid
    # correction per context camera, "auto": where the cameras were estimated from the photos (given
    # calibrations are trusted), the held-out cameras then aligned to their photos before scoring
    appearance: bool = False
    refine_cameras: bool | Literal["auto"] = False
    per_view: PerViewConfig = field(default_factory=PerViewConfig)  # their rates and gauge
    # the fit renders with the antialiasing filter (`render(..., antialiased=True)`), and the optimized
    # scene keeps it: every later render of it (renders, videos, the viewer, HRRC) uses it too
    antialiased: bool = False

    def __post_init__(self) -> None:
        if self.steps is not None and (
            isinstance(self.steps, bool) or not isinstance(self.steps, int) or self.steps < 0
        ):
            raise SurfSplatInputError(
                f"optimize.steps (--optimize-steps): expected an integer >= 0, got {self.steps!r}"
            )
        if self.seconds is not None and not (math.isfinite(self.seconds) and self.seconds > 0):
            raise SurfSplatInputError(
                f"optimize.seconds (--optimize-seconds): expected a positive number of seconds, got {self.seconds}"
            )
        if self.views_per_step < 1:
            raise SurfSplatInputError(f"optimize.views_per_step: expected at least 1, got {self.views_per_step}")
        if not (math.isfinite(self.scale) and 0 < self.scale <= 1):
            raise SurfSplatInputError(
                f"optimize.scale (--optimize-scale): expected a fraction in (0, 1], got {self.scale}"
            )
        shares = [share for share, _ in self.levels]
        if shares != sorted(shares) or any(not (0 < a <= 1 and 0 < b <= 1) for a, b in self.levels):
            raise SurfSplatInputError(
                f"optimize.levels: expected (share, scale) pairs in (0, 1] with rising shares, got {self.levels}"
            )
        unknown = [p for p in self.parameters if p not in PARAMETERS]
        if unknown or not self.parameters:
            raise SurfSplatInputError(
                f"optimize.parameters: expected some of {sorted(PARAMETERS)}, got {list(self.parameters)}"
            )
        if self.strategy not in STRATEGIES:
            raise SurfSplatInputError(
                f"optimize.strategy (--optimize-strategy): expected one of {sorted(STRATEGIES)}, got {self.strategy!r}"
            )
        if self.densify is not None and set(self.parameters) != set(PARAMETERS):
            raise SurfSplatInputError("optimize.densify: densification needs every parameter fitted")
        for name in ("means_lr", "means_lr_final", "quats_lr", "scales_lr", "opacities_lr", "sh_lr", "lr_scale"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise SurfSplatInputError(f"optimize.{name}: expected a positive rate, got {value}")
        for name in ("ssim_weight", "normal_from", "distortion_from"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 <= value <= 1):
                raise SurfSplatInputError(f"optimize.{name}: expected a share in [0, 1], got {value}")
        for name in ("normal_weight", "distortion_weight"):
            value = getattr(self, name)
            if value == "auto" and name == "normal_weight":
                continue
            if not (math.isfinite(value) and value >= 0):
                raise SurfSplatInputError(f"optimize.{name}: expected >= 0, got {value}")
        if self.sh_degree_share is not None and not (0 < self.sh_degree_share <= 1):
            raise SurfSplatInputError(
                f"optimize.sh_degree_share: expected a share in (0, 1] or None, got {self.sh_degree_share}"
            )
        if self.sh_degree not in (0, 1, 2, 3):
            raise SurfSplatInputError(f"optimize.sh_degree: expected 0 to 3, got {self.sh_degree}")
        if self.alpha_threshold not in (None, "auto") and not 0 < self.alpha_threshold <= 1:
            raise SurfSplatInputError(
                f"optimize.alpha_threshold: expected a threshold in (0, 1] or None, got {self.alpha_threshold}"
            )
        if self.adam not in ("dense", "selective"):
            raise SurfSplatInputError(f"optimize.adam: expected 'dense' or 'selective', got {self.adam!r}")
        if not isinstance(self.antialiased, bool):
            raise SurfSplatInputError(
                f"optimize.antialiased (--optimize-antialiased): expected True or False, got {self.antialiased!r}"
            )
        if self.prunings < 0:
            raise SurfSplatInputError(f"optimize.prunings: expected >= 0, got {self.prunings}")
        if not 0 <= self.prune_opacity < 1:
            raise SurfSplatInputError(
                f"optimize.prune_opacity: expected an opacity in [0, 1), got {self.prune_opacity}"
            )

    def runs_for(self, views: int) -> bool:
        """Whether a fit of `views` context views runs at all (`steps_for` is positive, whatever the pixels)."""
        return self.steps != 0 if self.steps is not None else views > 2

    def per_view_for(self, estimated_cameras: bool) -> PerViewConfig | None:
        """The per-photo terms of a fit whose cameras were (or were not) estimated from the photos."""
        cameras = estimated_cameras if self.refine_cameras == "auto" else bool(self.refine_cameras)
        if not (self.appearance or cameras):
            return None
        return replace(self.per_view, appearance=self.appearance, cameras=cameras)

    def steps_for(self, views: int, pixels: int) -> int:
        """The steps the fit of `views` context views of `pixels` pixels each runs at most (0: none):
        `steps` where given; else with a time budget a bound it never reaches, and without one, for
        three views or more, one step per VIEW_PIXELS_PER_STEP of their pixels (views x pixels / 768),
        between MIN_STEPS and MAX_STEPS: LLFF fern's 17 views at 368x496 -> 3,000 (the ceiling), DTU
        scan 24's 10 views at 288x400 -> 1,500, a 7-view clip at 288x400 -> 1,050.

        From the held-out curves of `benchmarks/optimize.py` (docs/optimize.md, "The budget"): fern
        still gained 0.3 dB held out from step 2,100 to 3,000 of its fit (24.09 -> 24.39 dB), so it
        keeps 3,000; DTU scan 24 scored 19.57 / 20.20 / 20.54 dB at 1,000 / 1,500 / 2,000 steps
        (fits of 31, 31 and 52 s on a busy machine) against 19.27 dB (the benchmark's run) and 20.25 to
        21.87 dB (four seeds end to end) at 3,000 (fits of 267 s alone): 1,500 is inside that spread
        at an eighth of the time; 1,000 (the floor) is 0.6 dB below 1,500. Below the floor the
        densification (a quarter to half of the fit, every 100 steps then) had fewer than three rounds."""
        if self.steps is not None or not self.runs_for(views):
            return self.steps or 0
        if self.seconds is not None:
            return 1_000_000
        return min(MAX_STEPS, max(MIN_STEPS, round(views * pixels / VIEW_PIXELS_PER_STEP)))

    def plan(self, extent: float, views: int, pixels: int) -> FitPlan:
        """The shared loop's plan for a scene of `extent` (3DGS's camera extent, scaling the position rate)
        fitted to `views` context views of `pixels` pixels each."""
        base = {
            "means": self.means_lr * extent,
            "quats": self.quats_lr,
            "log_scales": self.scales_lr,
            "logits": self.opacities_lr,
            "sh_dc": self.sh_lr,
            "sh_rest": self.sh_lr / 20,
        }
        fitted = {t for p in self.parameters for t in PARAMETERS[p]}
        rates = {k: r * self.lr_scale for k, r in base.items() if k in fitted}
        steps = self.steps_for(views, pixels)
        return FitPlan(
            name="optimize",
            steps=steps,
            rates=rates,
            views_per_step=self.views_per_step,
            seed=self.seed,
            scale=self.scale,
            loss="l1_dssim",
            ssim_weight=self.ssim_weight,
            normal_weight=0.0 if self.normal_weight == "auto" else self.normal_weight,
            normal_from=self.normal_from,
            distortion_weight=self.distortion_weight,
            distortion_from=self.distortion_from,
            means_final_rate=self.means_lr_final * extent * self.lr_scale if "means" in fitted else None,
            sh_degree_share=self.sh_degree_share if "sh" in self.parameters else None,
            prune_every=steps // (self.prunings + 1) if self.prunings and "opacities" in self.parameters else None,
            prune_opacity=self.prune_opacity,
            levels=self.levels,
            densify=None if self.densify is None else STRATEGIES[self.strategy](self),
            extent=extent,
            seconds=self.seconds,
            adam=self.adam,
            antialiased=self.antialiased,
        )


def scene_extent(cameras: Cameras) -> float:
    """3DGS's scene extent (`getNerfppNorm`): 1.1 times the largest distance of a camera centre from
    their mean; 1 for a single camera."""
    centers = cameras.centers
    radius = float((centers - centers.mean(0)).norm(dim=-1).max()) * 1.1
    return radius if radius > 0 else 1.0


def optimize_on_views(
    gaussians: Gaussians | None,  # [N] unbatched: the network's surfels or a saved fit's (None: none, for points)
    cameras: Cameras,  # [V] the context views, K in pixels of height x width
    images: Tensor,  # [V, 3, H, W] in [0, 1]
    width: int,
    height: int,
    config: OptimizeConfig | None = None,
    *,
    mode: str = "surfel",
    alpha_threshold: float | None = 0.001,
    backend: str = "auto",
    progress: bool = False,
    monitor=None,
    choice: StartChoice | None = None,
    estimated_cameras: bool = False,
    per_view_out: dict | None = None,
) -> tuple[Gaussians, dict[str, float]]:
    """The surfels optimized on the photos and the fit's figures: those of the loop
    (`fit.fit_on_views`), the start's (`starts.make_start`: "start", "start_surfels", "points") and
    "surfels_before" (the given ones), "surfels_after", "extent".
    `alpha_threshold`: the given surfels' forced-alpha threshold. The fit renders with the one
    `config.alpha_threshold` names, returned as stats["alpha_threshold"]: whatever renders the result
    should use it.
    `backend`: the renderer ("auto": the one `render` picks for the surfels' device); `monitor`: see
    `fit.fit_on_views` (held-out scores along the fit); `choice`: the start decided already
    (`starts.choose_start`, as `reconstruct` does before the network's passes).

    A start of "continue" goes on where a fit stopped: the given surfels as they are, at the full size
    from the first step, the position rate at its final value throughout (3DGS's schedule past its end)
    and no densification (the saved fit grew them); the forced-alpha threshold and the depth-normal
    term are the given surfels' (`alpha_threshold`, and 2DGS's term where they render with one: the
    network's, as from its start).
    `estimated_cameras`: the cameras came from the photos (`config.refine_cameras` "auto" then refines
    them); `per_view_out`: see `fit.fit_on_views`."""
    config = config or OptimizeConfig()
    extent = scene_extent(cameras)
    start, start_figures = make_start(config.start, gaussians, images, cameras, config.sh_degree, choice)
    threshold = config.alpha_threshold
    kind = start_figures["start"]
    keeps_threshold = kind == "network" or (kind == "continue" and alpha_threshold is not None)
    if threshold == "auto":
        threshold = alpha_threshold if kind in ("network", "continue") else None
    plan = replace(config.plan(extent, len(cameras), width * height), per_view=config.per_view_for(estimated_cameras))
    strategy = config.strategy
    if strategy == "auto":
        from ..render import resolve_backend

        gsplat = resolve_backend(backend, start.means.device, None, cameras) == "gsplat"
        strategy = "3dgs" if gsplat else "absgs"
        plan = replace(plan, densify=None if config.densify is None else STRATEGIES[strategy](config))
    if config.normal_weight == "auto" and keeps_threshold:
        plan = replace(plan, normal_weight=NETWORK_NORMAL_WEIGHT)
    if kind == "continue":
        final = plan.means_final_rate
        rates = {**plan.rates, "means": final} if final is not None and "means" in plan.rates else plan.rates
        plan = replace(plan, rates=rates, means_final_rate=None, levels=(), densify=None)
    fitted, stats = fit_on_views(
        start,
        cameras,
        images,
        width,
        height,
        plan,
        mode=mode,
        alpha_threshold=threshold,
        backend=backend,
        progress=progress,
        monitor=monitor,
        per_view_out=per_view_out,
    )
    stats["alpha_threshold"] = threshold
    stats["strategy"] = strategy if plan.densify is not None else None
    stats["antialiased"] = plan.antialiased
    stats["normal_weight"] = plan.normal_weight
    if not stats["kept"] and gaussians is not None:  # the fit raised its error: the given surfels stay
        fitted, stats["alpha_threshold"], stats["antialiased"] = gaussians, alpha_threshold, False
    stats.update(start_figures)
    stats.update(
        {
            "surfels_before": len(gaussians) if gaussians is not None else 0,
            "surfels_after": len(fitted),
            "extent": extent,
        }
    )
    return fitted, stats


def optimize_summary(stats: dict) -> str:
    """One line for the reconstruct summary and the capture report, from `optimize_on_views`'s figures."""
    before, after = (-10 * math.log10(max(stats[k], 1e-12)) for k in ("mse_before", "mse_after"))
    start = stats.get("start", "network")
    origin = {
        "points": f"{int(stats.get('points', 0)):,} COLMAP points",
        "network": "the network's surfels",
        "both": f"{int(stats.get('points', 0)):,} COLMAP points and the network's surfels",
        "continue": "the saved surfels (continued)",
    }.get(start, start)
    if stats.get("start_reason"):
        origin += f" ({stats['start_reason']})"
    line = (
        f"optimized on the context views from {origin}: {int(stats['steps'])} steps at "
        f"{int(stats['width'])}x{int(stats['height'])} in {stats['seconds']:.1f} s, colour PSNR there "
        f"{before:.2f} -> {after:.2f} dB, {int(stats.get('start_surfels', stats['surfels_before'])):,} -> "
        f"{int(stats['surfels_after']):,} surfels"
    )
    return line + ("" if stats["kept"] else " (not kept: the fit made it worse)")
