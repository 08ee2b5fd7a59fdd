"""Refit: the survivors' SH, opacities and tangent scales fitted to the input's renders."""

from __future__ import annotations

import math
from dataclasses import replace

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..render.types import Backend, RenderMode
from .config import CompactConfig


def refit(
    student: Gaussians,
    teacher: Gaussians,
    cameras: Cameras,
    width: int,
    height: int,
    cfg: CompactConfig,
    mode: RenderMode = "surfel",
    backend: Backend = "auto",
    alpha_threshold: float | None = 0.001,
    colours_only: bool = False,
) -> Gaussians:
    """`student` with SH, opacities and tangent scales fitted to `teacher`'s renders (step 4).

    Loss: the mean squared colour error over `cameras` at each of cfg.refit_factors times
    width x height, summed (colour only: where alpha falls below the threshold the background shows,
    so a hole costs colour too); cfg.refit_steps Adam steps. Opacities are
    fitted as logits and scales as logarithms, so both stay in range; the third scale (a surfel's
    zero thickness) is kept, and so are explicit covariances (their scales do not render).
    colours_only: fit the SH alone; opacities and scales come back exactly as they went in (step 5).
    """
    from ..render import render

    views = [(cameras.scaled(float(f)), width * int(f), height * int(f)) for f in cfg.refit_factors]
    with torch.no_grad():
        targets = [
            render(teacher, cams, w, h, mode=mode, backend=backend, alpha_threshold=alpha_threshold).color
            for cams, w, h in views
        ]
    sh = student.sh.clone().requires_grad_(True)
    logits = torch.logit(student.opacities.clamp(1e-4, 1 - 1e-4)).requires_grad_(True)
    # Explicit covariances (the release's adapter) render without the scales: those are not fitted.
    logits.requires_grad_(not colours_only)
    fit_scales = student.explicit_covariances is None and not colours_only
    log_scales = student.scales[:, :2].log().requires_grad_(fit_scales)
    thickness = student.scales[:, 2:]
    groups = [{"params": [sh, log_scales] if fit_scales else [sh], "lr": cfg.refit_lr}]
    if not colours_only:
        groups.append({"params": [logits], "lr": 4 * cfg.refit_lr})
    optimizer = torch.optim.Adam(groups)

    def current() -> Gaussians:
        if colours_only:
            return replace(student, sh=sh, validate=False)
        scales = torch.cat((log_scales.exp(), thickness), dim=-1)
        return replace(student, sh=sh, opacities=torch.sigmoid(logits), scales=scales, validate=False)

    def loss_of(g: Gaussians) -> Tensor:
        return sum(
            (out.color - target).square().mean()
            for (cams, w, h), target in zip(views, targets)
            for out in [render(g, cams, w, h, mode=mode, backend=backend, alpha_threshold=alpha_threshold)]
        )

    # Adam's steps keep a size near the rate however small the gradient is, so the lowest-loss
    # iterate (the input included) is returned: the refit never moves away from a better fit.
    best, best_loss = student, math.inf
    for step in range(cfg.refit_steps + 1):
        last = step == cfg.refit_steps  # the final iterate is only scored
        with torch.set_grad_enabled(not last):
            g = current()
            loss = loss_of(g)
        if float(loss.detach()) < best_loss:
            best_loss = float(loss.detach())
            if step == 0:
                best = student
            elif colours_only:  # opacities and scales exactly as they came (no round trip through logits)
                best = replace(student, sh=sh.detach(), validate=False)
            else:
                best = replace(g, sh=sh.detach(), opacities=g.opacities.detach(), scales=g.scales.detach())
        if not last:
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
    return best
