"""Compact surfels: fewer primitives for the same picture.

The model predicts one surfel per pixel per context view (the paper's second stated limitation:
"predicting one Gaussian per pixel can lead to redundant representations"). `compact` removes the
redundancy in three steps, repeated until a round changes nothing; a round deduplicates (2), merges
(3) and prunes (1) last, because merging needs whole blocks, which pruning would break up. The
strong levels then fit the survivors to the input's picture (4, 5):

1. prune: surfels whose blending weight is small in every context view and in a few views
   interpolated between them. The weight of surfel i is sum over pixels of w_ip / A_p, where w_ip
   is its compositing weight (alpha times transmittance) and A_p the pixel's alpha when forced alpha
   blending divides by it (1 elsewhere): how many pixels' worth of final colour the surfel makes. It
   is computed exactly by one backward pass per view: render every surfel with colour 1, so the
   colour image is sum_i w_ip; the gradient of sum_p colour_p / A_p (A_p held fixed) with respect
   to surfel i's colour is that weight. The compiled CPU renderer (or the torch / gsplat one on a
   GPU) does this in about the time of one training step. Weights are also taken at 2x (divided by
   4) where a level asks, so a surfel that alone fills a gap at a finer resolution keeps its weight.
   At levels 3-5 a pass prunes only surfels below the threshold whose weight is the smallest around
   their cell (never two neighbours at once), and passes repeat with fresh weights: where two views' layers
   overlap, the weights of one layer's survivors rise as its other surfels go, so strong levels
   (a threshold of about a pixel's worth) thin a doubled surface to one layer without opening
   holes. The survivors' tangent scales are then raised to their footprint's low-pass size (see
   `_floor_scales`), closing at x4 the gaps removed neighbours used to fill.
2. deduplicate: views are visited in order; a surfel of view j is dropped when it projects into
   view i < j onto a pixel whose surfel lies on the same plane (distance along the normal within a
   tolerance in view i's pixel footprints, normals within an angle), whose 3 x 3 neighbourhood is
   covered by locally coplanar surfels (so no silhouette or hole is relied on), and whose sampling is
   not coarser than view j's. The covering surfel absorbs the duplicate's alpha and colour.
3. merge: a quadtree over each view's pixel grid. A 2 x 2 block of same-size cells becomes one
   surfel when the four are coplanar (least-squares plane through their centres, every normal within
   an angle of it), of one colour and opacity within tolerances, of similar scales, and surrounded
   by surfels on their plane and of their colour; then 2 x 2 blocks of those, up to the level's
   largest block. The merged surfel sits at the centroid on the fitted plane, its tangent u follows
   the block's image rows, its scales are twice the children's effective ones (the surfel field of
   a coarser pixel grid: same overlap; the renderer's low-pass filter counts), its opacity the mean
   and its SH the alpha-mass-weighted mean. Depth and colour edges keep full resolution.
4. refit (levels 3-5): the surviving surfels' SH, opacities and tangent scales are fitted by Adam
   to the renders of the input reconstruction at the pruning pass's views, at their resolution
   (mean squared colour error; `refit_factors` adds finer ones, which measured no better at x4,
   since the floored scales already close the surface there, and worse at x1); positions,
   rotations and the cells stay. Steps 1-3 each replace several surfels by one chosen by a local
   rule; this step lets all of them settle together on the picture the input made. It runs only
   when steps 1-3 removed something; the rounds then run once more on its result (it moves
   weights and colours), without another refit.
5. recolour (levels 3-5): what that last round pruned (surfels the refit faded) leaves colour
   short around it, so the SH alone are fitted once more the same way. Weights are taken with
   colour 1, and duplicates are found by geometry, so this cannot make anything prunable or a
   duplicate; it can only let a block of now like-coloured surfels merge, which the rounds, run once
   more, do (rarely, and few).

Every surfel carries the pixel block it stands for (`CompactResult.cells`: view, row, column,
size), so the result can be compacted again. Rounds repeat until nothing changes (every round that
changes something removes surfels; `max_rounds` bounds them) and weights are always taken with the
surfels in (view, row, column) order, so the result is a fixed point of the rounds and gets no
refit or recolouring when compacted again: compact at a fixed level is idempotent. It is deterministic (no
randomness; the compiled CPU renderer's gradients do not depend on threads).

Written here because no library merges splats on a per-view quadtree with these surfel rules.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..geometry.rotations import matrix_to_quat
from ..geometry.sh import SH_C0
from ..render.types import BACKENDS, LOWPASS_RHO_SCALE, Backend, RenderMode
from ..utils.checks import SurfSplatInputError


@dataclass(frozen=True)
class CompactConfig:
    """How hard `compact` works; `LEVELS` holds the presets of `--compact LEVEL`."""

    prune_weight: float = 0.02  # pixels' worth of colour below which a surfel is pruned (0: no pruning)
    nearby_views: int = 2  # views interpolated between consecutive context views for the pruning pass
    dedup: bool = True  # remove surfels of later views lying on surfaces earlier views cover
    dedup_distance: float = 1.0  # plane distance tolerance, in pixel footprints of the covering view
    dedup_normal_degrees: float = 20.0  # normal agreement of a duplicate
    dedup_footprint_ratio: float = 1.5  # the covering view may sample the surface at most this much coarser
    merge_levels: int = 2  # quadtree depth: blocks up to 2^levels x 2^levels pixels (0: no merging)
    plane_tolerance: float = 0.05  # children's distance from the fitted plane, in child spacings (pixel footprints)
    normal_degrees: float = 10.0  # angle between a child's normal and the fitted plane's
    ring_tolerance: float = 0.5  # distance of the surfels around a block from its plane, in child spacings
    colour_tolerance: float = 0.02  # largest deviation of a child's base colour (0..1) from the block's mean
    opacity_tolerance: float = 0.05  # largest deviation of a child's opacity from the block's mean
    scale_ratio: float = 1.5  # largest ratio between the children's scales along one axis
    prune_factors: tuple[int, ...] = (1,)  # resolutions (times the context views') the weights are taken at
    prune_local_minima: bool = False  # a pass prunes only surfels whose weight is the smallest around them
    prune_passes: int = 16  # weight passes per round at most (local minima: each pass frees a few)
    scale_floor: bool = False  # survivors' tangent scales at least their footprint's low-pass size (see _floor_scales)
    max_rounds: int = 6  # prune/dedup/merge rounds at most (stops earlier when a round changes nothing)
    refit_steps: int = 0  # Adam steps fitting SH, opacity and scales to the input's renders (0: none)
    refit_factors: tuple[int, ...] = (1,)  # resolutions (times the context views') the refit compares at
    refit_lr: float = 0.005  # Adam rate of SH and log-scales (opacity logits take 4x)
    recolour_steps: int = 0  # Adam steps fitting only SH after the refit's round (0: none; see compact_surfels)

    def __post_init__(self) -> None:
        if self.prune_weight < 0:
            raise SurfSplatInputError(f"compact.prune_weight: expected >= 0, got {self.prune_weight}")
        if self.nearby_views < 0 or self.merge_levels < 0 or self.max_rounds < 1:
            raise SurfSplatInputError(
                "compact: nearby_views >= 0, merge_levels >= 0 and max_rounds >= 1 expected, got "
                f"{self.nearby_views}, {self.merge_levels}, {self.max_rounds}"
            )
        for name in ("dedup_distance", "plane_tolerance", "ring_tolerance", "colour_tolerance", "opacity_tolerance"):
            if not getattr(self, name) >= 0:
                raise SurfSplatInputError(f"compact.{name}: expected >= 0, got {getattr(self, name)}")
        if self.dedup_footprint_ratio < 1 or self.scale_ratio < 1:
            raise SurfSplatInputError("compact.dedup_footprint_ratio and scale_ratio: expected >= 1")
        if self.prune_passes < 1 or not all(int(f) == f >= 1 for f in self.prune_factors):
            raise SurfSplatInputError(
                f"compact: prune_passes >= 1 and integer prune_factors >= 1 expected, got {self.prune_passes}, "
                f"{self.prune_factors}"
            )
        if self.recolour_steps < 0:
            raise SurfSplatInputError(f"compact.recolour_steps: expected >= 0, got {self.recolour_steps}")
        if self.refit_steps < 0 or not self.refit_lr > 0 or not all(int(f) == f >= 1 for f in self.refit_factors):
            raise SurfSplatInputError(
                "compact: refit_steps >= 0, refit_lr > 0 and integer refit_factors >= 1 expected, got "
                f"{self.refit_steps}, {self.refit_lr}, {self.refit_factors}"
            )


# Presets of `--compact LEVEL`: each level merges one quadtree level deeper and tolerates more.
# From level 3 on, pruning takes weights at 1x and 2x, one neighbour at a time, and floors the
# survivors' scales, and the survivors are refitted and recoloured; level 4 (the default) prunes
# below 1.2 pixels' worth (thinning overlapping views' layers to one), level 5 below 2 and merges
# across larger colour and shape differences.
_LEVEL_3 = CompactConfig(
    prune_weight=0.5,
    prune_factors=(1, 2),
    prune_local_minima=True,
    scale_floor=True,
    merge_levels=3,
    colour_tolerance=0.05,
    opacity_tolerance=0.15,
    scale_ratio=2.0,
    dedup_distance=3.0,
    dedup_normal_degrees=30.0,
    refit_steps=50,
    recolour_steps=50,
)
_LEVEL_4 = replace(_LEVEL_3, prune_weight=1.2, merge_levels=4, dedup_distance=6.0, dedup_normal_degrees=90.0)
LEVELS: dict[int, CompactConfig] = {
    1: CompactConfig(merge_levels=1, colour_tolerance=0.015),
    2: CompactConfig(merge_levels=2, colour_tolerance=0.025),
    3: _LEVEL_3,
    4: _LEVEL_4,
    5: replace(
        _LEVEL_4,
        prune_weight=2.0,
        merge_levels=5,
        colour_tolerance=0.1,
        opacity_tolerance=0.2,
        scale_ratio=4.0,
        plane_tolerance=0.25,
        normal_degrees=30.0,
        ring_tolerance=1.5,
    ),
}
DEFAULT_LEVEL = 4  # the strongest level measured within 0.1 dB on every scene, at 2.36x or more (docs/compact.json)


def level_config(level: int) -> CompactConfig:
    """The preset of a `--compact` level (SurfSplatInputError for an unknown one)."""
    if level not in LEVELS:
        raise SurfSplatInputError(f"compact level: expected one of {sorted(LEVELS)}, got {level!r}")
    return LEVELS[level]


@dataclass
class CompactResult:
    """What `compact_surfels` returns."""

    gaussians: Gaussians  # [M] surfels, sorted by (view, row, column) of their cells
    cells: Tensor  # [M, 4] int64 (view, row, column, size): the size x size pixel block each surfel stands for
    stats: dict[str, int] = field(default_factory=dict)  # input, pruned, duplicates, merged away, output, rounds


def pixel_cells(views: int, height: int, width: int) -> Tensor:
    """[V*H*W, 4] the cells of the model's output: one pixel each, in (view, row, column) order."""
    v, r, c = torch.meshgrid(torch.arange(views), torch.arange(height), torch.arange(width), indexing="ij")
    return torch.stack((v.flatten(), r.flatten(), c.flatten(), torch.ones(v.numel(), dtype=torch.long)), dim=-1)


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
            g = _absorb(g, torch.nonzero(~keep).squeeze(-1), cover[~keep], _footprints(g, cells, cameras))
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
                g = _floor_scales(g, _footprints(g, cells, cameras))
        stats["rounds"] += 1
        if len(g) == before:
            break
    return g, cells


