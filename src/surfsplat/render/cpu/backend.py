"""Torch-facing side of the compiled CPU renderer: per-camera planning and the autograd function.

Per camera:
1. torch (autograd): camera-frame means mu = R_cw x + t in float64, computed with the very
   expression of the torch backend, so culling and the depth order agree with it bit for bit;
2. kernels (no autograd): projection, culling, stable depth sort, tile lists;
3. torch (autograd): colour from SH and the camera-facing normal of the survivors only, again with
   the torch backend's own helpers (the sign of an edge-on normal is decided identically);
4. `_Rasterize` (autograd.Function): compositing forward; backward = compositing backward, then the
   chain rule through the projection, both in the kernels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numba
import torch
from torch import Tensor

from ...checks import SurfSplatInputError
from ...gaussians import Gaussians
from ...geometry.cameras import Cameras
from ..torch_backend import _camera_facing, _colors
from ..types import RenderMode
from . import kernels
from .settings import CpuRenderSettings


@dataclass
class _Plan:
    """Everything the compositing needs for one camera, from the projection and binning kernels."""

    surfel: bool
    order: np.ndarray  # [M] input index of each survivor, front to back
    geom: np.ndarray  # [M, GEOM_SIZE] survivors' per-pixel coefficients
    box: np.ndarray  # [M, 4] survivors' inclusive pixel boxes (col0, col1, row0, row1)
    tile_start: np.ndarray  # [tiles + 1]
    tile_ids: np.ndarray  # [pairs] positions in `order`, per tile front to back
    R_cw: np.ndarray  # [3, 3] float64
    K: np.ndarray  # [3, 3] float64
    width: int
    height: int
    tile: int
    tiles_x: int
    chunk: int


def _np64(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to(torch.float64).numpy())


def _plan(
    mode: RenderMode, mu: Tensor, shape_src: Tensor, opacities: Tensor, scales: Tensor | None,
    R_cw: np.ndarray, K: np.ndarray, width: int, height: int, settings: CpuRenderSettings,
) -> _Plan:
    """Projection, culling, depth sort and tile lists (no autograd). shape_src: rotations or covariances."""
    n = mu.shape[0]
    mu_np, src_np, opac_np = _np64(mu), _np64(shape_src), _np64(opacities)
    geom = np.empty((n, kernels.GEOM_SIZE))
    box = np.empty((n, 4), dtype=np.int64)
    keep = np.empty(n, dtype=np.bool_)
    args = (width, height, settings.near_plane, settings.far_plane, geom, box, keep)
    if mode == "surfel":
        assert scales is not None
        kernels.project_surfels(mu_np, src_np, _np64(scales), opac_np, R_cw, K, *args)
    else:
        kernels.project_ewa(mu_np, src_np, opac_np, R_cw, K, *args)
    tile = settings.tile_size
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    order, tile_start, tile_ids = kernels.sort_and_bin(keep, mu_np[:, 2].copy(), box, tile, tiles_x, tiles_y)
    geom_sorted = np.empty((order.shape[0], kernels.GEOM_SIZE))
    box_sorted = np.empty((order.shape[0], 4), dtype=np.int64)
    kernels.gather_rows(geom, order, geom_sorted)
    kernels.gather_rows(box, order, box_sorted)
    return _Plan(mode == "surfel", order, geom_sorted, box_sorted, tile_start, tile_ids, R_cw, K,
                 width, height, tile, tiles_x, settings.parallel_chunk)


class _Rasterize(torch.autograd.Function):
    """Compositing of one camera with a hand-written backward (see `kernels.composite_backward`).

    Inputs: mu [N, 3] camera-frame means (float64), shape [N, 3, 3] world rotations (surfel) or
    world covariances (ewa), scales [N, 2] (surfel; ignored for ewa), opacities [N], features [M, 6]
    (colour and oriented normal of the survivors, in `plan.order`).
    Outputs: features [H, W, 6], alpha [H, W], depth [H, W], un-normalized, in the features' dtype.
    """

    @staticmethod
    def forward(ctx, mu, shape, scales, opacities, features, plan: _Plan):
        H, W = plan.height, plan.width
        feat_np = _np64(features)
        out_feat = np.empty((H, W, kernels.FEATURES))
        out_trans = np.empty((H, W))
        out_depth = np.empty((H, W))
        out_last = np.empty((H, W), dtype=np.int64)
        done = np.empty((H, W), dtype=np.bool_)
        with numba.parallel_chunksize(plan.chunk):
            kernels.composite_forward(
                plan.surfel, plan.geom, feat_np, plan.box, plan.tile_start, plan.tile_ids, W, H, plan.tile,
                plan.tiles_x, out_feat, out_trans, out_depth, out_last, done,
            )
        ctx.plan = plan
        ctx.feat_np = feat_np
        ctx.trans = out_trans
        ctx.last = out_last
        ctx.save_for_backward(mu, shape, scales, opacities, features)
        dtype = features.dtype
        return (
            torch.from_numpy(out_feat).to(dtype),
            torch.from_numpy(1.0 - out_trans).to(dtype),
            torch.from_numpy(out_depth).to(dtype),
        )

    @staticmethod
    def backward(ctx, g_feat, g_alpha, g_depth):
        plan: _Plan = ctx.plan
        mu, shape, scales, opacities, features = ctx.saved_tensors
        H, W = plan.height, plan.width
        M = plan.order.shape[0]
        g_feat_np = np.zeros((H, W, kernels.FEATURES)) if g_feat is None else _np64(g_feat)
        g_alpha_np = np.zeros((H, W)) if g_alpha is None else _np64(g_alpha)
        g_depth_np = np.zeros((H, W)) if g_depth is None else _np64(g_depth)
        grads = np.zeros((numba.get_num_threads(), M, kernels.GRAD_SIZE))
        with numba.parallel_chunksize(plan.chunk):
            kernels.composite_backward(
                plan.surfel, plan.geom, ctx.feat_np, plan.box, plan.tile_start, plan.tile_ids, W, H, plan.tile,
                plan.tiles_x, ctx.trans, ctx.last, g_feat_np, g_alpha_np, g_depth_np,
                np.empty((H, W)), np.empty((H, W)), grads,
            )
        summed = np.empty((M, kernels.GRAD_SIZE))
        kernels.sum_thread_grads(grads, summed)
        n = mu.shape[0]
        g_mu = np.zeros((n, 3))
        g_shape = np.zeros((n, 3, 3))
        g_scales = np.zeros((n, 2))
        g_opac = np.zeros(n)
        mu_np, shape_np, opac_np = _np64(mu), _np64(shape), _np64(opacities)
        if plan.surfel:
            kernels.surfel_project_backward(
                plan.order, mu_np, shape_np, _np64(scales), opac_np, plan.R_cw, plan.K, plan.geom, summed,
                g_mu, g_shape, g_scales, g_opac,
            )
        else:
            kernels.ewa_project_backward(
                plan.order, mu_np, shape_np, opac_np, plan.R_cw, plan.K, summed, g_mu, g_shape, g_opac
            )
        g_features = summed[:, kernels.GRAD_FEAT : kernels.GRAD_FEAT + kernels.FEATURES]

        def out(grad: np.ndarray, like: Tensor, needed: bool) -> Tensor | None:
            return torch.from_numpy(np.ascontiguousarray(grad)).to(like.dtype) if needed else None

        need = ctx.needs_input_grad
        return (
            out(g_mu, mu, need[0]),
            out(g_shape, shape, need[1]),
            out(g_scales, scales, need[2] and plan.surfel),
            out(g_opac, opacities, need[3]),
            out(g_features, features, need[4]),
            None,
        )


def render_cpu(
    gaussians: Gaussians, cameras: Cameras, width: int, height: int, mode: RenderMode,
    settings: CpuRenderSettings | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Un-normalized colour [C, 3, H, W], alpha [C, 1, H, W], depth [C, 1, H, W], normal [C, 3, H, W].

    The same function as `render_torch` (float rounding aside), differentiable with respect to the
    Gaussians (not the cameras).
    """
    settings = settings or CpuRenderSettings()
    g = gaussians
    if g.means.device.type != "cpu":
        raise SurfSplatInputError(f"backend: 'cpu' renders tensors on the CPU, got Gaussians on {g.means.device}")
    if cameras.c2w.requires_grad or cameras.K.requires_grad:
        raise SurfSplatInputError("cameras: the 'cpu' backend does not differentiate cameras; use backend='torch'")
    dt = torch.float64
    rotations = g.rotations
    shape = g.covariances if mode == "ewa" else rotations
    w2c = cameras.w2c.to(g.means)
    K_all = cameras.K.to(g.means)
    centers = cameras.centers.to(g.means)
    outs = []
    for c in range(len(cameras)):
        R_cw_t, t_cw = w2c[c, :3, :3].to(dt), w2c[c, :3, 3].to(dt)
        mu = g.means.to(dt) @ R_cw_t.T + t_cw  # [N, 3] (the torch backend's expression)
        plan = _plan(
            mode, mu, shape, g.opacities, g.scales if mode == "surfel" else None,
            _np64(R_cw_t), _np64(K_all[c]), width, height, settings,
        )
        idx = torch.from_numpy(plan.order)
        normals = _camera_facing(rotations[idx, :, 2], mu[idx].to(g.means.dtype), w2c[c, :3, :3])
        colors = _colors(g.sh[idx], g.means[idx], centers[c])
        features = torch.cat((colors, normals), dim=-1)  # [M, 6]
        scales = g.scales if mode == "surfel" else g.opacities.new_zeros(0)
        outs.append(_Rasterize.apply(mu, shape, scales, g.opacities, features, plan))
    color = torch.stack([o[0][..., 0:3] for o in outs]).permute(0, 3, 1, 2)
    normal = torch.stack([o[0][..., 3:6] for o in outs]).permute(0, 3, 1, 2)
    alpha = torch.stack([o[1] for o in outs])[:, None]
    depth = torch.stack([o[2] for o in outs])[:, None]
    return color, alpha, depth, normal
