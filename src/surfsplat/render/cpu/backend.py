"""Torch-facing side of the compiled CPU renderer: one autograd function per camera.

No torch op runs per Gaussian: quaternion to rotation, camera transform, SH colour, normal
orientation, projection, culling, sorting, binning, compositing and all their gradients run in the
kernels of `kernels.py`, in float64, on every core. Torch only hands tensors over (a NumPy view
or one cast) - which also keeps torch's own thread pool out of the way of the kernels'.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import torch
from torch import Tensor

from ...checks import SurfSplatInputError
from ...gaussians import Gaussians
from ...geometry.cameras import Cameras
from ..types import RenderMode
from . import kernels
from .settings import CpuRenderSettings

_SCRATCH = 64  # per-thread work space of the projection kernels (SH basis and its gradient)


@dataclass
class _Camera:
    """One camera as the kernels take it (float64 NumPy)."""

    R_cw: np.ndarray  # [3, 3] world-to-camera rotation
    t_cw: np.ndarray  # [3]
    center: np.ndarray  # [3] camera centre in the world
    K: np.ndarray  # [3, 3]
    width: int
    height: int


@dataclass
class _Plan:
    """What the forward pass leaves for the backward pass."""

    order: np.ndarray  # [M] input index of each survivor, front to back
    geom: np.ndarray  # [M, GEOM_SIZE] survivors' per-pixel coefficients
    box: np.ndarray  # [M, 4] survivors' inclusive pixel boxes (col0, col1, row0, row1)
    features: np.ndarray  # [M, 6] survivors' colour and oriented normal
    flip: np.ndarray  # [N] +-1: the sign given to each normal
    tile_start: np.ndarray  # [tiles + 1]
    tile_ids: np.ndarray  # [pairs] positions in `order`, per tile front to back
    trans: np.ndarray  # [H, W] final transmittance
    last: np.ndarray  # [H, W] 1 + tile-list position of each pixel's last blended Gaussian
    tiles_x: int


def _np64(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to(torch.float64).numpy())


def _inputs(means, quats, scales, opacities, sh, covariances):
    return (
        _np64(means), _np64(quats), _np64(scales), _np64(opacities), _np64(sh),
        _np64(covariances) if covariances is not None else np.zeros((0, 3, 3)),
    )


class _Rasterize(torch.autograd.Function):
    """Render one camera; backward = compositing backward then the projection's chain rule.

    Inputs: means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 2], opacities [N], sh [N, 3, B],
    covariances [N, 3, 3] or None (EWA with the surfels' own thin covariances).
    Outputs (un-normalized, the means' dtype): colour and normal [H, W, 6], alpha [H, W], depth [H, W].
    """

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, sh, covariances, surfel: bool, camera: _Camera,
                settings: CpuRenderSettings):
        x, q, sc, op, shc, cov = _inputs(means, quats, scales, opacities, sh, covariances)
        n = x.shape[0]
        rot = np.empty((n, 3, 3))
        kernels.quats_to_rotations(q, rot)
        W, H, tile = camera.width, camera.height, settings.tile_size
        threads = numba.get_num_threads()
        geom = np.empty((n, kernels.GEOM_SIZE))
        box = np.empty((n, 4), dtype=np.int64)
        keep = np.empty(n, dtype=np.bool_)
        depth = np.empty(n)
        features = np.empty((n, kernels.FEATURES))
        flip = np.empty(n)
        kernels.project(
            surfel, x, rot, sc, op, shc, cov, camera.R_cw, camera.t_cw, camera.center, camera.K, W, H,
            settings.near_plane, settings.far_plane, geom, box, keep, depth, features, flip,
            np.empty((threads, _SCRATCH)), np.empty((threads, 2, 3, 3)),
        )
        tiles_x, tiles_y = -(-W // tile), -(-H // tile)
        order, tile_start, tile_ids = kernels.sort_and_bin(keep, depth, box, tile, tiles_x, tiles_y)
        geom, box, features = kernels.gather_rows(geom, order), kernels.gather_rows(box, order), kernels.gather_rows(
            features, order
        )
        out_feat = np.empty((H, W, kernels.FEATURES))
        out_trans = np.empty((H, W))
        out_depth = np.empty((H, W))
        out_last = np.empty((H, W), dtype=np.int64)
        with numba.parallel_chunksize(settings.parallel_chunk):
            kernels.composite_forward(
                surfel, geom, features, box, tile_start, tile_ids, W, H, tile, tiles_x,
                out_feat, out_trans, out_depth, out_last,
            )
        ctx.surfel, ctx.camera, ctx.settings = surfel, camera, settings
        ctx.plan = _Plan(order, geom, box, features, flip, tile_start, tile_ids, out_trans, out_last, tiles_x)
        ctx.save_for_backward(means, quats, scales, opacities, sh, covariances)
        dtype = means.dtype
        return (
            torch.from_numpy(out_feat).to(dtype),
            torch.from_numpy(1.0 - out_trans).to(dtype),
            torch.from_numpy(out_depth).to(dtype),
        )

    @staticmethod
    def backward(ctx, g_feat, g_alpha, g_depth):
        plan: _Plan = ctx.plan
        camera: _Camera = ctx.camera
        settings: CpuRenderSettings = ctx.settings
        means, quats, scales, opacities, sh, covariances = ctx.saved_tensors
        W, H = camera.width, camera.height
        M = plan.order.shape[0]
        threads = numba.get_num_threads()
        g_feat_np = np.zeros((H, W, kernels.FEATURES)) if g_feat is None else _np64(g_feat)
        g_alpha_np = np.zeros((H, W)) if g_alpha is None else _np64(g_alpha)
        g_depth_np = np.zeros((H, W)) if g_depth is None else _np64(g_depth)
        per_thread = np.zeros((threads, M, kernels.GRAD_SIZE))
        with numba.parallel_chunksize(settings.parallel_chunk):
            kernels.composite_backward(
                ctx.surfel, plan.geom, plan.features, plan.box, plan.tile_start, plan.tile_ids, W, H,
                settings.tile_size, plan.tiles_x, plan.trans, plan.last, g_feat_np, g_alpha_np, g_depth_np, per_thread,
            )
        grads = kernels.sum_thread_grads(per_thread)
        x, q, sc, op, shc, cov = _inputs(means, quats, scales, opacities, sh, covariances)
        n = x.shape[0]
        rot = np.empty((n, 3, 3))
        kernels.quats_to_rotations(q, rot)
        g_means, g_rot, g_scales = np.zeros((n, 3)), np.zeros((n, 3, 3)), np.zeros((n, 2))
        g_opac, g_sh, g_cov = np.zeros(n), np.zeros_like(shc), np.zeros_like(cov)
        kernels.project_backward(
            ctx.surfel, plan.order, x, rot, sc, op, shc, cov, camera.R_cw, camera.t_cw, camera.center, camera.K,
            plan.geom, plan.flip, grads, g_means, g_rot, g_scales, g_opac, g_sh, g_cov,
            np.empty((threads, _SCRATCH)), np.empty((threads, 2, 3, 3)),
        )
        g_quats = np.empty((n, 4))
        kernels.quats_backward(q, g_rot, g_quats)

        def out(grad: np.ndarray, like: Tensor | None, index: int) -> Tensor | None:
            if like is None or not ctx.needs_input_grad[index]:
                return None
            return torch.from_numpy(grad).to(like.dtype)

        return (
            out(g_means, means, 0), out(g_quats, quats, 1), out(g_scales, scales, 2), out(g_opac, opacities, 3),
            out(g_sh, sh, 4), out(g_cov, covariances, 5), None, None, None,
        )


def render_cpu(
    gaussians: Gaussians, cameras: Cameras, width: int, height: int, mode: RenderMode,
    settings: CpuRenderSettings | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Un-normalized colour [C, 3, H, W], alpha [C, 1, H, W], depth [C, 1, H, W], normal [C, 3, H, W].

    The function of `render_torch` (float rounding aside), differentiable with respect to the
    Gaussians; camera parameters get no gradient (the dispatcher sends such requests to torch).
    """
    settings = settings or CpuRenderSettings()
    g = gaussians
    if g.means.device.type != "cpu":
        raise SurfSplatInputError(f"backend: 'cpu' renders tensors on the CPU, got Gaussians on {g.means.device}")
    if cameras.c2w.requires_grad or cameras.K.requires_grad:
        raise SurfSplatInputError("cameras: the 'cpu' backend does not differentiate cameras; use backend='torch'")
    covariances = g.explicit_covariances if mode == "ewa" else None
    w2c = _np64(cameras.w2c.to(g.means))
    K = _np64(cameras.K.to(g.means))
    centers = _np64(cameras.centers.to(g.means))
    outs = []
    for c in range(len(cameras)):
        camera = _Camera(
            np.ascontiguousarray(w2c[c, :3, :3]), np.ascontiguousarray(w2c[c, :3, 3]), centers[c], K[c], width, height
        )
        outs.append(
            _Rasterize.apply(g.means, g.quats, g.scales, g.opacities, g.sh, covariances, mode == "surfel", camera, settings)
        )
    color = torch.stack([o[0][..., 0:3] for o in outs]).permute(0, 3, 1, 2)
    normal = torch.stack([o[0][..., 3:6] for o in outs]).permute(0, 3, 1, 2)
    alpha = torch.stack([o[1] for o in outs])[:, None]
    depth = torch.stack([o[2] for o in outs])[:, None]
    return color, alpha, depth, normal