# ---------------------------------------------------------------------------------------------- validation
def _validate(
    g: Gaussians, cameras: Cameras, height: int, width: int, cells: Tensor | None, mode: str, backend: str
) -> Tensor:
    if not isinstance(g, Gaussians) or g.means.ndim != 2:
        raise SurfSplatInputError("compact: expected unbatched surfsplat.Gaussians ([N, 3] means)")
    if not isinstance(cameras, Cameras):
        raise SurfSplatInputError(f"compact: context_cameras must be surfsplat.Cameras, got {type(cameras).__name__}")
    if height < 1 or width < 1:
        raise SurfSplatInputError(f"compact: expected a positive height and width, got {height} x {width}")
    if mode not in ("surfel", "ewa"):
        raise SurfSplatInputError(f"compact: mode expected 'surfel' or 'ewa', got {mode!r}")
    if backend not in BACKENDS:
        raise SurfSplatInputError(f"compact: backend expected one of {BACKENDS}, got {backend!r}")
    views = len(cameras)
    if cells is None:
        if len(g) != views * height * width:
            raise SurfSplatInputError(
                f"compact: expected one surfel per pixel of each context view, {views} x {height} x {width} = "
                f"{views * height * width}, got {len(g)} (pass cells= for an already compacted reconstruction)"
            )
        return pixel_cells(views, height, width).to(g.means.device)
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


