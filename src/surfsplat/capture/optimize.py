"""Per-scene optimization: every surfel attribute fitted to the context photos, from the network's start.

    optimized, stats = optimize_on_views(fused, context_cameras, context_images, width, height, OptimizeConfig())

Why: the refinement (`refine.py`) keeps the network's positions and orientations, so a surface the
network put a little off, or tilted, stays so, and views between the context views show it. This
is the per-scene fit of 3DGS / 2DGS, started from the network's surfels instead of a sparse point
cloud: Adam over positions, rotations (quaternions), tangent scales (logarithms), opacities
(logits) and SH (DC and higher degrees apart), with the rates 3DGS and 2DGS use, their loss
((1 - 0.2) L1 + 0.2 D-SSIM) and 2DGS's depth-normal consistency term, the SH degree raised during
the fit, and the surfels whose opacity falls below 0.005 pruned a few times. The loop is the
refinement's (`fit.fit_on_views`): only the plan differs.

Rates (3DGS `arguments/__init__.py` OptimizationParams, the same in 2DGS): position 1.6e-4 times
the scene extent, decayed exponentially to 1.6e-6 times it; SH DC 2.5e-3, higher degrees 2.5e-3 / 20;
opacity 0.05; scaling 5e-3; rotation 1e-3. The scene extent is 3DGS's: 1.1 times the largest
distance of a context camera from their mean centre. 3DGS runs 30,000 steps of one view; a CPU
affords hundreds, so the schedules scale to the steps run: the SH degree is raised every 1/30 of
them (3DGS: every 1,000 of 30,000), the depth-normal term joins after 7/30 (2DGS: step 7,000).

Not here: 2DGS's depth-distortion term (every backend renders it, `render(..., distortion=True)`,
but the fit does not use it yet); densification (cloning and splitting) is left
out, the network's one surfel per pixel being denser than 3DGS ends with; the cameras stay fixed
(only the torch backend differentiates them, at several times the compiled backend's cost).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..utils.checks import SurfSplatInputError
from .fit import FitPlan, fit_on_views

SAVED_STEPS = 100  # `surfsplat optimize`'s steps: asked for explicitly, it runs by default (see OptimizeConfig.steps)

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

    The defaults come from `benchmarks/optimize.py` (docs/optimize.md has its curves): see `steps`.
    """

    # Off by default, from `benchmarks/optimize.py` (docs/optimize.json; 2 shared CPU cores, tiny-synthetic):
    # at equal or slightly better held-out PSNR it costs more than the refinement it replaces. Fern at
    # 176x240 (17 views): refinement 16.70 dB, 100 steps 16.74 dB (SSIM 0.279 -> 0.348); DTU scan 24 at
    # 144x192 (6 views): 10.05 -> 10.70 dB in about 3x the refinement's time; the rooms at 64x64:
    # 25.63 -> 25.33 dB, but depth AbsRel 0.160 -> 0.138 and median normal error 23.1 -> 18.9 degrees.
    # `surfsplat optimize` runs SAVED_STEPS when asked for.
    steps: int = 0  # Adam steps (0: no optimization)
    # views a step (not measured against 1 or 4 here: 3DGS draws 1, two average each step's gradient over two
    # viewpoints); the full working size, since half of it scored lower (fern 16.61 vs 16.74 dB, DTU 9.93 vs 10.70)
    views_per_step: int = 2  # context views rendered in one step (3DGS: 1)
    scale: float = 1.0  # the fit renders at this fraction of the working size (photos area-averaged)
    parameters: tuple[str, ...] = ("means", "quats", "scales", "opacities", "sh")  # what is fitted
    means_lr: float = 1.6e-4  # position rate at the first step, times the scene extent (3DGS)
    means_lr_final: float = 1.6e-6  # ... decayed exponentially to this at the last step (3DGS)
    quats_lr: float = 1e-3  # rotation (3DGS, 2DGS)
    scales_lr: float = 5e-3  # log tangent scales (3DGS, 2DGS)
    opacities_lr: float = 0.05  # opacity logits (3DGS, 2DGS)
    sh_lr: float = 2.5e-3  # SH DC; the higher degrees at sh_lr / 20 (3DGS)
    # 5: 3DGS's rates are made for 30,000 steps; in 100 the fit barely leaves the network's start (DTU
    # scan 24 held out: 9.84 dB at 1x, 10.70 dB at 5x; fern at 176x240: 15.89 dB at 1x, 16.32 dB at 5x in 50 steps)
    lr_scale: float = 5.0  # every rate above times this
    ssim_weight: float = 0.2  # loss (1 - w) L1 + w D-SSIM (3DGS's lambda_dssim)
    # 2DGS's 0.05 kept: it is what straightens the surface (rooms: median normal error 18.9 degrees with
    # it, 21.4 without) at a held-out PSNR cost (fern -0.14 dB, DTU -0.62 dB, rooms -0.06 dB at 100 steps)
    normal_weight: float = 0.05  # 2DGS's depth-normal consistency (0: off)
    normal_from: float = 7 / 30  # ... from this share of the steps on (2DGS: step 7,000 of 30,000)
    sh_degree_share: float | None = 1 / 30  # the SH degree rises from 0 every this share of the steps (None: all)
    prunings: int = 3  # times the faint surfels are pruned, evenly over the fit (0: never)
    prune_opacity: float = 0.005  # ... those below this opacity (3DGS's min_opacity)
    seed: int = 0  # which views each step renders

    def __post_init__(self) -> None:
        if isinstance(self.steps, bool) or not isinstance(self.steps, int) or self.steps < 0:
            raise SurfSplatInputError(
                f"optimize.steps (--optimize-steps): expected an integer >= 0, got {self.steps!r}"
            )
        if self.views_per_step < 1:
            raise SurfSplatInputError(f"optimize.views_per_step: expected at least 1, got {self.views_per_step}")
        if not (math.isfinite(self.scale) and 0 < self.scale <= 1):
            raise SurfSplatInputError(
                f"optimize.scale (--optimize-scale): expected a fraction in (0, 1], got {self.scale}"
            )
        unknown = [p for p in self.parameters if p not in PARAMETERS]
        if unknown or not self.parameters:
            raise SurfSplatInputError(
                f"optimize.parameters: expected some of {sorted(PARAMETERS)}, got {list(self.parameters)}"
            )
        for name in ("means_lr", "means_lr_final", "quats_lr", "scales_lr", "opacities_lr", "sh_lr", "lr_scale"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise SurfSplatInputError(f"optimize.{name}: expected a positive rate, got {value}")
        for name in ("ssim_weight", "normal_from"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 <= value <= 1):
                raise SurfSplatInputError(f"optimize.{name}: expected a share in [0, 1], got {value}")
        if not (math.isfinite(self.normal_weight) and self.normal_weight >= 0):
            raise SurfSplatInputError(f"optimize.normal_weight: expected >= 0, got {self.normal_weight}")
        if self.sh_degree_share is not None and not (0 < self.sh_degree_share <= 1):
            raise SurfSplatInputError(
                f"optimize.sh_degree_share: expected a share in (0, 1] or None, got {self.sh_degree_share}"
            )
        if self.prunings < 0:
            raise SurfSplatInputError(f"optimize.prunings: expected >= 0, got {self.prunings}")
        if not 0 <= self.prune_opacity < 1:
            raise SurfSplatInputError(
                f"optimize.prune_opacity: expected an opacity in [0, 1), got {self.prune_opacity}"
            )

    def plan(self, extent: float) -> FitPlan:
        """The shared loop's plan for a scene of `extent` (3DGS's camera extent, scaling the position rate)."""
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
        every = None
        if self.sh_degree_share is not None and "sh" in self.parameters:
            every = max(1, round(self.sh_degree_share * self.steps))
        return FitPlan(
            name="optimize",
            steps=self.steps,
            rates=rates,
            views_per_step=self.views_per_step,
            seed=self.seed,
            scale=self.scale,
            loss="l1_dssim",
            ssim_weight=self.ssim_weight,
            normal_weight=self.normal_weight,
            normal_from=self.normal_from,
            means_final_rate=self.means_lr_final * extent * self.lr_scale if "means" in fitted else None,
            sh_degree_every=every,
            prune_every=self.steps // (self.prunings + 1) if self.prunings and "opacities" in self.parameters else None,
            prune_opacity=self.prune_opacity,
        )


def scene_extent(cameras: Cameras) -> float:
    """3DGS's scene extent (`getNerfppNorm`): 1.1 times the largest distance of a camera centre from
    their mean; 1 for a single camera."""
    centers = cameras.centers
    radius = float((centers - centers.mean(0)).norm(dim=-1).max()) * 1.1
    return radius if radius > 0 else 1.0


def optimize_on_views(
    gaussians: Gaussians,  # [N] unbatched
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
) -> tuple[Gaussians, dict[str, float]]:
    """The surfels optimized on the photos and the fit's figures: those of the refinement
    (`fit.fit_on_views`) and "surfels_before", "surfels_after" (faint ones pruned), "extent".
    `backend`: the renderer ("auto": the one `render` picks for the surfels' device)."""
    config = config or OptimizeConfig()
    extent = scene_extent(cameras)
    fitted, stats = fit_on_views(
        gaussians,
        cameras,
        images,
        width,
        height,
        config.plan(extent),
        mode=mode,
        alpha_threshold=alpha_threshold,
        backend=backend,
        progress=progress,
    )
    stats.update({"surfels_before": len(gaussians), "surfels_after": len(fitted), "extent": extent})
    return fitted, stats


def optimize_summary(stats: dict[str, float]) -> str:
    """One line for the reconstruct summary and the capture report, from `optimize_on_views`'s figures."""
    before, after = (-10 * math.log10(max(stats[k], 1e-12)) for k in ("mse_before", "mse_after"))
    line = (
        f"optimized on the context views: {int(stats['steps'])} steps at {int(stats['width'])}x{int(stats['height'])}"
        f" in {stats['seconds']:.1f} s, colour PSNR there {before:.2f} -> {after:.2f} dB, "
        f"{int(stats['surfels_before']):,} -> {int(stats['surfels_after']):,} surfels"
    )
    return line + ("" if stats["kept"] else " (not kept: the fit made it worse)")
