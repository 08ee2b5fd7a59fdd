"""Refine a fused scene on its own context photos: colours, opacities and tangent sizes fitted.

    scene_gaussians, stats = refine_on_views(fused, context_cameras, context_images, width, height)

Why: fusion keeps, for each surface, the surfels of one pass (the first that saw it, or a much
closer view's). Their colours, opacities and sizes were predicted for that pass's two or three
views and blend with the neighbouring passes' surfels in ways no single pass saw. A frame between
the context views then looks worse than the two-view reconstruction from the path's ends, even
with every surfel moved onto the true surface (measured in the README, "Many views"). A short fit
on the context photos, the views the passes were given and never a held-out one, makes the fused
surfels agree with all of them at once.

What is fitted: the SH coefficients, the opacities (as logits) and the two tangent scales (as
logarithms; a surfel's zero thickness stays), with Adam, the opacity logits at 4x the rate, as in
the compaction's refit (`compaction.refit`). Positions and orientations stay the network's, so the
surface is the one predicted (`optimize.py` frees them too, in the same loop: `fit.fit_on_views`). Loss: the mean squared colour error of the renders (forced alpha
blending, as the reconstruction renders) against the photos. A step renders at most
`views_per_step` context views, drawn by a seeded generator without replacement, so the result is
the same on every run.

What it costs: by default the steps follow the context views, so that each view is fitted
`fits_per_view` times (a capture of V views renders about 22 V views in all; `steps` sets them
instead). The fit renders at `scale` of the working size (the photos area-averaged to it), a
quarter of the pixels at 0.5, and stops early once the loss of a window of `patience` steps has
fallen by less than `min_improvement` of the previous window's (off by default). The defaults were
chosen on the held-out PSNR against time curve of `benchmarks/capture.py --parts refine-rooms
refine`. The colour error before and after is measured on every view at the full working size; a
fit that raised it is not kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..utils.checks import SurfSplatInputError
from .fit import FitPlan, _stalled, fit_on_views

__all__ = ["RefineConfig", "_stalled", "refine_on_views", "refine_summary"]


@dataclass(frozen=True)
class RefineConfig:
    """How a fused scene is refined on its context photos (no steps: not at all)."""

    # Defaults chosen on `benchmarks/capture.py --parts refine-rooms refine` against the refinement
    # first shipped (100 steps of 16 views at rate 0.01), each in one run. The steps follow the
    # number of context views, so that each view is fitted about 22 times: on the 64x64 rooms (18
    # views) 50 steps of 8 views keep the held-out PSNR within 0.17 dB in 0.245 of the time (50 of 6:
    # -0.21 dB; 25 of 6: -0.56 dB; the fit keeps gaining up to 100 steps of 16); on DTU scan 24
    # (7 views at 288x400) the same 22 fits per view are 22 steps of all 7 views: -0.08 dB in 0.19 of
    # the time (25 of 6: -0.01 dB in 0.22; 25 of 4: +0.06 dB). Rendering the fit at half size lost
    # the refinement's gain altogether at 64 px and about half of it on DTU; a cosine decay of the
    # rate scored no better than a constant one.
    steps: int | None = None  # Adam steps at most (None: as many as `fits_per_view` asks for)
    fits_per_view: float = 22.0  # with steps None: steps = ceil(fits x views / views rendered a step)
    lr: float = 0.02  # rate of the SH coefficients and log scales; opacity logits at 4x
    views_per_step: int = 8  # context views rendered in one step (all of them when fewer)
    seed: int = 0  # which views each step renders
    scale: float = 1.0  # the fit's renders at this fraction of the working size (photos area-averaged)
    patience: int | None = None  # steps per window of the early stop (None: every step runs)
    min_improvement: float = 0.01  # stop when a window's mean loss fell by less than this share

    def __post_init__(self) -> None:
        if self.steps is not None and self.steps < 0:
            raise SurfSplatInputError(f"refine.steps (--refine-steps): expected >= 0, got {self.steps}")
        if not (math.isfinite(self.fits_per_view) and self.fits_per_view >= 0):
            raise SurfSplatInputError(f"refine.fits_per_view: expected >= 0, got {self.fits_per_view}")
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise SurfSplatInputError(f"refine.lr: expected a positive rate, got {self.lr}")
        if self.views_per_step < 1:
            raise SurfSplatInputError(f"refine.views_per_step: expected at least 1, got {self.views_per_step}")
        if not (math.isfinite(self.scale) and 0 < self.scale <= 1):
            raise SurfSplatInputError(f"refine.scale: expected a fraction in (0, 1], got {self.scale}")
        if self.patience is not None and self.patience < 1:
            raise SurfSplatInputError(f"refine.patience: expected at least 1 step or None, got {self.patience}")
        if not (math.isfinite(self.min_improvement) and 0 <= self.min_improvement < 1):
            raise SurfSplatInputError(f"refine.min_improvement: expected a share in [0, 1), got {self.min_improvement}")

    def steps_for(self, views: int) -> int:
        """The Adam steps for `views` context views: `steps`, or enough for `fits_per_view` fits of each."""
        if self.steps is not None:
            return self.steps
        return math.ceil(self.fits_per_view * views / max(1, min(self.views_per_step, views)) - 1e-9)

    def plan(self, views: int) -> FitPlan:
        """The shared loop's plan: SH, tangent log scales and opacity logits (at 4x the rate) free,
        the mean squared colour error."""
        rates = {"sh_dc": self.lr, "sh_rest": self.lr, "log_scales": self.lr, "logits": 4 * self.lr}
        return FitPlan(
            name="refine",
            steps=self.steps_for(views),
            rates=rates,
            views_per_step=self.views_per_step,
            seed=self.seed,
            scale=self.scale,
            loss="mse",
            patience=self.patience,
            min_improvement=self.min_improvement,
        )


def refine_on_views(
    gaussians: Gaussians,  # [N] unbatched
    cameras: Cameras,  # [V] the context views, K in pixels of height x width
    images: Tensor,  # [V, 3, H, W] in [0, 1]
    width: int,
    height: int,
    config: RefineConfig | None = None,
    *,
    mode: str = "surfel",
    alpha_threshold: float | None = 0.001,
    backend: str = "auto",
    progress: bool = False,
) -> tuple[Gaussians, dict[str, float]]:
    """The surfels with SH, opacities and tangent scales fitted to the photos, and the fit's figures:
    the mean squared colour error over every view before and after it, whether it was kept (a fit
    that raised the error is not used), the steps run, the render size and the seconds
    ({"steps", "max_steps", "mse_before", "mse_after", "kept", "scale", "width", "height", "seconds"}).
    `progress`: a progress bar over the steps. The loop is `fit_on_views`, the optimization's."""
    config = config or RefineConfig()
    return fit_on_views(
        gaussians,
        cameras,
        images,
        width,
        height,
        config.plan(len(cameras)),
        mode=mode,
        alpha_threshold=alpha_threshold,
        backend=backend,
        progress=progress,
    )


def refine_summary(stats: dict[str, float]) -> str:
    """One line for the reconstruct summary and the capture report, from `refine_on_views`'s figures."""
    before, after = (-10 * math.log10(max(stats[k], 1e-12)) for k in ("mse_before", "mse_after"))
    steps = f"{int(stats['steps'])} steps"
    if "max_steps" in stats and stats["steps"] < stats["max_steps"]:
        steps += f" of {int(stats['max_steps'])} (the loss stopped falling)"
    if "width" in stats:
        steps += f" at {int(stats['width'])}x{int(stats['height'])}"
    if "seconds" in stats:
        steps += f" in {stats['seconds']:.1f} s"
    line = f"refined on the context views: {steps}, colour PSNR there {before:.2f} -> {after:.2f} dB"
    return line + ("" if stats["kept"] else " (not kept: the fit made it worse)")