# ---------------------------------------------------------------------------------------------- pruning
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
    owner = _owner_map(cells, views, height, width)
    big = len(weights)
    ranks = torch.where(owner >= 0, rank[owner.clamp_min(0)], big).double()
    around = -torch.nn.functional.max_pool2d(-ranks[:, None], 3, stride=1, padding=1)[:, 0].long()
    lowest = torch.full_like(rank, big).scatter_reduce_(
        0, owner[owner >= 0], around[owner >= 0], reduce="amin", include_self=True
    )
    return lowest == rank


# ---------------------------------------------------------------------------------------------- refit
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


# ---------------------------------------------------------------------------------------------- duplicates
def _owner_map(cells: Tensor, views: int, height: int, width: int) -> Tensor:
    """[V, H, W] index of the surfel whose cell covers each pixel (-1: none)."""
    owner = torch.full((views, height, width), -1, dtype=torch.long, device=cells.device)
    for s in torch.unique(cells[:, 3]).tolist():
        idx = torch.nonzero(cells[:, 3] == s).squeeze(-1)
        dr, dc = torch.meshgrid(
            torch.arange(s, device=cells.device), torch.arange(s, device=cells.device), indexing="ij"
        )
        rows = cells[idx, 1, None] + dr.flatten()
        cols = cells[idx, 2, None] + dc.flatten()
        owner[cells[idx, 0, None].expand_as(rows), rows, cols] = idx[:, None].expand_as(rows)
    return owner


