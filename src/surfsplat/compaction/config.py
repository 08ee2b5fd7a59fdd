"""The compaction levels: `CompactConfig` and the presets of `--compact LEVEL`."""

from __future__ import annotations

from dataclasses import dataclass, replace

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
    scale_floor: bool = False  # survivors' tangent scales at least their footprint's low-pass size (see floor_scales)
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
