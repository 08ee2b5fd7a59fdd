"""Deduplication: a surfel another view already covers on the same plane is absorbed by it."""

from __future__ import annotations

import math
from dataclasses import replace

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from .cells import cell_footprints, floor_scales, oriented_normals, owner_map
from .config import CompactConfig


def _duplicate_cover(
    g: Gaussians, cells: Tensor, cameras: Cameras, height: int, width: int, cfg: CompactConfig
) -> Tensor:
    """[N] for each surfel of a view j > 0 lying on a surface an earlier view's surfels cover, the index
    of the covering surfel; -1 for the others."""
    views = len(cameras)
    keep = torch.ones(len(g), dtype=torch.bool, device=g.means.device)
    owner = owner_map(cells, views, height, width)
    normals = oriented_normals(g, cells, cameras)
    w2c = cameras.w2c.to(g.means)
    K = cameras.K.to(g.means)
    cos_tol = math.cos(math.radians(cfg.dedup_normal_degrees))
    # World size of one pixel of each surfel's own view at its depth.
    own = cells[:, 0]
    footprint_own = cell_footprints(g, cells, cameras) / cells[:, 3]
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
    return floor_scales(g, footprint, hit)


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
