"""Merging: 2 x 2 blocks of coplanar, like-coloured surfels become one, up the quadtree; scale floors."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..geometry.rotations import matrix_to_quat
from ..geometry.sh import SH_C0
from ..render.types import LOWPASS_RHO_SCALE
from .cells import oriented_normals, owner_map
from .config import CompactConfig


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
        owner_map(cells, views, height, width), block_v, block_r * 2 * size, block_c * 2 * size, 2 * size
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
    normals = oriented_normals(g, cells, cameras)[kids]  # [B, 4, 3]
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