def _oriented_normals(g: Gaussians, cells: Tensor, cameras: Cameras) -> Tensor:
    """[N, 3] unit normals facing the camera of each surfel's own view."""
    n = g.normals
    to_camera = cameras.centers.to(g.means)[cells[:, 0]] - g.means
    return torch.where((n * to_camera).sum(-1, keepdim=True) < 0, -n, n)


def _duplicate_cover(
    g: Gaussians, cells: Tensor, cameras: Cameras, height: int, width: int, cfg: CompactConfig
) -> Tensor:
    """[N] for each surfel of a view j > 0 lying on a surface an earlier view's surfels cover, the index
    of the covering surfel; -1 for the others."""
    views = len(cameras)
    keep = torch.ones(len(g), dtype=torch.bool, device=g.means.device)
    owner = _owner_map(cells, views, height, width)
    normals = _oriented_normals(g, cells, cameras)
    w2c = cameras.w2c.to(g.means)
    K = cameras.K.to(g.means)
    cos_tol = math.cos(math.radians(cfg.dedup_normal_degrees))
    # World size of one pixel of each surfel's own view at its depth.
    own = cells[:, 0]
    footprint_own = _footprints(g, cells, cameras) / cells[:, 3]
    cover = torch.full((len(g),), -1, dtype=torch.long, device=g.means.device)
    interior = {0: _interior(g, normals, owner[0], w2c[0], K[0], cfg.dedup_distance)}
    for j in range(1, views):
        idx = torch.nonzero(own == j).squeeze(-1)
        gone = torch.zeros(len(idx), dtype=torch.bool, device=idx.device)
        m = g.means[idx]
        for i in range(j):
            p = m @ w2c[i, :3, :3].T + w2c[i, :3, 3]
            z = p[:, 2]
            front = z > 1e-6
            uv = (p @ K[i].T)[:, :2] / torch.where(front, z, torch.ones_like(z))[:, None]
            inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
            col = uv[:, 0].floor().clamp(0, width - 1).long()
            row = uv[:, 1].floor().clamp(0, height - 1).long()
            t = owner[i, row, col]
            ok = inside & (t >= 0) & interior[i][row, col]
            t = t.clamp_min(0)
            footprint_i = z / K[i, 0, 0]
            plane = ((m - g.means[t]) * normals[t]).sum(-1).abs() <= cfg.dedup_distance * footprint_i
            agree = (normals[idx] * normals[t]).sum(-1) >= cos_tol
            # Per pixel, view i must sample the surface about as finely as view j (a merged covering
            # cell stands for its pixels, so the comparison is with view i's pixel, not its cell).
            finer = footprint_i <= cfg.dedup_footprint_ratio * footprint_own[idx]
            found = ok & plane & agree & finer & ~gone
            cover[idx[found]] = t[found]
            gone |= found
        keep[idx[gone]] = False
        # View j is final now: later views compare with its surviving surfels only.
        held = owner[j] >= 0
        owner[j][held] = torch.where(keep[owner[j][held]], owner[j][held], -1)
        interior[j] = _interior(g, normals, owner[j], w2c[j], K[j], cfg.dedup_distance)
    return cover


