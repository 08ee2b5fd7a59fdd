"""`compact` and `compact_surfels`: the rounds of prune, deduplicate and merge, then refit and recolour."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..geometry.pixels import pixel_cells
from ..render.types import Backend, RenderMode, check_render_args
from ..utils.checks import SurfSplatInputError
from .cells import cell_footprints, floor_scales
from .config import DEFAULT_LEVEL, CompactConfig, level_config
from .dedup import _absorb, _duplicate_cover
from .merge import _merge_level
from .prune import _local_minima, _prune_weights
from .refit import refit


@dataclass
class CompactResult:
    """What `compact_surfels` returns."""

    gaussians: Gaussians  # [M] surfels, sorted by (view, row, column) of their cells
    cells: Tensor  # [M, 4] int64 (view, row, column, size): the size x size pixel block each surfel stands for
    stats: dict[str, int] = field(default_factory=dict)  # input, pruned, duplicates, merged away, output, rounds


def compact(
    gaussians: Gaussians,
    context_cameras: Cameras,
    height: int,
    width: int,
    level: int = DEFAULT_LEVEL,
    *,
    config: CompactConfig | None = None,
    cells: Tensor | None = None,
    mode: RenderMode = "surfel",
    backend: Backend = "auto",
    alpha_threshold: float | None = 0.001,
) -> Gaussians:
    """Fewer surfels rendering the same picture (see the module docstring).

    gaussians:       [N] unbatched; without `cells`, the model's output: N = V*H*W in (view, row,
                     column) order, one surfel per pixel of each context view
    context_cameras: the V context cameras, K in pixels of the H x W maps
    level:           a preset of `LEVELS` (1 gentle .. 5 strong); `config` overrides it
    cells:           [N, 4] (view, row, column, size) when the input is already compacted
    mode, backend, alpha_threshold: how the reconstruction is rendered (the pruning pass uses them)
    Returns Gaussians [M], M <= N.
    """
    return compact_surfels(
        gaussians,
        context_cameras,
        height,
        width,
        level,
        config=config,
        cells=cells,
        mode=mode,
        backend=backend,
        alpha_threshold=alpha_threshold,
    ).gaussians


def compact_surfels(
    gaussians: Gaussians,
    context_cameras: Cameras,
    height: int,
    width: int,
    level: int = DEFAULT_LEVEL,
    *,
    config: CompactConfig | None = None,
    cells: Tensor | None = None,
    mode: RenderMode = "surfel",
    backend: Backend = "auto",
    alpha_threshold: float | None = 0.001,
) -> CompactResult:
    """`compact` with the cells of the result and counts of what each step removed."""
    cfg = config if config is not None else level_config(level)
    cells = _validate(gaussians, context_cameras, height, width, cells, mode, backend)
    g = gaussians.detach()
    cameras = context_cameras.to(device=g.means.device, dtype=g.means.dtype)
    probe_cameras = _probe_cameras(cameras, cfg.nearby_views)
    stats = {"input": len(g), "pruned": 0, "duplicates": 0, "merged_away": 0, "rounds": 0}
    render_args = (mode, backend, alpha_threshold)
    g, cells = _rounds(g, cells, cameras, probe_cameras, height, width, cfg, render_args, stats)
    if cfg.refit_steps > 0 and len(g) < len(gaussians):
        g = refit(g, gaussians.detach(), probe_cameras, width, height, cfg, *render_args)
        # The refit moves opacities, scales and colours: what it made redundant goes too (without a
        # second refit). The result is a fixed point of the rounds, and a compacted input that the
        # rounds leave as it is gets no refit, so compacting it again changes nothing.
        g, cells = _rounds(g, cells, cameras, probe_cameras, height, width, cfg, render_args, stats)
        # What that round pruned leaves its neighbours' colours short: the SH alone are fitted once
        # more. Weights (taken with colour 1), duplicates and pruning do not depend on colours, so
        # the rounds on its result can at most merge blocks the new colours made alike; their result
        # is a fixed point again.
        if cfg.recolour_steps > 0:
            recolour = replace(cfg, refit_steps=cfg.recolour_steps)
            g = refit(g, gaussians.detach(), probe_cameras, width, height, recolour, *render_args, colours_only=True)
            g, cells = _rounds(g, cells, cameras, probe_cameras, height, width, cfg, render_args, stats)
    stats["output"] = len(g)
    return CompactResult(g, cells, stats)


def _rounds(
    g: Gaussians,
    cells: Tensor,
    cameras: Cameras,
    probe_cameras: Cameras,
    height: int,
    width: int,
    cfg: CompactConfig,
    render_args: tuple,
    stats: dict[str, int],
) -> tuple[Gaussians, Tensor]:
    """Deduplicate, merge and prune, round after round, until a round removes nothing (or
    cfg.max_rounds); counts go to `stats`. The result is in (view, row, column) order."""
    for _ in range(cfg.max_rounds):
        before = len(g)
        if cfg.dedup and len(cameras) > 1:
            cover = _duplicate_cover(g, cells, cameras, height, width, cfg)
            keep = cover < 0
            stats["duplicates"] += int((~keep).sum())
            g = _absorb(g, torch.nonzero(~keep).squeeze(-1), cover[~keep], cell_footprints(g, cells, cameras))
            g, cells = g.subset(keep), cells[keep]
        for depth in range(cfg.merge_levels):
            count = len(g)
            g, cells = _merge_level(g, cells, cameras, len(cameras), height, width, 2**depth, cfg)
            stats["merged_away"] += count - len(g)
        # Last: merging needs whole blocks, which pruning would break up. In (view, row, column)
        # order, the output's: surfels at equal depth composite in input order, so the weights, and
        # whether a compacted result prunes again, must not depend on how it was put together.
        order = _cell_order(cells, height, width)
        g, cells = g.subset(order), cells[order]
        for _ in range(cfg.prune_passes if cfg.prune_weight > 0 else 0):
            weights = _prune_weights(g, probe_cameras, width, height, cfg, *render_args)
            keep = weights >= cfg.prune_weight
            if cfg.prune_local_minima:
                keep |= ~_local_minima(weights, cells, len(cameras), height, width)
            if bool(keep.all()):
                break
            stats["pruned"] += int((~keep).sum())
            g, cells = g.subset(keep), cells[keep]
            if cfg.scale_floor:
                g = floor_scales(g, cell_footprints(g, cells, cameras))
        stats["rounds"] += 1
        if len(g) == before:
            break
    return g, cells


def _validate(
    g: Gaussians, cameras: Cameras, height: int, width: int, cells: Tensor | None, mode: str, backend: str
) -> Tensor:
    check_render_args("compact", g, cameras, width, height, mode, backend)
    views = len(cameras)
    if cells is None:
        if len(g) != views * height * width:
            raise SurfSplatInputError(
                f"compact: expected one surfel per pixel of each context view, {views} x {height} x {width} = "
                f"{views * height * width}, got {len(g)} (pass cells= for an already compacted reconstruction)"
            )
        return pixel_cells(views, height, width, g.means.device)
    if cells.shape != (len(g), 4) or cells.dtype != torch.long:
        raise SurfSplatInputError(
            f"compact: cells expected int64 [{len(g)}, 4], got {cells.dtype} {tuple(cells.shape)}"
        )
    v, r, c, s = cells.unbind(-1)
    ok = (v >= 0) & (v < views) & (s >= 1) & (r >= 0) & (c >= 0) & (r + s <= height) & (c + s <= width)
    ok &= (r % s == 0) & (c % s == 0) & ((s & (s - 1)) == 0)
    if not bool(ok.all()):
        raise SurfSplatInputError("compact: cells must be aligned power-of-two blocks inside the context views")
    return cells.to(g.means.device)


def _cell_order(cells: Tensor, height: int, width: int) -> Tensor:
    """Indices sorting cells by (view, row, column); cells do not overlap, so the keys are unique."""
    key = (cells[:, 0] * height + cells[:, 1]) * width + cells[:, 2]
    return torch.argsort(key, stable=True)


def _probe_cameras(cameras: Cameras, nearby: int) -> Cameras:
    """The context cameras plus `nearby` cameras strictly between each consecutive pair."""
    if nearby == 0 or len(cameras) < 2:
        return cameras
    from ..export.paths import interpolate_cameras

    c2w, K = [cameras.c2w], [cameras.K]
    for i in range(len(cameras) - 1):
        between = interpolate_cameras(cameras[i : i + 2], nearby + 2)
        c2w.append(between.c2w[1:-1])
        K.append(between.K[1:-1])
    return Cameras(torch.cat(c2w), torch.cat(K), validate=False)
