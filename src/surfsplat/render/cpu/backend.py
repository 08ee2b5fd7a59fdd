"""Torch-facing side of the compiled CPU renderer: one autograd function for all cameras of a call.

No torch op runs per Gaussian: quaternion to rotation, camera transform, SH colour, normal
orientation, projection, culling, sorting, binning, compositing and all their gradients run in the
kernels of `kernels.py`, the heavy ones on every core (the light passes on one: a parallel region
costs a thread wake-up, which beside another busy process can take longer than the pass). Torch only
hands tensors over (a NumPy view or one cast) - which also keeps torch's own thread pool out of the
way of the kernels'. `normalize_cpu` does the dispatcher's forced-alpha normalization and background
the same way, so a render's whole-image work is compiled too. The inputs are converted
and the rotations built once per call, whatever the number of cameras; the backward sums every
camera's gradients into one set of buffers, camera after camera, so the result is the same for any
number of threads and no per-camera gradient is ever materialised.

Precision (`CpuRenderSettings.precision`): the per-Gaussian work (projection and its chain rule,
under a tenth of the time) always runs in float64 from float64 copies of the inputs; the per-pair
work (compositing forward and backward, the rest) runs in float64 or float32, the latter from
per-Gaussian coefficients rounded once to float32 about their stored centres - the torch
backend's split, which keeps sub-pixel accuracy on large images. float64 is the exact reference.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numba
import numpy as np
import torch
from torch import Tensor

from ...geometry.cameras import Cameras
from ...geometry.gaussians import Gaussians
from ...utils.checks import SurfSplatInputError
from ..types import EWA_DILATION, LOWPASS_RHO_SCALE, RenderMode, screen_filter
from . import kernels
from .settings import CpuRenderSettings

# Per-thread work space of the projection kernels (SH basis and its derivatives), each row followed
# by 8 unused floats (a cache line): the rows are written for every Gaussian, and two threads writing
# one line would pass it back and forth between their cores.
_SCRATCH = 64 + 8
_NP_DTYPES = {
    torch.float64: np.float64,
    torch.float32: np.float32,
    torch.float16: np.float16,
    torch.bfloat16: np.float32,
}
_DIRECT_GRAD = (torch.float32, torch.float64)  # gradient dtypes the kernels may write directly
# Gaussians a thread takes at a time in the per-Gaussian kernels: handed out as threads come free,
# so a thread that waits for a core (beside another busy process) does not hold back a fixed half.
_GAUSSIAN_CHUNK = 1024
# Pixels from which the forced-alpha normalization runs on every thread: a parallel region has to
# wake the other threads, and beside another busy process a woken thread waits for a core for up to
# the scheduler's latency (12 ms measured on 2 cores); a 256 x 256 image takes 0.2 ms on one.
_PARALLEL_PIXELS = 1 << 18
# Survivors from which the tile binning runs on every thread (`_prepare`).
_PARALLEL_SURVIVORS = 250_000


@dataclass
class _Camera:
    """One camera as the kernels take it (float64 NumPy, whatever the precision)."""

    R_cw: np.ndarray  # [3, 3] world-to-camera rotation
    t_cw: np.ndarray  # [3]
    center: np.ndarray  # [3] camera centre in the world
    K: np.ndarray  # [3, 3]
    width: int
    height: int
    # the screen-space filter (`kernels.project`): surfels' rho2d coefficient and EWA's dilation,
    # 2DGS's and 3DGS's, or those of a camera `filter_zoom` times coarser (`render`)
    lowpass: float = LOWPASS_RHO_SCALE
    dilation: float = EWA_DILATION


@dataclass
class _Plan:
    """Survivors of culling, front to back (survivor m is the m-th nearest), and their tile lists:
    the work of one camera."""

    # Per Gaussian in input order, as the projection wrote them (culled Gaussians' rows are unused):
    geom: np.ndarray  # [N, GEOM_SIZE] per-pixel coefficients (the compositing dtype)
    box: np.ndarray  # [N, 4] inclusive pixel boxes (col0, col1, row0, row1)
    features: np.ndarray  # [N, 6] colour and oriented normal (the compositing dtype)
    flip: np.ndarray  # [N] +-1: the sign given to each normal
    lit: np.ndarray  # [N] bit ch: colour channel ch not clamped at 0
    tile_start: np.ndarray  # [tiles + 1]
    tile_ids: np.ndarray  # [pairs] the survivors touching each tile (input indices), front to back
    pair_start: np.ndarray  # [M + 1] survivor m's entries of tile_ids are
    pair_of: np.ndarray  # [pairs]   pair_of[pair_start[m]:pair_start[m + 1]]
    rank: np.ndarray  # [N] each Gaussian's survivor index m (-1: culled)
    order: np.ndarray  # [M] each survivor's input index (the inverse of rank)
    tiles_x: int


class _Held(threading.local):
    """Work arrays each thread keeps from one backward pass to the next, by name."""

    def __init__(self) -> None:
        self.arrays: dict[tuple[str, type], np.ndarray] = {}


_held = _Held()


def _held_empty(name: str, shape: tuple[int, ...], dtype: type) -> np.ndarray:
    """np.empty(shape, dtype), from a buffer this thread keeps for `name` from call to call.

    For the backward's largest work arrays, whose contents never outlive the call: a fresh array of
    this size is fresh memory from the system every call (glibc maps anything over 32 MB anew),
    which the kernel has to fault in and zero, page by page. That took 90-110 ms of system time in
    some forward+backward calls at 1024 x 1024, against 8 ms in others. A buffer more than 4x
    larger than asked for is let go, so one large render does not hold its memory for good.
    """
    size = math.prod(shape)
    buffer = _held.arrays.get((name, dtype))
    if buffer is None or buffer.size < size or buffer.size > 4 * size:
        buffer = np.empty(max(size, 1), dtype=dtype)
        _held.arrays[(name, dtype)] = buffer
    return buffer[:size].reshape(shape)


def _np(t: Tensor, dtype: type[np.floating] = np.float64) -> np.ndarray:
    # NumPy casts single-threaded; a torch cast would wake torch's thread pool for every tensor.
    t = t.detach()
    if t.dtype == torch.bfloat16:  # NumPy has no bfloat16
        t = t.float()
    return np.ascontiguousarray(t.numpy(), dtype=dtype)


def _np64(t: Tensor) -> np.ndarray:
    return _np(t, np.float64)


def compositing_dtype(settings: CpuRenderSettings, dtype: torch.dtype) -> type[np.floating]:
    """The float type of the per-pair work for inputs of `dtype`: `settings.precision`, where
    "auto" is float64 for float64 inputs and float32 for any other float."""
    if settings.precision == "auto":
        return np.float64 if dtype == torch.float64 else np.float32
    return np.float64 if settings.precision == "float64" else np.float32


def _tensor(a: np.ndarray, dtype: torch.dtype) -> Tensor:
    out = torch.from_numpy(np.ascontiguousarray(a, dtype=_NP_DTYPES[dtype]))
    return out if out.dtype == dtype else out.to(dtype)


def _np_read(t: Tensor) -> np.ndarray:
    """A float32 or float64 tensor as it is (a view), any other float as float64.

    For the inputs that the projection kernels only ever meet with a float64 operand (means and SH
    coefficients: camera transform, view direction, SH sums) or cast to float64 first (quaternions):
    numba promotes a float32 element to float64 there, so reading the float32 array gives the
    results of a float64 copy bit for bit, without the copy (the SH coefficients are most of the
    per-Gaussian data).
    """
    return _np(t, np.float32 if t.dtype == torch.float32 else np.float64)


def _inputs(means, quats, scales, opacities, sh, covariances):
    return (
        _np_read(means),
        _np_read(quats),
        _np64(scales),
        _np64(opacities),
        _np_read(sh),
        _np64(covariances) if covariances is not None else np.zeros((0, 3, 3)),
    )


def _cameras(cameras: Cameras, width: int, height: int, filter_zoom: float = 1.0) -> list[_Camera]:
    w2c = _np64(cameras.w2c)
    K = _np64(cameras.K)
    centers = _np64(cameras.centers)
    lowpass, dilation = screen_filter(filter_zoom)
    return [
        _Camera(
            np.ascontiguousarray(w2c[c, :3, :3]),
            np.ascontiguousarray(w2c[c, :3, 3]),
            centers[c],
            K[c],
            width,
            height,
            lowpass,
            dilation,
        )
        for c in range(len(cameras))
    ]


def _convention_args(settings: CpuRenderSettings) -> tuple[float, float, bool]:
    """The kernels' form of the settings' `RenderConventions`: (low-pass sigma or 0, clamp or inf, release support)."""
    sigma = settings.lowpass_center_sigma
    clamp = settings.ewa_jacobian_clamp
    return (
        0.0 if sigma is None else float(sigma),
        math.inf if clamp is None else float(clamp),
        settings.ewa_support == "release",
    )


def _prepare(
    surfel: bool,
    inputs: tuple,
    rot: np.ndarray,
    camera: _Camera,
    settings: CpuRenderSettings,
    dtype: type[np.floating],
    fill_rotations: bool,
) -> _Plan:
    """Projection, culling, depth sort and tile lists of one camera (the kernels' first half),
    with the coefficients and features in `dtype` (the depth sort key stays float64). rot [N, 3, 3]
    holds the rotations of the quaternions: filled by the projection when fill_rotations (a call's
    first camera), read otherwise."""
    x, q, sc, op, shc, cov = inputs
    n = x.shape[0]
    threads = numba.get_num_threads()
    geom = np.empty((n, kernels.GEOM_SIZE), dtype=dtype)
    box = np.empty((n, 4), dtype=np.int64)
    bin_box = np.empty((n, 4), dtype=np.int64)
    keep = np.empty(n, dtype=np.bool_)
    depth = np.empty(n)
    features = np.empty((n, kernels.FEATURES), dtype=dtype)
    flip = np.empty(n)
    lit = np.empty(n, dtype=np.uint8)
    with numba.parallel_chunksize(_GAUSSIAN_CHUNK):
        kernels.project(
            surfel,
            x,
            q,
            fill_rotations,
            rot,
            sc,
            op,
            shc,
            cov,
            camera.R_cw,
            camera.t_cw,
            camera.center,
            camera.K,
            camera.width,
            camera.height,
            settings.near_plane,
            settings.far_plane,
            *_convention_args(settings),
            camera.lowpass,
            camera.dilation,
            geom,
            box,
            bin_box,
            keep,
            depth,
            features,
            flip,
            lit,
            np.empty((threads, _SCRATCH)),
            np.empty((threads, 2, 3, 3)),
        )
    tile = settings.tile_size
    tiles_x, tiles_y = -(-camera.width // tile), -(-camera.height // tile)
    order = kernels.depth_order(keep, depth)
    # One run of survivors a thread, taken as threads come free: more runs scatter the writes over
    # more places (at 1024 x 1024, 4 runs a thread took 7.2 ms and 1 run 5.1 ms; one thread 7.5 ms).
    # Below _PARALLEL_SURVIVORS one thread: its two parallel regions cost more than they save
    # beside another busy process (a 100k-surfel fit step went from 1.66x to 1.93x its time alone).
    parts = threads if order.shape[0] >= _PARALLEL_SURVIVORS else 1
    rank = np.full(n, -1, dtype=np.int64)
    with numba.parallel_chunksize(1):
        tile_start, tile_ids, pair_start, pair_of = kernels.bin_tiles(
            bin_box, order, tile, tiles_x, tiles_y, parts, rank
        )
    return _Plan(
        geom,
        box,
        features,
        flip,
        lit,
        tile_start,
        tile_ids,
        pair_start,
        pair_of,
        rank,
        order,
        tiles_x,
    )


class _Rasterize(torch.autograd.Function):
    """Render every camera; backward = per camera the compositing backward then the projection's
    chain rule, added into one set of gradient buffers in camera order.

    Inputs: means [N, 3], quats [N, 4] (w, x, y, z), scales [N, 2], opacities [N], sh [N, 3, B],
    covariances [N, 3, 3] or None (EWA with the surfels' own thin covariances).
    Outputs (un-normalized, the means' dtype): colour [C, 3, H, W], alpha [C, 1, H, W],
    depth [C, 1, H, W], normal [C, 3, H, W], and with `distortion` 2DGS's depth distortion
    [C, 1, H, W]. Compositing runs in `compositing_dtype`; gradients come back in each input's dtype.
    probe [C, N, 2] or None (surfels): its "gradient" is the absolute screen gradient (`render`'s
    absgrad), summed in the compositing backward beside the others only when it is given.
    """

    @staticmethod
    def forward(
        ctx,
        means,
        quats,
        scales,
        opacities,
        sh,
        covariances,
        surfel: bool,
        cameras: list[_Camera],
        settings: CpuRenderSettings,
        distortion: bool = False,
        probe: Tensor | None = None,
    ):
        inputs = _inputs(means, quats, scales, opacities, sh, covariances)
        rot = np.empty((means.shape[0], 3, 3))
        ft = compositing_dtype(settings, means.dtype)
        C, W, H = len(cameras), cameras[0].width, cameras[0].height
        color, normal = np.empty((C, 3, H, W), dtype=ft), np.empty((C, 3, H, W), dtype=ft)
        depth, trans = np.empty((C, 1, H, W), dtype=ft), np.empty((C, 1, H, W), dtype=ft)
        last = np.empty((C, H, W), dtype=np.int32)
        # Per camera the distortion and each ray's moment sum w z (which the backward needs).
        moments = np.empty((C, 2, H, W), dtype=ft) if distortion else None
        plans = []
        for c, camera in enumerate(cameras):
            plan = _prepare(surfel, inputs, rot, camera, settings, ft, fill_rotations=c == 0)
            with numba.parallel_chunksize(settings.parallel_chunk):
                kernels.composite_forward(
                    surfel,
                    camera.lowpass,
                    plan.geom,
                    plan.features,
                    plan.box,
                    plan.tile_start,
                    plan.tile_ids,
                    W,
                    H,
                    settings.tile_size,
                    plan.tiles_x,
                    color[c],
                    normal[c],
                    depth[c, 0],
                    trans[c, 0],
                    last[c],
                    None if moments is None else moments[c],
                )
            plans.append(plan)
        ctx.surfel, ctx.cameras, ctx.settings, ctx.moments = surfel, cameras, settings, moments
        ctx.absgrad = probe is not None and surfel
        ctx.plans, ctx.trans, ctx.last, ctx.inputs, ctx.rot = plans, trans, last, inputs, rot
        ctx.save_for_backward(means, quats, scales, opacities, sh, covariances)  # autograd's in-place checks
        dtype = means.dtype
        maps = (_tensor(color, dtype), _tensor(1.0 - trans, dtype), _tensor(depth, dtype), _tensor(normal, dtype))
        if moments is None:
            return maps
        return (*maps, _tensor(moments[:, 0:1], dtype))

    @staticmethod
    def backward(ctx, g_color, g_alpha, g_depth, g_normal, g_distortion=None):
        settings: CpuRenderSettings = ctx.settings
        saved = ctx.saved_tensors  # raises if an input was modified in place since the forward
        x, q, sc, op, shc, cov = ctx.inputs  # the forward's inputs as the kernels read them (`_inputs`)
        ft = ctx.trans.dtype.type  # the compositing dtype
        C, H, W = ctx.last.shape
        n = x.shape[0]
        threads = numba.get_num_threads()
        upstream = [
            np.zeros(shape, dtype=ft) if g is None else _np(g, ft)
            for g, shape in (
                (g_color, (C, 3, H, W)),
                (g_normal, (C, 3, H, W)),
                (g_alpha, (C, 1, H, W)),
                (g_depth, (C, 1, H, W)),
            )
        ]
        g_means, g_rot, g_scales = np.zeros((n, 3)), np.zeros((n, 3, 3)), np.zeros((n, 2))
        # The SH gradient gets one addition per camera (float64 arithmetic, rounded where stored), so
        # for one camera it is accumulated straight into the dtype it is returned in: the same bits as
        # a float64 buffer cast afterwards, without that buffer and cast (most of the per-Gaussian data).
        sh_dtype = _NP_DTYPES[saved[4].dtype] if C == 1 and saved[4].dtype in _DIRECT_GRAD else np.float64
        # The kernels' distortion input per camera: dL/dD and the forward's moment sum (None: no gradient
        # flows from the distortion, and the kernel without it runs).
        distortion = None
        if ctx.moments is not None and g_distortion is not None:
            distortion = np.stack((_np(g_distortion, ft)[:, 0], ctx.moments[:, 1]), axis=1)
        g_opac, g_sh, g_cov = np.zeros(n), np.zeros(shc.shape, dtype=sh_dtype), np.zeros(cov.shape)
        scratch, cov_scratch = np.empty((threads, _SCRATCH)), np.empty((threads, 2, 3, 3))
        # each survivor's compositing gradient, per camera
        rows = _held_empty("rows", (n, kernels.GRAD_SIZE), np.float64)
        wanted = ctx.needs_input_grad
        geometry = wanted[0] or wanted[1]  # means or rotations
        shape = wanted[2] or wanted[5]  # scales or explicit covariances
        g_probe = np.zeros((C, n, 2)) if ctx.absgrad else None
        for c, (camera, plan) in enumerate(zip(ctx.cameras, ctx.plans)):
            # every row gets written
            pair_grads = _held_empty("pair_grads", (plan.tile_ids.shape[0], kernels.GRAD_SIZE), ft)
            abs_coef = abs_pairs = None
            if g_probe is not None:
                abs_coef = np.empty((n, kernels.ABS_SIZE), dtype=ft)
                abs_pairs = np.empty((plan.tile_ids.shape[0], 2), dtype=ft)
                with numba.parallel_chunksize(_GAUSSIAN_CHUNK):
                    kernels.surfel_abs_coefficients(
                        plan.order, x, ctx.rot, sc, camera.R_cw, camera.t_cw, camera.K,
                        _convention_args(settings)[0], plan.geom, abs_coef,
                    )  # fmt: skip
            with numba.parallel_chunksize(settings.parallel_chunk):
                kernels.composite_backward(
                    ctx.surfel,
                    camera.lowpass,
                    plan.geom,
                    plan.features,
                    plan.box,
                    plan.tile_start,
                    plan.tile_ids,
                    W,
                    H,
                    settings.tile_size,
                    plan.tiles_x,
                    ctx.trans[c, 0],
                    ctx.last[c],
                    upstream[0][c],
                    upstream[1][c],
                    upstream[2][c, 0],
                    upstream[3][c, 0],
                    pair_grads,
                    None if distortion is None else distortion[c],
                    abs_coef,
                    abs_pairs,
                )
            with numba.parallel_chunksize(_GAUSSIAN_CHUNK):
                kernels.sum_pair_rows(plan.order, plan.pair_start, plan.pair_of, pair_grads, rows)
                if g_probe is not None:
                    kernels.sum_pair_abs(plan.order, plan.pair_start, plan.pair_of, abs_pairs, plan.geom, g_probe[c])
                kernels.project_backward(
                    ctx.surfel,
                    geometry,
                    shape,
                    plan.rank,
                    rows,
                    x,
                    ctx.rot,
                    sc,
                    op,
                    shc,
                    cov,
                    camera.R_cw,
                    camera.t_cw,
                    camera.center,
                    camera.K,
                    camera.width,
                    camera.height,
                    *_convention_args(settings)[:2],
                    camera.dilation,
                    plan.geom,
                    plan.flip,
                    plan.lit,
                    g_means,
                    g_rot,
                    g_scales,
                    g_opac,
                    g_sh,
                    g_cov,
                    scratch,
                    cov_scratch,
                )
        g_quats = np.empty((n, 4))
        if wanted[1]:
            kernels.quats_backward(np.asarray(q, dtype=np.float64), g_rot, g_quats)  # its products in float64

        grads = (g_means, g_quats, g_scales, g_opac, g_sh, g_cov)
        return (
            *(
                None if like is None or not ctx.needs_input_grad[i] else _tensor(grad, like.dtype)
                for i, (grad, like) in enumerate(zip(grads, saved))
            ),
            None,
            None,
            None,
            None,
            None if g_probe is None else _tensor(g_probe, saved[0].dtype),
        )


def _check(gaussians: Gaussians, cameras: Cameras) -> None:
    if gaussians.means.device.type != "cpu":
        raise SurfSplatInputError(
            f"backend: 'cpu' renders tensors on the CPU, got Gaussians on {gaussians.means.device}"
        )
    if cameras.c2w.requires_grad or cameras.K.requires_grad:
        raise SurfSplatInputError("cameras: the 'cpu' backend does not differentiate cameras; use backend='torch'")


def render_cpu(
    gaussians: Gaussians,
    cameras: Cameras,
    width: int,
    height: int,
    mode: RenderMode,
    settings: CpuRenderSettings | None = None,
    distortion: bool = False,
    probe: Tensor | None = None,
    filter_zoom: float = 1.0,
) -> tuple[Tensor, ...]:
    """Un-normalized colour [C, 3, H, W], alpha [C, 1, H, W], depth [C, 1, H, W], normal [C, 3, H, W],
    and with `distortion` (surfels) 2DGS's depth distortion [C, 1, H, W] (see `render`). `probe`
    [C, N, 2]: `render`'s absgrad tensor, or None. `filter_zoom`: `render`'s.

    The function of `render_torch` (float rounding aside), differentiable with respect to the
    Gaussians; camera parameters get no gradient (the dispatcher sends such requests to torch).
    """
    settings = settings or CpuRenderSettings()
    g = gaussians
    _check(g, cameras)
    covariances = g.explicit_covariances if mode == "ewa" else None
    return _Rasterize.apply(
        g.means,
        g.quats,
        g.scales,
        g.opacities,
        g.sh,
        covariances,
        mode == "surfel",
        _cameras(cameras, width, height, filter_zoom),
        settings,
        distortion,
        probe,
    )


def contributing_pairs(
    gaussians: Gaussians,
    cameras: Cameras,
    width: int,
    height: int,
    mode: RenderMode,
    settings: CpuRenderSettings | None = None,
    filter_zoom: float = 1.0,
) -> list[int]:
    """Per camera, the number of (pixel, Gaussian) pairs with alpha >= 1/255 (termination ignored).

    The renderer's work measure, independent of any backend: benchmarks report pairs per second.
    """
    settings = settings or CpuRenderSettings()
    g = gaussians
    _check(g, cameras)
    inputs = _inputs(g.means, g.quats, g.scales, g.opacities, g.sh, g.explicit_covariances if mode == "ewa" else None)
    rot = np.empty((g.means.shape[0], 3, 3))
    counts = []
    ft = compositing_dtype(settings, g.means.dtype)
    for c, cam in enumerate(_cameras(cameras, width, height, filter_zoom)):
        plan = _prepare(mode == "surfel", inputs, rot, cam, settings, ft, fill_rotations=c == 0)
        counts.append(
            int(
                kernels.count_contributing_pairs(
                    mode == "surfel",
                    cam.lowpass,
                    plan.geom,
                    plan.box,
                    plan.tile_start,
                    plan.tile_ids,
                    width,
                    height,
                    settings.tile_size,
                    plan.tiles_x,
                )
            )
        )
    return counts


def _pixel_parts(alpha: np.ndarray) -> int:
    """Runs of image rows for the per-pixel kernels: 1 (one thread) below _PARALLEL_PIXELS."""
    return 1 if alpha.size < _PARALLEL_PIXELS else 2 * numba.get_num_threads()


class _Normalize(torch.autograd.Function):
    """Forced-alpha normalization and background of the raw maps (`kernels.normalize_forward`)."""

    @staticmethod
    def forward(ctx, color, alpha, depth, normal, threshold: float | None, background: Tensor):
        ft = _NP_DTYPES[color.dtype] if color.dtype in _DIRECT_GRAD else np.float64
        maps = [_np(t, ft) for t in (color, alpha, depth, normal)]
        # torch compares a tensor with a Python float in the tensor's dtype: so does the kernel
        limit = ft(math.inf if threshold is None else threshold)
        bg = _np(background, ft)
        out = [np.empty_like(maps[0]), np.empty_like(maps[2]), np.empty_like(maps[3])]
        kernels.normalize_forward(*maps, limit, bg, *out, _pixel_parts(maps[1]))
        ctx.maps, ctx.limit, ctx.bg = maps, limit, bg
        return tuple(_tensor(o, color.dtype) for o in out)

    @staticmethod
    def backward(ctx, g_color, g_depth, g_normal):
        color, alpha, depth, normal = ctx.maps
        upstream = [
            np.zeros_like(like) if g is None else _np(g, like.dtype.type)
            for g, like in ((g_color, color), (g_depth, depth), (g_normal, normal))
        ]
        grads = [np.empty_like(color), np.zeros_like(alpha), np.empty_like(depth), np.empty_like(normal)]
        kernels.normalize_backward(
            color, alpha, depth, normal, ctx.limit, ctx.bg, *upstream, *grads, _pixel_parts(alpha)
        )
        dtype = g_color.dtype if g_color is not None else (g_depth if g_depth is not None else g_normal).dtype
        return (*(_tensor(g, dtype) for g in grads), None, None)


def normalize_cpu(
    color: Tensor, alpha: Tensor, depth: Tensor, normal: Tensor, threshold: float | None, background: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """`render.normalize_by_alpha` followed by the background, in one compiled pass each way:
    (colour over the background, depth, normal). The background gets no gradient."""
    color_out, depth_out, normal_out = _Normalize.apply(color, alpha, depth, normal, threshold, background.detach())
    return color_out, depth_out, normal_out
