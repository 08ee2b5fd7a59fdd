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
   `floor_scales`), closing at x4 the gaps removed neighbours used to fill.
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

Modules: `config` (the levels), `compact` (the rounds), `prune`, `dedup`, `merge`, `refit`.
"""

from .compact import CompactResult, compact, compact_surfels
from .config import DEFAULT_LEVEL, LEVELS, CompactConfig, level_config
from .prune import blending_weights
from .refit import refit

__all__ = [
    "DEFAULT_LEVEL",
    "LEVELS",
    "CompactConfig",
    "CompactResult",
    "blending_weights",
    "compact",
    "compact_surfels",
    "level_config",
    "refit",
]
