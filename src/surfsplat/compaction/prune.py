"""Pruning: blending weights by one backward pass per view, and the local minima pruned at strong levels."""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..geometry.sh import SH_C0
from ..render.types import Backend, RenderMode
from .cells import owner_map
from .config import CompactConfig


def blending_weights(
    gaussians: Gaussians,
    cameras: Cameras,
    width: int,
    height: int,
    *,
    mode: RenderMode = "surfel",
    backend: Backend = "auto",
    alpha_threshold: float | None = 0.001,
) -> Tensor:
    """[N] each surfel's largest, over the cameras, total normalized blending weight.

    In one view that is sum_p w_ip / A_p (A_p: the pixel's alpha where forced alpha blending divides
    by it, else 1): the number of pixels' worth of final colour the surfel makes. Exact, by one
    backward pass per view through the renderer: with every surfel's colour 1 (SH degree 0,
    DC = 0.5 / SH_C0), d(sum_p colour_p / A_p) / d(DC_i) = SH_C0 * sum_p w_ip / A_p.
    """
    g = gaussians.detach()
    dc = torch.full_like(g.sh[:, :1, :1], 0.5 / SH_C0).requires_grad_(True)
    best = torch.zeros(len(g), dtype=g.means.dtype, device=g.means.device)
    from ..render import render

    with torch.enable_grad():
        for c in range(len(cameras)):
            dc.grad = None
            probe = replace(g, sh=dc.expand(-1, 3, -1), validate=False)
            out = render(probe, cameras[c], width, height, mode=mode, backend=backend, alpha_threshold=None)
            alpha = out.alpha.detach()
            if alpha_threshold is None:
                scale = torch.ones_like(alpha)
            else:
                scale = torch.where(alpha >= alpha_threshold, 1 / alpha.clamp_min(alpha_threshold), 1.0)
            (out.color[:, :1] * scale).sum().backward()
            best = torch.maximum(best, dc.grad[:, 0, 0] / SH_C0)
    return best


def _prune_weights(
    g: Gaussians,
    cameras: Cameras,
    width: int,
    height: int,
    cfg: CompactConfig,
    mode: RenderMode,
    backend: Backend,
    alpha_threshold: float | None,
) -> Tensor:
    """[N] the largest blending weight over cfg.prune_factors, in pixels of the context views' size
    (a weight at f times the resolution divided by f^2): a surfel that alone fills a gap its
    neighbours leave at a finer resolution keeps a weight there that it shares at 1x."""
    weights = [
        blending_weights(
            g,
            cameras.scaled(float(f)),
            width * f,
            height * f,
            mode=mode,
            backend=backend,
            alpha_threshold=alpha_threshold,
        )
        / f**2
        for f in cfg.prune_factors
    ]
    return torch.stack(weights).amax(0)


def _local_minima(weights: Tensor, cells: Tensor, views: int, height: int, width: int) -> Tensor:
    """[N] surfels whose weight is the smallest among the surfels owning the pixels of their cell and
    the one-pixel ring around it (ties broken by index), so one pass never removes two neighbours."""
    rank = torch.empty_like(cells[:, 0])
    rank[torch.argsort(weights, stable=True)] = torch.arange(len(weights), device=cells.device)
    owner = owner_map(cells, views, height, width)
    big = len(weights)
    ranks = torch.where(owner >= 0, rank[owner.clamp_min(0)], big).double()
    around = -torch.nn.functional.max_pool2d(-ranks[:, None], 3, stride=1, padding=1)[:, 0].long()
    lowest = torch.full_like(rank, big).scatter_reduce_(
        0, owner[owner >= 0], around[owner >= 0], reduce="amin", include_self=True
    )
    return lowest == rank
