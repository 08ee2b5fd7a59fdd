"""Cells: the pixel block each surfel stands for, which surfel owns each pixel, its footprint and scale floor."""

from __future__ import annotations

import math
from dataclasses import replace

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..geometry.pixels import pixel_footprints
from ..render.types import LOWPASS_RHO_SCALE


def owner_map(cells: Tensor, views: int, height: int, width: int) -> Tensor:
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


def oriented_normals(g: Gaussians, cells: Tensor, cameras: Cameras) -> Tensor:
    """[N, 3] unit normals facing the camera of each surfel's own view."""
    n = g.normals
    to_camera = cameras.centers.to(g.means)[cells[:, 0]] - g.means
    return torch.where((n * to_camera).sum(-1, keepdim=True) < 0, -n, n)


def cell_footprints(g: Gaussians, cells: Tensor, cameras: Cameras) -> Tensor:
    """[N] world size of each surfel's pixel block in its own view (pixel footprint times block size)."""
    return pixel_footprints(g, cameras, views=cells[:, 0]) * cells[:, 3]


def floor_scales(g: Gaussians, footprint: Tensor, which: Tensor | None = None) -> Gaussians:
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