def _footprints(g: Gaussians, cells: Tensor, cameras: Cameras) -> Tensor:
    """[N] world size of each surfel's pixel block in its own view (camera z / focal * block size)."""
    own = cells[:, 0]
    w2c, K = cameras.w2c.to(g.means)[own], cameras.K.to(g.means)[own]
    z = (w2c[:, 2, :3] * g.means).sum(-1) + w2c[:, 2, 3]
    return z.abs() / K[:, 0, 0] * cells[:, 3]


def _absorb(g: Gaussians, removed: Tensor, cover: Tensor, footprint: Tensor) -> Gaussians:
    """Covering surfels take over the alpha and colour of the duplicates they replace.

    Two layers of opacity o_t and o_s composite to 1 - (1 - o_t)(1 - o_s) with colour weights o_t and
    (1 - o_t) o_s; the covering surfel gets that opacity and that mix of SH, with o_s and the SH of
    its duplicates averaged, so removing a layer neither thins the surface nor shifts its colour.
    Two interleaved layers also fill each other's gaps where the adapter clamped the scales below
    the pixel spacing (gaps the screen-space filter hides at x1 but not at x4): a covering surfel's
    scales are raised to at least that filter's 1/sqrt(2) of its footprint, as merged surfels' are.
    removed: [R] indices of duplicates, cover: [R] their covering surfels, footprint: [N].
    """
    if len(removed) == 0:
        return g
    n = len(g)
    count = torch.zeros(n, dtype=g.means.dtype, device=g.means.device).index_add_(
        0, cover, torch.ones_like(cover, dtype=g.means.dtype)
    )
    o_sum = torch.zeros_like(count).index_add_(0, cover, g.opacities[removed])
    sh_sum = torch.zeros_like(g.sh).index_add_(0, cover, g.sh[removed] * g.opacities[removed, None, None])
    hit = count > 0
    o_s = o_sum[hit] / count[hit]  # mean opacity of the absorbed duplicates
    sh_s = sh_sum[hit] / o_sum[hit].clamp_min(1e-30)[:, None, None]  # their opacity-weighted mean SH
    o_t = g.opacities[hit]
    w_t, w_s = o_t, (1 - o_t) * o_s
    opacities = g.opacities.clone()
    opacities[hit] = 1 - (1 - o_t) * (1 - o_s)
    sh = g.sh.clone()
    sh[hit] = (w_t[:, None, None] * g.sh[hit] + w_s[:, None, None] * sh_s) / (w_t + w_s).clamp_min(1e-30)[:, None, None]
    g = replace(g, opacities=opacities, sh=sh, validate=False)
    return _floor_scales(g, footprint, hit)


