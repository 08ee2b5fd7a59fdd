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
`views_per_step` context views, drawn by a seeded generator without replacement, so the cost per
step is bounded for hundreds of views and the result is the same on every run.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ..checks import SurfSplatInputError
from ..gaussians import Gaussians
from ..geometry.cameras import Cameras

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class RefineConfig:
    """How a fused scene is refined on its context photos (steps 0: not at all)."""

    steps: int = 100  # Adam steps
    lr: float = 0.01  # rate of the SH coefficients and log scales; opacity logits at 4x
    views_per_step: int = 16  # context views rendered in one step (all of them when fewer)
    seed: int = 0  # which views each step renders

    def __post_init__(self) -> None:
        if self.steps < 0:
            raise SurfSplatInputError(f"refine.steps (--refine-steps): expected >= 0, got {self.steps}")
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise SurfSplatInputError(f"refine.lr: expected a positive rate, got {self.lr}")
        if self.views_per_step < 1:
            raise SurfSplatInputError(f"refine.views_per_step: expected at least 1, got {self.views_per_step}")


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
) -> tuple[Gaussians, dict[str, float]]:
    """The surfels with SH, opacities and tangent scales fitted to the photos, and the fit's figures:
    the mean squared colour error over every view before and after it, and whether it was kept
    ({"steps", "mse_before", "mse_after", "kept"}: a fit that raised the error is not used)."""
    from ..render import render

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

    def draw(g: Gaussians, which: Tensor) -> Tensor:
        out = render(g, cameras[which], width, height, mode=mode, backend=backend, alpha_threshold=alpha_threshold)
        return out.color

    def mse(g: Gaussians) -> float:
        with torch.no_grad():
            chunks = torch.arange(v).split(config.views_per_step)
            total = sum(float((draw(g, c) - images[c]).square().sum()) for c in chunks)
        return total / images.numel()

    before = mse(g0)
    if config.steps == 0:
        return g0, {"steps": 0, "mse_before": before, "mse_after": before, "kept": 1.0}
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

    generator = torch.Generator().manual_seed(config.seed)
    for _ in range(config.steps):
        which = torch.randperm(v, generator=generator)[: config.views_per_step].sort().values
        loss = (draw(current(), which) - images[which]).square().mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        fitted = current()
        fitted = replace(
            fitted, sh=fitted.sh.detach(), opacities=fitted.opacities.detach(), scales=fitted.scales.detach()
        )
    after = mse(fitted)
    stats = {"steps": config.steps, "mse_before": before, "mse_after": after, "kept": float(after <= before)}
    if after > before:  # a rate too high for this scene: the photos are matched worse, so it is not used
        logger.warning(
            "refine: the fit raised the context views' colour error (%.3g -> %.3g); the fused surfels are kept "
            "as predicted (lower CaptureOptions.refine.lr)",
            before,
            after,
        )
        return g0, stats
    return fitted, stats


def refine_summary(stats: dict[str, float]) -> str:
    """One line for the reconstruct summary and the capture report, from `refine_on_views`'s figures."""
    before, after = (-10 * math.log10(max(stats[k], 1e-12)) for k in ("mse_before", "mse_after"))
    line = (
        f"refined on the context views: {int(stats['steps'])} steps, colour PSNR there {before:.2f} -> {after:.2f} dB"
    )
    return line + ("" if stats["kept"] else " (not kept: the fit made it worse)")
