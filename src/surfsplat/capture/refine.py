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
surface is the one predicted. Loss: the mean squared colour error of the renders (forced alpha
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

import logging
import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..utils.checks import SurfSplatInputError

logger = logging.getLogger(__name__)


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
    `progress`: a progress bar over the steps."""
    import time

    import torch.nn.functional as F

    from ..render import render
    from ..utils.log import progress as progress_bar

    start = time.perf_counter()

    config = config or RefineConfig()
    v = len(cameras)
    if images.shape != (v, 3, height, width):
        raise SurfSplatInputError(f"refine: images expected [{v}, 3, {height}, {width}], got {tuple(images.shape)}")
    g0 = gaussians.detach()
    if g0.explicit_covariances is not None:
        raise SurfSplatInputError(
            "refine: surfels with explicit covariances (the release adapter) have no scales to fit"
        )
    images = images.to(g0.means.device, g0.means.dtype)
    cameras = cameras.to(device=g0.means.device, dtype=g0.means.dtype)

    fit_w, fit_h = max(1, round(width * config.scale)), max(1, round(height * config.scale))
    resize = torch.tensor([fit_w / width, fit_h / height, 1.0], dtype=cameras.K.dtype, device=cameras.K.device)
    fit_cameras = Cameras(cameras.c2w, cameras.K * resize[:, None], validate=False)
    fit_images = images if config.scale == 1 else F.interpolate(images, size=(fit_h, fit_w), mode="area")

    def draw(g: Gaussians, cams: Cameras, w: int, h: int) -> Tensor:
        return render(g, cams, w, h, mode=mode, backend=backend, alpha_threshold=alpha_threshold).color

    def mse(g: Gaussians) -> float:
        with torch.no_grad():
            chunks = torch.arange(v, device=images.device).split(config.views_per_step)
            sums = torch.stack([(draw(g, cameras[c], width, height) - images[c]).square().sum() for c in chunks])
        # read once; the chunks' float32 sums are added in Python's double precision, as they always were
        return sum(sums.tolist()) / images.numel()

    total = config.steps_for(v)
    figures = {"max_steps": total, "scale": config.scale, "width": fit_w, "height": fit_h}
    before = mse(g0)
    if total == 0:
        seconds = time.perf_counter() - start
        return g0, {"steps": 0, "mse_before": before, "mse_after": before, "kept": 1.0, **figures, "seconds": seconds}
    sh = g0.sh.clone().requires_grad_(True)
    logits = torch.logit(g0.opacities.clamp(1e-4, 1 - 1e-4)).requires_grad_(True)
    log_scales = g0.scales[:, :2].log().requires_grad_(True)
    thickness = g0.scales[:, 2:]
    optimizer = torch.optim.Adam(
        [{"params": [sh, log_scales], "lr": config.lr}, {"params": [logits], "lr": 4 * config.lr}]
    )

    def current() -> Gaussians:
        scales = torch.cat((log_scales.exp(), thickness), dim=-1)
        return replace(g0, sh=sh, opacities=torch.sigmoid(logits), scales=scales, validate=False)

    # Every step's views drawn up front on the host's generator (the same draws on every device)
    # and moved to the device once: [steps, views rendered a step].
    generator = torch.Generator().manual_seed(config.seed)
    draws = [torch.randperm(v, generator=generator)[: config.views_per_step].sort().values for _ in range(total)]
    draws = torch.stack(draws).to(images.device)
    # Each step's loss stays on the device until a window of the early stop ends (never without
    # one): reading it every step would make the host wait for the device every step.
    losses: list[float] = []
    pending: list[Tensor] = []
    with progress_bar(total=total, desc="refine", unit="step", enabled=progress) as bar:
        for step in range(total):
            which = draws[step]
            loss = (draw(current(), fit_cameras[which], fit_w, fit_h) - fit_images[which]).square().mean()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            pending.append(loss.detach())
            bar.update(1)
            if config.patience is not None and (step + 1) % config.patience == 0:
                losses += torch.stack(pending).tolist()
                pending = []
                if _stalled(losses, config.patience, config.min_improvement):
                    break
    steps = len(losses) + len(pending)
    with torch.no_grad():
        fitted = current()
        fitted = replace(
            fitted, sh=fitted.sh.detach(), opacities=fitted.opacities.detach(), scales=fitted.scales.detach()
        )
    after = mse(fitted)
    stats = {"steps": steps, "mse_before": before, "mse_after": after, "kept": float(after <= before), **figures}
    stats["seconds"] = time.perf_counter() - start
    if after > before:  # a rate too high for this scene: the photos are matched worse, so it is not used
        logger.warning(
            "refine: the fit raised the context views' colour error (%.3g -> %.3g); the fused surfels are kept "
            "as predicted (lower CaptureOptions.refine.lr)",
            before,
            after,
        )
        return g0, stats
    return fitted, stats


def _stalled(losses: list[float], patience: int | None, min_improvement: float) -> bool:
    """Whether the last window of `patience` steps lowered the mean loss by less than
    `min_improvement` of the window before it (windows end at the current step)."""
    if patience is None or len(losses) < 2 * patience or len(losses) % patience:
        return False
    last = sum(losses[-patience:]) / patience
    previous = sum(losses[-2 * patience : -patience]) / patience
    return last > previous * (1 - min_improvement)


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