def _floor_scales(g: Gaussians, footprint: Tensor, which: Tensor | None = None) -> Gaussians:
    """Tangent scales of surfels `which` (all: None) raised to at least the renderer's low-pass size
    of their footprint [N] (1/sqrt(2) of it), as merged surfels' are.

    The adapter's tangent clamp leaves many surfels smaller than their pixel spacing; at the
    resolution they were predicted at the screen-space filter hides the gaps between them, but at
    x2 or x4 it does not, where overlapping layers and neighbours used to fill them. Once some of
    those are gone the survivors must cover their own footprint; facing the camera they render the
    same at 1x (the filter already draws them that large)."""
    which = torch.ones(len(g), dtype=torch.bool, device=g.means.device) if which is None else which
    floor = footprint[which, None] / math.sqrt(LOWPASS_RHO_SCALE)
    scales = g.scales.clone()
    scales[which] = torch.maximum(scales[which], floor)
    covariances = g.explicit_covariances
    if covariances is not None:
        # Explicit covariances grow by the same amount along the surfel's tangents.
        R = g.rotations[which][..., :2]  # [W, 3, 2] tangent axes
        extra = (floor.square() - g.scales[which].square()).clamp_min(0)  # [W, 2]
        covariances = covariances.clone()
        covariances[which] = covariances[which] + (R * extra[:, None, :]) @ R.transpose(-1, -2)
    return replace(g, scales=scales, explicit_covariances=covariances, validate=False)


def _interior(g: Gaussians, normals: Tensor, owner: Tensor, w2c: Tensor, K: Tensor, tolerance: float) -> Tensor:
    """[H, W] pixels whose 3 x 3 neighbourhood is owned by surfels on the centre surfel's plane."""
    H, W = owner.shape
    ok = owner >= 0
    centre = owner.clamp_min(0)
    mean, normal = g.means[centre], normals[centre]
    z = mean @ w2c[2, :3] + w2c[2, 3]
    footprint = z / K[0, 0]
    padded = torch.nn.functional.pad(owner, (1, 1, 1, 1), value=-1)
    for dr in (0, 1, 2):
        for dc in (0, 1, 2):
            other = padded[dr : dr + H, dc : dc + W]
            ok &= other >= 0
            distance = ((g.means[other.clamp_min(0)] - mean) * normal).sum(-1).abs()
            ok &= distance <= tolerance * footprint
    return ok


# ---------------------------------------------------------------------------------------------- merging
def _merge_level(
    g: Gaussians, cells: Tensor, cameras: Cameras, views: int, height: int, width: int, size: int, cfg: CompactConfig
) -> tuple[Gaussians, Tensor]:
    """Merge every qualifying 2 x 2 block of size-`size` cells into one cell of twice the size."""
    rows, cols = height // size, width // size
    if rows < 2 or cols < 2:
        return g, cells
    grid = torch.full((views, rows, cols), -1, dtype=torch.long, device=cells.device)
    at = cells[:, 3] == size
    idx = torch.nonzero(at).squeeze(-1)
    grid[cells[idx, 0], cells[idx, 1] // size, cells[idx, 2] // size] = idx
    r2, c2 = rows // 2 * 2, cols // 2 * 2
    # Children a b / c d of each aligned block, [V, rows/2, cols/2] each.
    a, b = grid[:, 0:r2:2, 0:c2:2], grid[:, 0:r2:2, 1:c2:2]
    c, d = grid[:, 1:r2:2, 0:c2:2], grid[:, 1:r2:2, 1:c2:2]
    children = torch.stack((a, b, c, d), dim=-1)  # [V, R, C, 4]
    full = (children >= 0).all(-1)
    if not bool(full.any()):
        return g, cells
    block_v, block_r, block_c = torch.nonzero(full, as_tuple=True)
    kids = children[full]  # [B, 4]
    ring = _ring_owners(
        _owner_map(cells, views, height, width), block_v, block_r * 2 * size, block_c * 2 * size, 2 * size
    )
    merged, ok = _merge_blocks(g, cells, cameras, kids, ring, cfg)
    if not bool(ok.any()):
        return g, cells
    kids = kids[ok]
    new_cells = torch.stack(
        (block_v[ok], block_r[ok] * 2 * size, block_c[ok] * 2 * size, torch.full_like(block_v[ok], 2 * size)), dim=-1
    )
    keep = torch.ones(len(g), dtype=torch.bool, device=cells.device)
    keep[kids.flatten()] = False
    merged = merged.subset(ok)
    return Gaussians.cat([g.subset(keep), merged]), torch.cat([cells[keep], new_cells])


def _std_along(R: Tensor, scales: Tensor, e: Tensor) -> Tensor:
    """[B] standard deviation of surfels (rotations [B, 3, 3], scales [B, 2]) along unit directions [B, 3]."""
    local = (R[..., :2] * e[..., None]).sum(-2)  # direction in the surfels' tangent axes
    return (local.square() * scales.square()).sum(-1).sqrt()


def _ring_owners(owner: Tensor, v: Tensor, r: Tensor, c: Tensor, size: int) -> Tensor:
    """[B, 8 size + 4] owners of the one-pixel ring around each size x size block (-1: none, -2: outside
    the image, where nothing of this view is to be covered)."""
    V, H, W = owner.shape
    span = torch.arange(-1, size + 1, device=owner.device)
    inner = torch.arange(size, device=owner.device)
    top_bottom_r = torch.cat((torch.full_like(span, -1), torch.full_like(span, size)))
    top_bottom_c = torch.cat((span, span))
    sides_r = torch.cat((inner, inner))
    sides_c = torch.cat((torch.full_like(inner, -1), torch.full_like(inner, size)))
    rows = r[:, None] + torch.cat((top_bottom_r, sides_r))
    cols = c[:, None] + torch.cat((top_bottom_c, sides_c))
    inside = (rows >= 0) & (rows < H) & (cols >= 0) & (cols < W)
    found = owner[v[:, None].expand_as(rows), rows.clamp(0, H - 1), cols.clamp(0, W - 1)]
    return torch.where(inside, found, -2)


def _merge_blocks(
    g: Gaussians, cells: Tensor, cameras: Cameras, kids: Tensor, ring: Tensor, cfg: CompactConfig
) -> tuple[Gaussians, Tensor]:
    """One merged surfel per block of four children [B, 4] (a b / c d), and which blocks qualify [B].

    ring: [B, R] owners of the pixels around each block (see `_ring_owners`). A block merges only
    inside a surface of its colour: the ring's pixels in the image are covered by surfels near its
    plane and of its colour, because a merged surfel's alpha falls off towards the block's border,
    where only neighbours keep the coverage (at a silhouette the background would show through), and
    its falloff reaches into the neighbours' pixels (across a colour edge it would blur it), so
    surface borders and colour edges keep full resolution.
    """
    P = g.means[kids]  # [B, 4, 3]
    normals = _oriented_normals(g, cells, cameras)[kids]  # [B, 4, 3]
    R_kids = g.rotations[kids]  # [B, 4, 3, 3]
    scales = g.scales[kids]  # [B, 4, 2]
    opac = g.opacities[kids]  # [B, 4]
    rgb = g.sh[kids][..., 0] * SH_C0 + 0.5  # [B, 4, 3] base colour (SH DC)

    centroid = P.mean(1)
    Q = P - centroid[:, None]
    _, eigvecs = torch.linalg.eigh(Q.transpose(1, 2) @ Q)
    n = eigvecs[..., 0]  # least-squares plane normal
    mean_normal = normals.sum(1)
    n = torch.where((n * mean_normal).sum(-1, keepdim=True) < 0, -n, n)
    # Child spacing: the world size of a child's pixel block at the centroid's depth in its own view
    # (the children's own distances would grow across the depth edges this is meant to detect).
    view = cells[kids[:, 0], 0]
    w2c, K = cameras.w2c.to(P)[view], cameras.K.to(P)[view]
    depth = (w2c[:, 2, :3] * centroid).sum(-1) + w2c[:, 2, 3]
    spacing = depth.abs() / K[:, 0, 0] * cells[kids[:, 0], 3]
    planar = (Q * n[:, None]).sum(-1).abs().amax(1) <= cfg.plane_tolerance * spacing
    aligned = (normals * n[:, None]).sum(-1).amin(1) >= math.cos(math.radians(cfg.normal_degrees))
    uniform = (rgb - rgb.mean(1, keepdim=True)).abs().amax((1, 2)) <= cfg.colour_tolerance
    uniform &= (opac - opac.mean(1, keepdim=True)).abs().amax(1) <= cfg.opacity_tolerance
    # Scales compared as drawn: never below the renderer's low-pass filter (see `extent` below).
    effective = torch.maximum(scales, spacing[:, None, None] / math.sqrt(LOWPASS_RHO_SCALE))
    similar = (effective.amax(1) <= cfg.scale_ratio * effective.amin(1)).all(-1)
    ring_distance = ((g.means[ring.clamp_min(0)] - centroid[:, None]) * n[:, None]).sum(-1).abs()
    # ... and of the block's colour: a merged surfel's falloff reaches into its neighbours' pixels,
    # where it would blur a colour edge.
    ring_rgb = g.sh[ring.clamp_min(0), :, 0] * SH_C0 + 0.5  # [B, R, 3]
    ring_match = (ring_rgb - rgb.mean(1, keepdim=True)).abs().amax(-1) <= cfg.colour_tolerance
    near_plane = (ring >= 0) & (ring_distance <= cfg.ring_tolerance * spacing[:, None]) & ring_match
    surrounded = (near_plane | (ring == -2)).all(1)
    ok = planar & aligned & uniform & similar & surrounded & (spacing > 0)

    # Tangent u along the block's rows (right column minus left column), v = n x u.
    u = (P[:, 1] + P[:, 3]) - (P[:, 0] + P[:, 2])
    u = u - (u * n).sum(-1, keepdim=True) * n
    fallback = R_kids[:, 0, :, 0] - (R_kids[:, 0, :, 0] * n).sum(-1, keepdim=True) * n
    u = torch.where(u.norm(dim=-1, keepdim=True) > 1e-12 * spacing[:, None], u, fallback)
    u = u / u.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    v = torch.linalg.cross(n, u, dim=-1)
    R = torch.stack((u, v, n), dim=-1)  # columns: tangent u, tangent v, normal

    # The renderer never draws a surfel thinner than its screen-space low-pass filter (a Gaussian of
    # 1/sqrt(2) px), so children one pixel apart cover their gaps even when their own scales are
    # smaller (tangent-clamped, small multipliers): their effective extent along an axis is at least
    # 1/sqrt(2) of their spacing. The merged surfel gets twice the effective extent, so it covers
    # its block as the children did.
    step_u = 0.5 * ((P[:, 1] + P[:, 3]) - (P[:, 0] + P[:, 2]))  # between the children's columns
    step_v = 0.5 * ((P[:, 2] + P[:, 3]) - (P[:, 0] + P[:, 1]))  # between their rows

    def extent(axis: Tensor, step: Tensor) -> Tensor:  # [B, 3] -> [B] twice the children's effective extent
        sigma = sum(_std_along(R_kids[:, k], scales[:, k], axis) for k in range(4)) / 4
        floor = (step * axis).sum(-1).abs() / math.sqrt(LOWPASS_RHO_SCALE)
        return 2 * torch.maximum(sigma, floor)

    mass = opac * scales[..., 0] * scales[..., 1]  # integrated alpha of each child
    weights = mass / mass.sum(1, keepdim=True).clamp_min(1e-30)
    sh = (g.sh[kids] * weights[..., None, None]).sum(1)
    merged_scales = torch.stack((extent(u, step_u), extent(v, step_v)), dim=-1)
    covariances = None
    if g.explicit_covariances is not None:
        # The same rule for explicit covariances: the merged tangent extents, and twice the children's
        # mean thickness along the normal.
        children = g.explicit_covariances[kids]  # [B, 4, 3, 3]
        thickness = 4 * (weights * torch.einsum("bi,bkij,bj->bk", n, children, n)).sum(1)
        variances = torch.cat((merged_scales.square(), thickness[:, None]), dim=-1)
        covariances = (R * variances[:, None, :]) @ R.transpose(-1, -2)
    merged = Gaussians(
        means=centroid,
        quats=matrix_to_quat(R),
        scales=merged_scales,
        opacities=opac.mean(1),
        sh=sh,
        explicit_covariances=covariances,
        validate=False,
    )
    return merged, ok
