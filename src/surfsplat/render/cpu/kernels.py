"""Numba kernels of the compiled CPU renderer (both modes, forward and backward).

Written by hand rather than as torch ops: the work is per (pixel, Gaussian) pair with early
termination and data-dependent footprints, which tensor ops can only do padded and with every
intermediate stored. The kernels compute the function of the torch reference
(`render/torch_backend.py`) pair by pair, the way the CUDA rasterizers of 3DGS/2DGS do, but
shaped for a CPU core:

* `project`: one parallel pass over the Gaussians giving each one's rotation, camera-frame
  geometry, per-pixel coefficients, opacity-aware pixel box, culling flag, SH colour and
  camera-facing normal.
* `depth_order`, `bin_tiles`: stable depth sort of the survivors, then a parallel counting sort into
  tiles, so every tile lists its Gaussians front to back (no global key sort). The lists hold
  input indices: nothing per Gaussian is copied into sorted order.
* `composite_forward`: tiles in parallel; inside a tile the loop runs over its Gaussians and, for
  each, only over the pixels of its box, LANES pixels at a time as one `simd.Vec` each: a row of
  the box, or two rows of a box at most LANES / 2 wide (`_pixels`). Alpha (`_alpha`) and the
  front-to-back blend into tile-local pixel state (`_blend`) are one branch-free pass per step,
  over pixel state stored field by field. Pixels stop by the 3DGS rule and the tile stops once all
  of its pixels have.
* `composite_backward`: the same tiles traversed back to front. Each pixel recovers the
  transmittance in front of a Gaussian by dividing out its alpha, and carries the weighted sum of
  what lies behind, so no per-pixel-pair state is stored. Each (tile, Gaussian) entry gets its own
  gradient row, summed per SIMD lane and then over the lanes in a fixed order (no atomics, no
  per-thread buffers), and `sum_pair_rows` sums a Gaussian's rows in a fixed order: gradients are
  bit-identical for any number of threads and any scheduling.
* Depth distortion (2DGS Eq. 13, surfels, when asked): `_blend` also carries two runs per pixel, the
  running moment sum w z and the distortion, and `_unblend` adds its dL/dw to each weight's
  gradient (the alpha chain rule does the rest) and its dL/dz to the centre depth's. The switch is
  an argument that is None or an array: numba compiles one variant per type and drops the branch
  from the None one, so rendering without it runs the kernels it ran before.
* `project_backward`, `quats_backward`: the chain rule from those per-Gaussian gradients back to
  means, quaternions, scales, opacities, SH coefficients (and explicit covariances).
* Memory order: rows a loop reads out of order (a tile list's Gaussians, a Gaussian's per-tile
  gradient rows) are fetched `_AHEAD` entries early (`_prefetch`); everything else is read in input
  order.

Per-Gaussian coefficients (rows of `geom`, GEOM_* columns):
  surfel: projected centre c, log opacity, centre depth mu_z, det T, the cross product
          h(p) = A + p_x B + p_y C of 2DGS stored as A_c = h(c), B, C, so that
          h(p) = A_c + (p_x - c_x) B + (p_y - c_y) C stays exact far from the image origin,
          and the centre c_lp of the low-pass term rho2d = 2 |p - c_lp|^2.
  ewa:    projected centre, log opacity, centre depth and the inverse 2D covariance (a, b, c).

Precision: the per-Gaussian kernels compute in float64. The compositing kernels are generic in the
dtype of `geom` (numba compiles one specialisation per dtype): float64 is the exact reference,
float32 halves the memory per pair and doubles the SIMD lanes of every pixel loop. Every literal and
work array there takes that dtype (`ft = geom.dtype.type`, `ft(0.5)`, `np.empty(n, dtype=ft)`),
since in numba a float32 meeting a float64 literal or an integer becomes float64. `project` writes
the coefficients in that dtype and expands h about the centre as stored, so a pixel's offset from
it is exact in float32 too.
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import get_thread_id, njit, prange, types
from numba.core import cgutils
from numba.core.errors import TypingError
from numba.extending import intrinsic

from ...geometry.gaussians import THIN_SCALE
from ...geometry.sh import SH_C0, SH_C1, SH_C2, SH_C3
from ..types import (
    ALPHA_MAX,
    ALPHA_MIN,
    EWA_LAMBDA_GAP_MIN,
    EWA_RADIUS_SIGMAS,
    EWA_TILE,
    LOG_ALPHA_MIN,
    TRANSMITTANCE_MIN,
)
from .simd import (
    LANES,
    any_lane,
    count,
    fma,
    half_iota,
    lane,
    lane_sums,
    load,
    load_at,
    load_first,
    select,
    splat,
    store,
    store_at,
    store_first,
    upper_lanes,
)


def _emit_prefetch(builder, pointer):
    """LLVM's prefetch of the cache line at pointer: a read, kept close, of data."""
    byte_pointer = ir.IntType(8).as_pointer()
    i32 = ir.IntType(32)
    fn = cgutils.get_or_insert_function(
        builder.module, ir.FunctionType(ir.VoidType(), [byte_pointer, i32, i32, i32]), "llvm.prefetch.p0"
    )
    builder.call(fn, [builder.bitcast(pointer, byte_pointer), i32(0), i32(3), i32(1)])  # read, keep, data


@intrinsic
def _prefetch(typingctx, array, row):
    """Ask the cache for array[row, 0, ...] ahead of its use (LLVM's prefetch: a read, kept close).

    The kernels read per-Gaussian rows in an order memory cannot guess: the tile lists visit the
    depth-sorted survivors, and the backward sums each Gaussian's per-tile rows from all over its
    array. Numba has no prefetch of its own; this is LLVM's intrinsic, issued a few rows ahead of
    the loop (on 4M random 64-byte rows it took a gather loop from 138 to 86 ms).
    """

    def codegen(context, builder, signature, args):
        array_type = signature.args[0]
        data = context.make_array(array_type)(context, builder, args[0])
        zero = context.get_constant(types.intp, 0)
        index = [args[1]] + [zero] * (array_type.ndim - 1)
        pointer = cgutils.get_item_pointer(context, builder, array_type, data, index, wraparound=False)
        _emit_prefetch(builder, pointer)
        return context.get_dummy_value()

    return types.void(array, row), codegen


@intrinsic
def _prefetch_last(typingctx, array, row):
    """`_prefetch` of the last element of array[row] (a 2D row): a row that is not aligned to a cache
    line, or is longer than one, also needs its end fetched."""

    def codegen(context, builder, signature, args):
        array_type = signature.args[0]
        data = context.make_array(array_type)(context, builder, args[0])
        shape = cgutils.unpack_tuple(builder, data.shape, array_type.ndim)
        last = builder.sub(shape[1], context.get_constant(types.intp, 1))
        pointer = cgutils.get_item_pointer(context, builder, array_type, data, [args[1], last], wraparound=False)
        _emit_prefetch(builder, pointer)
        return context.get_dummy_value()

    if not (isinstance(array, types.Array) and array.ndim == 2):
        raise TypingError(f"_prefetch_last takes a 2D array, not {array}")
    return types.void(array, row), codegen


# Rows ahead of the loop that `_prefetch` asks for: enough to cover a memory access's latency.
_AHEAD = 16


# Columns of the per-Gaussian coefficient rows.
GEOM_CX, GEOM_CY, GEOM_LOGO, GEOM_DEPTH, GEOM_DET = 0, 1, 2, 3, 4
GEOM_A, GEOM_B, GEOM_C = 5, 8, 11  # surfel: A_c, B, C (3 each)
GEOM_CONIC = 5  # ewa: conic (a, b, c) of rho = a dx^2 + 2 b dx dy + c dy^2
GEOM_LP = 14  # surfel: the low-pass centre (2; `RenderConventions.lowpass_center_sigma`)
GEOM_SIZE = 16

# Columns of the per-Gaussian gradient rows produced by the compositing backward pass.
GRAD_H, GRAD_HX, GRAD_HY = 0, 3, 6  # surfel: sum g_h, sum dx g_h, sum dy g_h over the pixels
GRAD_CONIC = 0  # ewa: dL/d(conic a, b, c)
GRAD_CX, GRAD_CY, GRAD_DET, GRAD_DEPTH, GRAD_LOGO = 9, 10, 11, 12, 13
GRAD_FEAT = 14  # 6 features: colour, normal
GRAD_SIZE = 20
FEATURES = 6

_NEAR_ZERO = 1e-12  # |z| below this is treated as 1 before dividing (the point is culled anyway)
_CONIC_DET_MIN = 1e-20  # floor of the 2D covariance determinant (as the torch backend)
_QUAT_NORM_MIN = 1e-300  # quaternion norms are floored here before dividing (Gaussians rejects zero quaternions)


# ---------------------------------------------------------------------------------------------
# Projection
# ---------------------------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def _surfel_matrix(mu, R, s0, s1, R_cw, K):
    """Rows of T = K [R_cw R e1 s0, R_cw R e2 s1, mu] (2DGS Eq. 9 with the camera-frame mean mu)."""
    u0 = (R_cw[0, 0] * R[0, 0] + R_cw[0, 1] * R[1, 0] + R_cw[0, 2] * R[2, 0]) * s0
    u1 = (R_cw[1, 0] * R[0, 0] + R_cw[1, 1] * R[1, 0] + R_cw[1, 2] * R[2, 0]) * s0
    u2 = (R_cw[2, 0] * R[0, 0] + R_cw[2, 1] * R[1, 0] + R_cw[2, 2] * R[2, 0]) * s0
    v0 = (R_cw[0, 0] * R[0, 1] + R_cw[0, 1] * R[1, 1] + R_cw[0, 2] * R[2, 1]) * s1
    v1 = (R_cw[1, 0] * R[0, 1] + R_cw[1, 1] * R[1, 1] + R_cw[1, 2] * R[2, 1]) * s1
    v2 = (R_cw[2, 0] * R[0, 1] + R_cw[2, 1] * R[1, 1] + R_cw[2, 2] * R[2, 1]) * s1
    m0, m1, m2 = mu[0], mu[1], mu[2]
    tx0 = K[0, 0] * u0 + K[0, 1] * u1 + K[0, 2] * u2
    tx1 = K[0, 0] * v0 + K[0, 1] * v1 + K[0, 2] * v2
    tx2 = K[0, 0] * m0 + K[0, 1] * m1 + K[0, 2] * m2
    ty0 = K[1, 0] * u0 + K[1, 1] * u1 + K[1, 2] * u2
    ty1 = K[1, 0] * v0 + K[1, 1] * v1 + K[1, 2] * v2
    ty2 = K[1, 0] * m0 + K[1, 1] * m1 + K[1, 2] * m2
    tw0 = K[2, 0] * u0 + K[2, 1] * u1 + K[2, 2] * u2
    tw1 = K[2, 0] * v0 + K[2, 1] * v1 + K[2, 2] * v2
    tw2 = K[2, 0] * m0 + K[2, 1] * m1 + K[2, 2] * m2
    return tx0, tx1, tx2, ty0, ty1, ty2, tw0, tw1, tw2


@njit(cache=True, error_model="numpy")
def _opacity_extent(log_opacity):
    """k^2 with o exp(-rho / 2) >= ALPHA_MIN exactly when rho <= k^2: 2 log(o / ALPHA_MIN), taken
    from log o (the projection computes it anyway; a second logarithm was a tenth of its time)."""
    return 2.0 * max(log_opacity - LOG_ALPHA_MIN, 0.0)


@njit(cache=True, error_model="numpy")
def _pixel_range(lo, hi, size):
    """Inclusive pixel indices whose centres i + 0.5 lie in [lo, hi], clamped to the image.

    The bounds are clamped before rounding: an unbounded footprint (a surfel crossing the camera
    plane) has infinite bounds, and rounding an infinity to an integer is undefined (it gave
    INT64_MIN, an empty range, and the surfel silently vanished).
    """
    lo = min(max(lo, -1.0), size + 1.0)
    hi = min(max(hi, -1.0), size + 1.0)
    first = min(max(math.ceil(lo - 0.5), 0.0), float(size))
    last = min(max(math.floor(hi - 0.5), -1.0), float(size - 1))
    return int(first), int(last)


@njit(cache=True, error_model="numpy")
def _lowpass_center(tx0, tx1, tx2, ty0, ty1, ty2, tw0, tw1, tw2, cx, cy, sigma):
    """Centre of the surfel low-pass term and the C22 it came from (0: the projected centre).

    sigma > 0: the box centre of the projected sigma-ellipse, (C02, C12) / C22 of the dual conic
    T diag(1, 1, -1/sigma^2) T^T while C22 < 0; otherwise (or sigma <= 0, meaning none) the
    projected centre (cx, cy). The torch backend's `lowpass_center`.
    """
    if sigma > 0.0:
        e = -1.0 / (sigma * sigma)
        c22 = tw0 * tw0 + tw1 * tw1 + e * tw2 * tw2
        if c22 < -1e-12:
            c02 = tx0 * tw0 + tx1 * tw1 + e * tx2 * tw2
            c12 = ty0 * tw0 + ty1 * tw1 + e * ty2 * tw2
            return c02 / c22, c12 / c22, c22
    return cx, cy, 0.0


@njit(cache=True, error_model="numpy")
def _release_tile_range(p, radius, size):
    """Inclusive pixel range of the 16-pixel tiles diff-gaussian-rasterization picks on one axis.

    p is the centre in that rasterizer's pixel frame (ours - 0.5); empty ranges have first > last.
    """
    grid = float(-(-size // EWA_TILE))
    t0 = min(max(math.floor((p - radius) / EWA_TILE), 0.0), grid)
    t1 = min(max(math.floor((p + radius + EWA_TILE - 1) / EWA_TILE), 0.0), grid)
    if t1 <= t0:
        return 0, -1
    return int(t0) * EWA_TILE, min(int(t1) * EWA_TILE, size) - 1


@njit(cache=True, error_model="numpy")
def _quat_rotation(q, R):
    """R [3, 3] = rotation of the normalized quaternion q = (w, x, y, z) (geometry/rotations.py),
    in float64 whatever q's float type (a float32 q gives the bits of its float64 copy)."""
    q0, q1, q2, q3 = float(q[0]), float(q[1]), float(q[2]), float(q[3])
    norm = max(math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3), _QUAT_NORM_MIN)
    w, x, y, z = q0 / norm, q1 / norm, q2 / norm, q3 / norm
    R[0, 0], R[0, 1], R[0, 2] = 1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)
    R[1, 0], R[1, 1], R[1, 2] = 2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)
    R[2, 0], R[2, 1], R[2, 2] = 2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)


@njit(cache=True, error_model="numpy")
def quats_backward(quats, g_rotations, g_quats):
    """g_quats [N, 4] = dL/dquats from dL/drotations [N, 3, 3] through `_quat_rotation`."""
    for i in range(quats.shape[0]):
        q0, q1, q2, q3 = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
        raw = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
        norm = max(raw, _QUAT_NORM_MIN)
        w, x, y, z = q0 / norm, q1 / norm, q2 / norm, q3 / norm
        G = g_rotations[i]
        gw = 2.0 * (-z * G[0, 1] + y * G[0, 2] + z * G[1, 0] - x * G[1, 2] - y * G[2, 0] + x * G[2, 1])
        gx = 2.0 * (
            y * G[0, 1]
            + z * G[0, 2]
            + y * G[1, 0]
            - 2.0 * x * G[1, 1]
            - w * G[1, 2]
            + z * G[2, 0]
            + w * G[2, 1]
            - 2.0 * x * G[2, 2]
        )
        gy = 2.0 * (
            -2.0 * y * G[0, 0]
            + x * G[0, 1]
            + w * G[0, 2]
            + x * G[1, 0]
            + z * G[1, 2]
            - w * G[2, 0]
            + z * G[2, 1]
            - 2.0 * y * G[2, 2]
        )
        gz = 2.0 * (
            -2.0 * z * G[0, 0]
            - w * G[0, 1]
            + x * G[0, 2]
            + w * G[1, 0]
            - 2.0 * z * G[1, 1]
            + y * G[1, 2]
            + x * G[2, 0]
            + y * G[2, 1]
        )
        # q_hat = q / |q|: dL/dq = (dL/dq_hat - q_hat (q_hat . dL/dq_hat)) / |q|
        dot = w * gw + x * gx + y * gy + z * gz if raw > _QUAT_NORM_MIN else 0.0
        g_quats[i, 0] = (gw - w * dot) / norm
        g_quats[i, 1] = (gx - x * dot) / norm
        g_quats[i, 2] = (gy - y * dot) / norm
        g_quats[i, 3] = (gz - z * dot) / norm


@njit(cache=True, error_model="numpy")
def _camera_point(x, R_cw, t_cw):
    """mu = R_cw x + t (the torch backend's camera-frame mean, float64)."""
    return (
        R_cw[0, 0] * x[0] + R_cw[0, 1] * x[1] + R_cw[0, 2] * x[2] + t_cw[0],
        R_cw[1, 0] * x[0] + R_cw[1, 1] * x[1] + R_cw[1, 2] * x[2] + t_cw[1],
        R_cw[2, 0] * x[0] + R_cw[2, 1] * x[1] + R_cw[2, 2] * x[2] + t_cw[2],
    )


@njit(cache=True, error_model="numpy")
def _ewa_cov2d(mu, cov, R_cw, K, lim_x, lim_y):
    """J W Sigma W^T J^T (3DGS Eq. 5) with the affine Jacobian J at the camera-frame mean mu.

    Returns its entries (a, b, c) = (00, 01, 11), the rows p, q of J W, and the guarded z.
    J = [[fx/z, s/z, -(fx x + s y)/z], [0, fy/z, -fy y/z]] with x = mu_x/z, y = mu_y/z clamped
    to +-lim_x, +-lim_y (3DGS's Jacobian clamp; infinite limits for none).
    """
    z = mu[2] if abs(mu[2]) > _NEAR_ZERO else 1.0
    fx, fy, skew = K[0, 0], K[1, 1], K[0, 1]
    x, y = min(max(mu[0] / z, -lim_x), lim_x), min(max(mu[1] / z, -lim_y), lim_y)
    j00, j01, j02, j11, j12 = fx / z, skew / z, -(fx * x + skew * y) / z, fy / z, -fy * y / z
    p0 = j00 * R_cw[0, 0] + j01 * R_cw[1, 0] + j02 * R_cw[2, 0]
    p1 = j00 * R_cw[0, 1] + j01 * R_cw[1, 1] + j02 * R_cw[2, 1]
    p2 = j00 * R_cw[0, 2] + j01 * R_cw[1, 2] + j02 * R_cw[2, 2]
    q0 = j11 * R_cw[1, 0] + j12 * R_cw[2, 0]
    q1 = j11 * R_cw[1, 1] + j12 * R_cw[2, 1]
    q2 = j11 * R_cw[1, 2] + j12 * R_cw[2, 2]
    sq0 = cov[0, 0] * q0 + cov[0, 1] * q1 + cov[0, 2] * q2  # Sigma q
    sq1 = cov[1, 0] * q0 + cov[1, 1] * q1 + cov[1, 2] * q2
    sq2 = cov[2, 0] * q0 + cov[2, 1] * q1 + cov[2, 2] * q2
    sp0 = cov[0, 0] * p0 + cov[0, 1] * p1 + cov[0, 2] * p2  # Sigma p
    sp1 = cov[1, 0] * p0 + cov[1, 1] * p1 + cov[1, 2] * p2
    sp2 = cov[2, 0] * p0 + cov[2, 1] * p1 + cov[2, 2] * p2
    a = p0 * sp0 + p1 * sp1 + p2 * sp2
    b = p0 * sq0 + p1 * sq1 + p2 * sq2
    c = q0 * sq0 + q1 * sq1 + q2 * sq2
    return a, b, c, p0, p1, p2, q0, q1, q2, z


@njit(cache=True, error_model="numpy")
def _thin_covariance(R, s0, s1, out):
    """out = R diag(s0^2, s1^2, THIN_SCALE^2) R^T: the surfel as a thin 3D Gaussian (Gaussians.covariances)."""
    v0, v1, v2 = s0 * s0, s1 * s1, THIN_SCALE * THIN_SCALE
    for r in range(3):
        for c in range(3):
            out[r, c] = R[r, 0] * v0 * R[c, 0] + R[r, 1] * v1 * R[c, 1] + R[r, 2] * v2 * R[c, 2]


@njit(cache=True, error_model="numpy")
def _sh_basis(x, y, z, n_bases, Y):
    """Real SH basis of 3DGS (geometry/sh.py) at the unit direction (x, y, z), first n_bases terms."""
    Y[0] = SH_C0
    if n_bases > 1:
        Y[1], Y[2], Y[3] = -SH_C1 * y, SH_C1 * z, -SH_C1 * x
    if n_bases > 4:
        xx, yy, zz = x * x, y * y, z * z
        Y[4] = SH_C2[0] * x * y
        Y[5] = SH_C2[1] * y * z
        Y[6] = SH_C2[2] * (2.0 * zz - xx - yy)
        Y[7] = SH_C2[3] * x * z
        Y[8] = SH_C2[4] * (xx - yy)
    if n_bases > 9:
        Y[9] = SH_C3[0] * y * (3.0 * xx - yy)
        Y[10] = SH_C3[1] * x * y * z
        Y[11] = SH_C3[2] * y * (4.0 * zz - xx - yy)
        Y[12] = SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
        Y[13] = SH_C3[4] * x * (4.0 * zz - xx - yy)
        Y[14] = SH_C3[5] * z * (xx - yy)
        Y[15] = SH_C3[6] * x * (xx - 3.0 * yy)


@njit(cache=True, error_model="numpy")
def _sh_basis_grad(x, y, z, n_bases, GX, GY, GZ):
    """Partial derivatives of `_sh_basis` with respect to x, y, z (first n_bases terms)."""
    for k in range(n_bases):
        GX[k], GY[k], GZ[k] = 0.0, 0.0, 0.0
    if n_bases > 1:
        GY[1], GZ[2], GX[3] = -SH_C1, SH_C1, -SH_C1
    if n_bases > 4:
        GX[4], GY[4] = SH_C2[0] * y, SH_C2[0] * x
        GY[5], GZ[5] = SH_C2[1] * z, SH_C2[1] * y
        GX[6], GY[6], GZ[6] = -2.0 * SH_C2[2] * x, -2.0 * SH_C2[2] * y, 4.0 * SH_C2[2] * z
        GX[7], GZ[7] = SH_C2[3] * z, SH_C2[3] * x
        GX[8], GY[8] = 2.0 * SH_C2[4] * x, -2.0 * SH_C2[4] * y
    if n_bases > 9:
        xx, yy, zz = x * x, y * y, z * z
        GX[9], GY[9] = 6.0 * SH_C3[0] * x * y, SH_C3[0] * (3.0 * xx - 3.0 * yy)
        GX[10], GY[10], GZ[10] = SH_C3[1] * y * z, SH_C3[1] * x * z, SH_C3[1] * x * y
        GX[11] = -2.0 * SH_C3[2] * x * y
        GY[11] = SH_C3[2] * (4.0 * zz - xx - 3.0 * yy)
        GZ[11] = 8.0 * SH_C3[2] * y * z
        GX[12], GY[12] = -6.0 * SH_C3[3] * x * z, -6.0 * SH_C3[3] * y * z
        GZ[12] = SH_C3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy)
        GX[13] = SH_C3[4] * (4.0 * zz - 3.0 * xx - yy)
        GY[13] = -2.0 * SH_C3[4] * x * y
        GZ[13] = 8.0 * SH_C3[4] * x * z
        GX[14], GY[14], GZ[14] = 2.0 * SH_C3[5] * x * z, -2.0 * SH_C3[5] * y * z, SH_C3[5] * (xx - yy)
        GX[15], GY[15] = SH_C3[6] * (3.0 * xx - 3.0 * yy), -6.0 * SH_C3[6] * x * y


@njit(cache=True, error_model="numpy")
def _view_direction(x, cam_center):
    """Unit direction from the camera centre to x (F.normalize: divided by max(|v|, 1e-12))."""
    v0, v1, v2 = x[0] - cam_center[0], x[1] - cam_center[1], x[2] - cam_center[2]
    norm = max(math.sqrt(v0 * v0 + v1 * v1 + v2 * v2), 1e-12)
    return v0 / norm, v1 / norm, v2 / norm, norm


@njit(cache=True, error_model="numpy")
def _beyond(mu, radius, K, row, border, side):
    """Whether the sphere of `radius` about mu lies wholly on the `side` (+-1) of the plane through
    the camera centre that projects onto pixel coordinate `border` along image axis `row` (0: x, 1: y):
    (K[row] - border K[2]) . X = 0. The test d > radius |n| of the signed distance d = side n . mu as
    d > 0 and d^2 > radius^2 |n|^2, without the square root (four a Gaussian were a quarter of the
    projection's time)."""
    n0 = K[row, 0] - border * K[2, 0]
    n1 = K[row, 1] - border * K[2, 1]
    n2 = K[row, 2] - border * K[2, 2]
    d = side * (n0 * mu[0] + n1 * mu[1] + n2 * mu[2])
    return d > 0.0 and d * d > radius * radius * (n0 * n0 + n1 * n1 + n2 * n2)


@njit(cache=True, error_model="numpy")
def _surfel_off_image(mu, radius, margin, K, width, height):
    """Whether a sphere of `radius` about the camera-frame point mu projects entirely outside the
    image grown by `margin` pixels on every side. Only for a sphere wholly in front of the camera
    plane: one reaching it has an unbounded projection (a surfel crossing the camera plane may
    cover every pixel), and is never off-image.
    """
    if mu[2] <= radius:
        return False
    return (
        _beyond(mu, radius, K, 0, -margin, -1.0)
        or _beyond(mu, radius, K, 0, width + margin, 1.0)
        or _beyond(mu, radius, K, 1, -margin, -1.0)
        or _beyond(mu, radius, K, 1, height + margin, 1.0)
    )


@njit(parallel=True, cache=True, error_model="numpy")
def project(
    surfel,
    means,
    quats,
    fill_rotations,
    rotations,
    scales,
    opacities,
    sh,
    covariances,
    R_cw,
    t_cw,
    cam_center,
    K,
    width,
    height,
    near,
    far,
    lowpass_sigma,
    jacobian_clamp,
    release_support,
    lowpass,
    dilation,
    geom,
    box,
    bin_box,
    keep,
    depth,
    features,
    flip,
    lit,
    scratch,
    cov_scratch,
):
    """Per-Gaussian coefficients, pixel boxes, culling, colour and oriented normal (parallel over N).

    lowpass_sigma (<= 0: none), jacobian_clamp (inf: none) and release_support are the
    `RenderConventions` of the call; lowpass (surfels' rho2d = lowpass |p - c|^2, `_alpha`) and dilation
    (EWA's, added to the 2D covariance's diagonal) the screen-space filter's: LOWPASS_RHO_SCALE and
    EWA_DILATION for 2DGS's and 3DGS's, LOWPASS_RHO_SCALE / zoom^2 and EWA_DILATION zoom^2 for the
    filter of a camera zoom times coarser.

    means [N, 3], quats [N, 4], rotations [N, 3, 3] (written here from quats when fill_rotations,
    read otherwise: a call's later cameras reuse the first one's), scales [N, 2], opacities [N],
    sh [N, 3, B] (world frame);
    covariances [N, 3, 3] explicit EWA covariances or [0, 3, 3] to use the surfels' own thin ones.
    Writes geom [N, GEOM_SIZE], box [N, 4] (col0, col1, row0, row1: the pixels that can have alpha
    > 0, which the compositing visits), bin_box [N, 4] (the pixels whose tiles list the Gaussian:
    box, or for EWA with release_support the release rule's tiles), keep [N], depth [N] (camera
    z, the sort key), features [N, 6] (colour, normal facing the camera), flip [N] (+-1, the
    normal's sign) and lit [N] (bit ch set where colour channel ch is not clamped at 0, so the
    backward pass need not evaluate the SH again). scratch [threads, >= 16], cov_scratch [threads, 2, 3, 3] are per-thread work space.
    """
    n_bases = sh.shape[2]
    explicit = covariances.shape[0] > 0
    lim_x = jacobian_clamp * width / (2.0 * K[0, 0])
    lim_y = jacobian_clamp * height / (2.0 * K[1, 1])
    for i in prange(means.shape[0]):
        tid = get_thread_id()
        if fill_rotations:
            _quat_rotation(quats[i], rotations[i])
        mu = _camera_point(means[i], R_cw, t_cw)
        z = mu[2]
        safe_z = z if abs(z) > _NEAR_ZERO else 1.0
        depth[i] = z
        log_o = math.log(opacities[i]) if opacities[i] > 0 else -math.inf
        k2 = _opacity_extent(log_o)
        # Cull before projecting, by rules that keep every Gaussian `keep` below would keep: the
        # depth and opacity tests themselves, and for surfels a bounding sphere of the k-sigma
        # ellipse (and of the sigma-ellipse that places the low-pass centre) that projects off the
        # image grown by the low-pass reach and a pixel. EWA footprints come from the affine
        # approximation, which a sphere does not bound: those are culled after projecting.
        culled = not (z > near and z < far and opacities[i] >= ALPHA_MIN)
        if surfel and not culled:
            reach = max(math.sqrt(k2), lowpass_sigma) * max(scales[i, 0], scales[i, 1])
            culled = _surfel_off_image(mu, reach, math.sqrt(k2 / lowpass) + 1.0, K, width, height)
        if culled:
            keep[i] = False
            flip[i] = 1.0
            lit[i] = 0
            continue
        g = geom[i]
        g[GEOM_LOGO] = log_o
        if surfel:
            tx0, tx1, tx2, ty0, ty1, ty2, tw0, tw1, tw2 = _surfel_matrix(
                mu, rotations[i], scales[i, 0], scales[i, 1], R_cw, K
            )
            # The centre as stored (rounded once where the geometry is float32): h is expanded about
            # it, so a pixel's offset from the stored centre is exact and large images stay sub-pixel.
            g[GEOM_CX], g[GEOM_CY] = tx2 / safe_z, ty2 / safe_z
            cx, cy = float(g[GEOM_CX]), float(g[GEOM_CY])
            lx, ly, _ = _lowpass_center(tx0, tx1, tx2, ty0, ty1, ty2, tw0, tw1, tw2, cx, cy, lowpass_sigma)
            # Box: the k-sigma ellipse u^2 + v^2 = k^2 maps under T to a conic whose dual is
            # T diag(1, 1, -1/k^2) T^T; its tangent lines give the exact box while it is an ellipse.
            d2 = -1.0 / max(k2, 1e-12)
            c00 = tx0 * tx0 + tx1 * tx1 + d2 * tx2 * tx2
            c11 = ty0 * ty0 + ty1 * ty1 + d2 * ty2 * ty2
            c02 = tx0 * tw0 + tx1 * tw1 + d2 * tx2 * tw2
            c12 = ty0 * tw0 + ty1 * tw1 + d2 * ty2 * tw2
            c22 = tw0 * tw0 + tw1 * tw1 + d2 * tw2 * tw2
            r_lp = math.sqrt(k2 / lowpass)  # the screen-space filter's own reach
            if c22 < -1e-12:
                ex, ey = c02 / c22, c12 / c22
                hx = math.sqrt(max(c02 * c02 - c00 * c22, 0.0)) / abs(c22)
                hy = math.sqrt(max(c12 * c12 - c11 * c22, 0.0)) / abs(c22)
                xmin, xmax = min(ex - hx, lx - r_lp), max(ex + hx, lx + r_lp)
                ymin, ymax = min(ey - hy, ly - r_lp), max(ey + hy, ly + r_lp)
            else:  # the footprint is unbounded (a hyperbola or parabola): every pixel
                xmin, xmax, ymin, ymax = -math.inf, math.inf, -math.inf, math.inf
            # h(p) = A + p_x B + p_y C with A = T_x x T_y, B = T_y x T_w, C = T_w x T_x.
            ax, ay, az = tx1 * ty2 - tx2 * ty1, tx2 * ty0 - tx0 * ty2, tx0 * ty1 - tx1 * ty0
            bx, by, bz = ty1 * tw2 - ty2 * tw1, ty2 * tw0 - ty0 * tw2, ty0 * tw1 - ty1 * tw0
            qx, qy, qz = tw1 * tx2 - tw2 * tx1, tw2 * tx0 - tw0 * tx2, tw0 * tx1 - tw1 * tx0
            g[GEOM_DEPTH] = tw2
            g[GEOM_DET] = tw0 * ax + tw1 * ay + tw2 * az
            g[GEOM_A] = ax + cx * bx + cy * qx
            g[GEOM_A + 1] = ay + cx * by + cy * qy
            g[GEOM_A + 2] = az + cx * bz + cy * qz
            g[GEOM_B], g[GEOM_B + 1], g[GEOM_B + 2] = bx, by, bz
            g[GEOM_C], g[GEOM_C + 1], g[GEOM_C + 2] = qx, qy, qz
            g[GEOM_LP], g[GEOM_LP + 1] = lx, ly
        else:
            if explicit:
                cov = covariances[i]
            else:
                cov = cov_scratch[tid, 0]
                _thin_covariance(rotations[i], scales[i, 0], scales[i, 1], cov)
            a, b, c, _, _, _, _, _, _, _ = _ewa_cov2d(mu, cov, R_cw, K, lim_x, lim_y)
            a += dilation
            c += dilation
            det = max(a * c - b * b, _CONIC_DET_MIN)
            cx = K[0, 0] * (mu[0] / safe_z) + K[0, 1] * (mu[1] / safe_z) + K[0, 2]
            cy = K[1, 1] * (mu[1] / safe_z) + K[1, 2]
            # The k-sigma ellipse's box: no pixel outside it has alpha >= ALPHA_MIN.
            hx, hy = math.sqrt(k2 * a), math.sqrt(k2 * c)
            xmin, xmax, ymin, ymax = cx - hx, cx + hx, cy - hy, cy + hy
            g[GEOM_DEPTH] = z
            g[GEOM_DET] = 0.0
            g[GEOM_CONIC], g[GEOM_CONIC + 1], g[GEOM_CONIC + 2] = c / det, -b / det, a / det
            for j in range(GEOM_CONIC + 3, GEOM_SIZE):
                g[j] = 0.0
        g[GEOM_CX], g[GEOM_CY] = cx, cy
        if surfel or not release_support:
            box[i, 0], box[i, 1] = _pixel_range(xmin, xmax, width)
            box[i, 2], box[i, 3] = _pixel_range(ymin, ymax, height)
            for j in range(4):
                bin_box[i, j] = box[i, j]
        else:  # diff-gaussian-rasterization's square of radius ceil(3 sqrt(lambda_max)), in 16-pixel tiles
            mid = 0.5 * (a + c)
            lam = mid + math.sqrt(max(EWA_LAMBDA_GAP_MIN, mid * mid - (a * c - b * b)))
            radius = math.ceil(EWA_RADIUS_SIGMAS * math.sqrt(max(lam, 0.0)))
            bin_box[i, 0], bin_box[i, 1] = _release_tile_range(cx - 0.5, radius, width)
            bin_box[i, 2], bin_box[i, 3] = _release_tile_range(cy - 0.5, radius, height)
            # Those tiles list it; inside them only the ellipse's box (a pixel wider, against
            # rounding) is composited: the release support is whole tiles, mostly of alpha 0. The
            # box is cut to those tiles too, as the compositing's own tiles may be larger.
            x0, x1 = _pixel_range(xmin - 1.0, xmax + 1.0, width)
            y0, y1 = _pixel_range(ymin - 1.0, ymax + 1.0, height)
            box[i, 0], box[i, 1] = max(x0, bin_box[i, 0]), min(x1, bin_box[i, 1])
            box[i, 2], box[i, 3] = max(y0, bin_box[i, 2]), min(y1, bin_box[i, 3])
        keep[i] = (
            z > near
            and z < far
            and opacities[i] >= ALPHA_MIN
            and bin_box[i, 0] <= bin_box[i, 1]
            and bin_box[i, 2] <= bin_box[i, 3]
        )
        # Colour: SH at the direction from the camera centre, + 0.5, clamped at 0 (3DGS).
        dx = dy = dz = 0.0  # degree 0 is the same from every direction
        if n_bases > 1:
            dx, dy, dz, _ = _view_direction(means[i], cam_center)
        Y = scratch[tid]
        _sh_basis(dx, dy, dz, n_bases, Y)
        bits = 0
        for ch in range(3):
            v = 0.5
            for k in range(n_bases):
                v += sh[i, ch, k] * Y[k]
            features[i, ch] = max(v, 0.0)
            bits |= (1 << ch) if v >= 0.0 else 0
        lit[i] = bits
        # Normal: the rotated z axis, flipped to face the camera (n_cam . mu <= 0).
        R = rotations[i]
        n_dot = (
            (R_cw[0, 0] * R[0, 2] + R_cw[0, 1] * R[1, 2] + R_cw[0, 2] * R[2, 2]) * mu[0]
            + (R_cw[1, 0] * R[0, 2] + R_cw[1, 1] * R[1, 2] + R_cw[1, 2] * R[2, 2]) * mu[1]
            + (R_cw[2, 0] * R[0, 2] + R_cw[2, 1] * R[1, 2] + R_cw[2, 2] * R[2, 2]) * mu[2]
        )
        flip[i] = -1.0 if n_dot > 0 else 1.0
        for r in range(3):
            features[i, 3 + r] = flip[i] * R[r, 2]


# ---------------------------------------------------------------------------------------------
# Sorting and binning
# ---------------------------------------------------------------------------------------------


def depth_order(keep, depth):
    """Input indices of the survivors sorted front to back (stable: ties keep input order).

    One sort of 64-bit integers: each survivor's depth as an integer of the same order (`_depth_keys`)
    with its lowest bits given to the input index, so NumPy's vectorized integer sort (on AVX-512:
    0.77 ms for 120k keys, where its argsort of the depths took 2.0 ms and its stable sort 9x that)
    orders by depth and then by index. Depths equal in all but those lowest bits are put in exact
    order afterwards (`_order_from_keys`): the result is the stable sort's exactly.
    """
    depth_bits = depth.view(np.int64)
    keys, bits = _depth_keys(keep, depth_bits)
    keys.sort()
    return _order_from_keys(keys, bits, depth_bits)


@njit(cache=True, error_model="numpy")
def _ordered(b):
    """The bits b of a float64 as an int64 in the same order as the floats (0.0 and -0.0 equal)."""
    if b == np.int64(-0x8000000000000000):  # -0.0
        return np.int64(0)
    return b ^ np.int64(0x7FFFFFFFFFFFFFFF) if b < 0 else b


@njit(cache=True, error_model="numpy")
def _depth_keys(keep, depth_bits):
    """Sort keys of the survivors (keep): the ordered depth with its lowest `bits` bits replaced by
    the input index, and `bits` (enough for every index)."""
    n = keep.shape[0]
    bits = 1
    while (1 << bits) < n:
        bits += 1
    keys = np.empty(np.count_nonzero(keep), dtype=np.int64)
    j = 0
    for i in range(n):
        if keep[i]:
            keys[j] = ((_ordered(depth_bits[i]) >> bits) << bits) | i
            j += 1
    return keys, bits


@njit(cache=True, error_model="numpy")
def _order_from_keys(keys, bits, depth_bits):
    """The input indices of sorted keys, each run of keys equal but for the index bits put in the
    order of the full depths, ties by index (insertion sort: such runs are a few keys at most)."""
    m = keys.shape[0]
    out = np.empty(m, dtype=np.int64)
    index_mask = (np.int64(1) << bits) - 1
    for j in range(m):
        out[j] = keys[j] & index_mask
    j = 0
    while j < m:
        e = j + 1
        while e < m and keys[e] >> bits == keys[j] >> bits:
            e += 1
        for t in range(j + 1, e):
            i = out[t]
            key = (_ordered(depth_bits[i]), i)
            u = t
            while u > j and (_ordered(depth_bits[out[u - 1]]), out[u - 1]) > key:
                out[u] = out[u - 1]
                u -= 1
            out[u] = i
        j = e
    return out


@njit(parallel=True, cache=True, error_model="numpy")
def bin_tiles(box, order, tile, tiles_x, tiles_y, parts, rank):
    """The survivors, front to back (input indices order [M]; box [N, 4] the pixel boxes of every
    Gaussian in input order), listed per tile.

    Returns tile_start [tiles + 1] and tile_ids [pairs]: the survivors (as input indices) touching
    each tile, front to back; and the same lists seen from the survivors: the entries of tile_ids
    that belong to survivor m (the m-th nearest) are pair_of[pair_start[m]:pair_start[m + 1]] (its
    tiles in row-major order). The backward pass sums per-tile gradients through them in that fixed
    order, whatever thread handled which tile. The tile lists name Gaussians by input index, so the
    compositing reads every per-Gaussian array as the projection wrote it, with no sorted copy.

    A counting sort in parallel: the survivors are cut into `parts` runs of consecutive ones (taken
    by threads as they come free); each run counts its entries per tile, a serial prefix sum gives
    every run its own cursor into each tile's list (after the runs in front of it), and each run
    then writes its entries in depth order. The result does not depend on `parts`; parts = 1
    runs on this thread alone (no parallel region: see `normalize_forward`). Also sets
    rank[order[m]] = m (each survivor's place in depth order; the caller fills rank with -1).
    """
    n = order.shape[0]
    n_tiles = tiles_x * tiles_y
    tiles = np.empty((n, 4), dtype=np.int64)  # tile range of each survivor's box: tx0, tx1, ty0, ty1
    # Each run's count (then cursor) per tile, rows a cache line longer so no two runs share a line.
    cursor = np.zeros((parts, n_tiles + 8), dtype=np.int64)
    pair_start = np.empty(n + 1, dtype=np.int64)
    pair_start[0] = 0
    # A survivor's box lies in the image (non-negative pixels), so a power-of-two tile divides by a
    # shift (the four integer divisions were a fifth of this pass).
    shift = 0
    while (1 << shift) < tile:
        shift += 1
    pow2 = (1 << shift) == tile
    if parts == 1:
        _count_run(box, order, tile, tiles_x, shift, pow2, 0, 1, tiles, cursor, pair_start, rank)
    else:
        for j in prange(parts):
            _count_run(box, order, tile, tiles_x, shift, pow2, j, parts, tiles, cursor, pair_start, rank)
    tile_start = np.empty(n_tiles + 1, dtype=np.int64)
    tile_start[0] = 0
    for t in range(n_tiles):
        at = tile_start[t]
        for j in range(parts):
            at, cursor[j, t] = at + cursor[j, t], at
        tile_start[t + 1] = at
    for m in range(n):
        pair_start[m + 1] += pair_start[m]
    tile_ids = np.empty(tile_start[n_tiles], dtype=np.int64)
    pair_of = np.empty(tile_start[n_tiles], dtype=np.int64)
    # Visiting survivors in depth order fills every tile's list front to back.
    if parts == 1:
        _fill_run(order, tiles_x, 0, 1, tiles, cursor, pair_start, tile_ids, pair_of)
    else:
        for j in prange(parts):
            _fill_run(order, tiles_x, j, parts, tiles, cursor, pair_start, tile_ids, pair_of)
    return tile_start, tile_ids, pair_start, pair_of


@njit(cache=True, error_model="numpy")
def _run_bounds(j, parts, n):
    """First and end of run j when n items are cut into `parts` runs of consecutive ones."""
    return j * n // parts, (j + 1) * n // parts


@njit(cache=True, error_model="numpy")
def _count_run(box, order, tile, tiles_x, shift, pow2, j, parts, tiles, cursor, pair_start, rank):
    """`bin_tiles`' first pass over run j of `parts`: its entries per tile, each survivor's tile
    range, entry count and rank."""
    m0, m1 = _run_bounds(j, parts, order.shape[0])
    for m in range(m0, m1):
        if m + _AHEAD < m1:
            _prefetch(box, order[m + _AHEAD])
        i = order[m]
        rank[i] = m
        if pow2:
            tx0, tx1, ty0, ty1 = box[i, 0] >> shift, box[i, 1] >> shift, box[i, 2] >> shift, box[i, 3] >> shift
        else:
            tx0, tx1, ty0, ty1 = box[i, 0] // tile, box[i, 1] // tile, box[i, 2] // tile, box[i, 3] // tile
        tiles[m, 0], tiles[m, 1], tiles[m, 2], tiles[m, 3] = tx0, tx1, ty0, ty1
        for ty in range(ty0, ty1 + 1):
            for tx in range(tx0, tx1 + 1):
                cursor[j, ty * tiles_x + tx] += 1
        pair_start[m + 1] = (ty1 - ty0 + 1) * (tx1 - tx0 + 1)


@njit(cache=True, error_model="numpy")
def _fill_run(order, tiles_x, j, parts, tiles, cursor, pair_start, tile_ids, pair_of):
    """`bin_tiles`' second pass over run j of `parts`: its entries written at its own cursors."""
    m0, m1 = _run_bounds(j, parts, order.shape[0])
    q = pair_start[m0]
    for m in range(m0, m1):
        i = order[m]
        for ty in range(tiles[m, 2], tiles[m, 3] + 1):
            for tx in range(tiles[m, 0], tiles[m, 1] + 1):
                t = ty * tiles_x + tx
                at = cursor[j, t]
                tile_ids[at] = i
                pair_of[q] = at
                q += 1
                cursor[j, t] = at + 1


# ---------------------------------------------------------------------------------------------
# Compositing
# ---------------------------------------------------------------------------------------------

_EXP_MIN = LOG_ALPHA_MIN - 2.0  # exponents below this give alpha < ALPHA_MIN anyway
_TAYLOR = tuple(1.0 / math.factorial(k) for k in range(20))  # e^y's series


@njit(cache=True, error_model="numpy")
def _exp_nonpositive(x, ft):
    """e^x for x in [_EXP_MIN, 0], clamped below at _EXP_MIN, in the float type ft of x (a scalar
    or a `simd.Vec`; relative error < 1e-14 in float64, < 2e-6 in float32). See `_exp_of_8th`,
    which takes x / 8."""
    return _exp_of_8th(max(x, ft(_EXP_MIN)) * ft(0.125), ft)


@njit(cache=True, error_model="numpy")
def _exp_of_8th(y, ft):
    """e^(8 y) for y in [_EXP_MIN / 8, 0], in the float type ft of y (a scalar or a `simd.Vec`).

    Plain multiply-adds, so a row of pixels evaluates in SIMD lanes (a libm call per pixel was
    60% of the compositing time): the Taylor series at y (|y| < 0.95; 12 terms in float32, 20 in
    float64), then squared three times. The series runs by Estrin's scheme, in pairs, so that its
    chain of dependent operations is 4 or 5 deep rather than 11 or 19 (the compositing waits on
    it); three squarings multiply its rounding error by 8 (five, from y = x / 32, multiplied it
    by 32). Forward and backward both use it, so they agree on every alpha bit. Every constant is
    cast to ft: a float64 literal would turn float32 lanes into float64 ones.
    """
    c = _TAYLOR
    y2 = y * y
    y4 = y2 * y2
    y8 = y4 * y4
    # Decided at compile time: the comparison of two constants folds away.
    if ft(1.0) + ft(1e-10) != ft(1.0):
        # float64: 20 terms (the next, 0.95^20 / 20!, is below 1e-19)
        f0 = fma(y2, fma(y, ft(c[3]), ft(c[2])), fma(y, ft(c[1]), ft(c[0])))
        f1 = fma(y2, fma(y, ft(c[7]), ft(c[6])), fma(y, ft(c[5]), ft(c[4])))
        f2 = fma(y2, fma(y, ft(c[11]), ft(c[10])), fma(y, ft(c[9]), ft(c[8])))
        f3 = fma(y2, fma(y, ft(c[15]), ft(c[14])), fma(y, ft(c[13]), ft(c[12])))
        f4 = fma(y2, fma(y, ft(c[19]), ft(c[18])), fma(y, ft(c[17]), ft(c[16])))
        p = fma(y8 * y8, f4, fma(y8, fma(y4, f3, f2), fma(y4, f1, f0)))
    else:
        # float32: 12 terms (the next, 0.95^12 / 12!, is below 2e-9)
        f0 = fma(y2, fma(y, ft(c[3]), ft(c[2])), fma(y, ft(c[1]), ft(c[0])))
        f1 = fma(y2, fma(y, ft(c[7]), ft(c[6])), fma(y, ft(c[5]), ft(c[4])))
        f2 = fma(y2, fma(y, ft(c[11]), ft(c[10])), fma(y, ft(c[9]), ft(c[8])))
        p = fma(y8, f2, fma(y4, f1, f0))
    p = p * p
    p = p * p
    return p * p


# A tile's pixels are processed LANES at a time (a tile row wider than LANES spans several chunks),
# each quantity of those pixels one `simd.Vec`: one AVX-512 register of float32, two AVX2 ones.
# Pixel state is stored per chunk as LANES-long runs of each field (structure of arrays), chunk
# b = tile row * chunks + chunk being row b of a 2D array, with one more tile row of padding.

# Forward pixel state runs: features 0-5, depth, transmittance (negated once the pixel has stopped).
S_DEPTH, S_T = FEATURES, FEATURES + 1
FORWARD_RUNS = FEATURES + 2
# With depth distortion, two more: the running moment sum w z and the distortion itself.
S_MOMENT, S_DIST = FORWARD_RUNS, FORWARD_RUNS + 1
DISTORTION_RUNS = 2
# Backward pixel state runs: upstream dL/dfeatures (0-5), T (walked back), the weighted sum behind,
# dL/dT_out T_out, dL/ddepth.
B_T, B_BEHIND, B_GOUT, B_GDEPTH = FEATURES, FEATURES + 1, FEATURES + 2, FEATURES + 3
BACKWARD_RUNS = FEATURES + 4
# With depth distortion, four more: dL/dD, the ray's sum of weights W and moment M, and the moment
# up to and including the current Gaussian (walked back from M).
B_DIST_G, B_DIST_W, B_DIST_M, B_DIST_MI = BACKWARD_RUNS, BACKWARD_RUNS + 1, BACKWARD_RUNS + 2, BACKWARD_RUNS + 3
DISTORTION_BACKWARD_RUNS = 4


@njit(cache=True, boundscheck=False, error_model="numpy")
def _pixels(ft, x0, y0, chunks, c0, c1, r1, r, ch, packed):
    """Where the LANES lanes of one step over a Gaussian's box sit in the tile at (x0, y0).

    Not packed: the LANES pixels of chunk ch of row r. Packed (a box at most LANES / 2 wide within
    one chunk): two rows at once, the lower lanes LANES / 2 pixels of row r and the upper lanes the
    same columns of row r + 1, which halves the steps over the narrow boxes of small Gaussians.
    Returns the state rows and in-row offsets of the two halves (for `simd.load_at`), the pixel
    centres px, py and the mask of lanes inside the box (columns c0..c1, rows up to r1). A row
    r + 1 past the tile is the state's padding row (masked out).
    """
    half = LANES // 2
    b_lo = (r - y0) * chunks + ch
    if packed:
        lo = hi = min(c0 - x0 - ch * LANES, half)
        r_hi, b_hi = r + 1, b_lo + chunks
    else:
        lo, hi = 0, half
        r_hi, b_hi = r, b_lo
    upper = upper_lanes()
    base = x0 + ch * LANES
    col = half_iota(ft) + select(upper, splat(ft(base + hi)), splat(ft(base + lo)))
    row = select(upper, splat(ft(r_hi)), splat(ft(r)))
    inside = (col >= ft(c0)) & (col <= ft(c1)) & (row <= ft(r1))
    # Pixel centres are exact integers plus one half, so every pass computes the same offsets.
    return b_lo, lo, b_hi, hi, col + ft(0.5), row + ft(0.5), inside


@njit(cache=True, boundscheck=False, error_model="numpy")
def _alpha(surfel, lowpass, g, px, py, inside):
    """alpha, depth, 1 / hz and the mask of pixels with alpha > 0 of Gaussian g (its geom row) at
    the pixel centres (px, py) of the lanes; only lanes inside (its box) can have alpha > 0.

    surfel: rho = (hx^2 + hy^2) / hz^2 where that is strictly below the low-pass rho2d = lowpass |p - c|^2
            (which implies hz != 0: no division at grazing rays), else rho2d; depth is det T / hz
            (the z of the ray-splat intersection) or the centre depth (2DGS). lowpass (in g's dtype) is
            2DGS's 2 (LOWPASS_RHO_SCALE), or that over zoom^2 for the filter of a camera zoom times coarser.
    ewa:    rho = d^T conic d with d = p - c; depth is the centre depth.
    alpha = min(o exp(-rho / 2), ALPHA_MAX) where o exp(-rho / 2) >= ALPHA_MIN, else exactly 0.
    1 / hz is kept on the ray-splat branch and 0 on the filter branch (and for ewa), so the backward
    pass takes the very branch the forward pass took; lanes with alpha 0 get depth and 1 / hz 0.
    Plain IEEE arithmetic (see `simd`): a pixel gets the same bits from it in every pass, packed or
    not. Computes in the dtype of g, constants included.
    """
    ft = g.dtype.type
    zero, one = ft(0.0), ft(1.0)
    dy = py - g[GEOM_CY]
    if surfel:
        ey = py - g[GEOM_LP + 1]
        dx = px - g[GEOM_CX]
        # Terms in px alone first: they are the same on every row of a column of steps, so the
        # compiler can compute them once a column (`_blend`).
        hx = fma(dy, g[GEOM_C], fma(dx, g[GEOM_B], g[GEOM_A]))
        hy = fma(dy, g[GEOM_C + 1], fma(dx, g[GEOM_B + 1], g[GEOM_A + 1]))
        hz = fma(dy, g[GEOM_C + 2], fma(dx, g[GEOM_B + 2], g[GEOM_A + 2]))
        ex = px - g[GEOM_LP]
        rho2d = fma(ey * lowpass, ey, (ex * lowpass) * ex)
        inv = one / hz  # first, as it is the slowest step (where hz = 0 it is not used)
        q = fma(hx, hx, hy * hy)
        ray = q < rho2d * (hz * hz)
        rho = select(ray, q * inv * inv, rho2d)
        depth = select(ray, g[GEOM_DET] * inv, splat(g[GEOM_DEPTH]))
    else:
        dx = px - g[GEOM_CX]
        rho = fma(dy, fma(dy, g[GEOM_CONIC + 2], (ft(2.0) * g[GEOM_CONIC + 1]) * dx), (dx * g[GEOM_CONIC]) * dx)
        depth = splat(g[GEOM_DEPTH])
        inv = splat(zero)
        ray = inv != inv  # no lane
    # log(alpha) / 8 = (log o - rho / 2) / 8 in one rounding: scaling by 2^-3 is exact, so the
    # test against LOG_ALPHA_MIN / 8 is the test against LOG_ALPHA_MIN, and the exponential takes it
    # as it is. Lanes that fail the test are not used, whatever their exponential.
    y = fma(rho, ft(-1.0 / 16.0), splat(g[GEOM_LOGO] * ft(0.125)))
    ok = inside & (y >= ft(LOG_ALPHA_MIN) * ft(0.125))
    alpha = select(ok, min(_exp_of_8th(y, ft), ft(ALPHA_MAX)), splat(zero))
    inv = select(ray & ok, inv, splat(zero))
    return alpha, select(ok, depth, splat(zero)), inv, ok


@njit(cache=True, boundscheck=False, error_model="numpy")
def _blend(surfel, lowpass, g, f, state, last, x0, y0, chunks, c0, c1, r0, r1, position, distortion):
    """Front-to-back blending of one Gaussian (geom row g, features f) into the chunks of its box,
    columns c0..c1 and rows r0..r1 of the tile at (x0, y0): state [(tile + 1) chunks,
    FORWARD_RUNS * LANES], last [(tile + 1) chunks, LANES] (1 + the tile-list position of each
    pixel's last blended Gaussian), the last tile row of each being padding (`_pixels`). Returns
    how many pixels stopped.

    The 3DGS/2DGS rule: a pixel takes the Gaussian when alpha > 0 and it has not stopped; the
    Gaussian that would take its transmittance below the floor ends the pixel and is itself not
    blended. Masks select what a branch would have skipped.

    distortion: None, or an array (only its type is read) to also accumulate 2DGS's depth distortion
    of the Gaussian's centre depth z in the runs S_MOMENT and S_DIST. Numba compiles one variant per
    type and drops the branch from the None one, so rendering without it costs what it did.
    """
    ft = state.dtype.type
    ch0, ch1 = (c0 - x0) // LANES, (c1 - x0) // LANES
    total = 0
    # A step over pixels that have all stopped computes alpha to no effect (their T <= 0 takes
    # nothing): that costs less than keeping count of each row's running pixels to skip it.
    if ch0 == ch1 and c1 - c0 < LANES // 2:  # packed: two half rows a step
        for r in range(r0, r1 + 1, 2):
            b, lo, b2, hi, px, py, inside = _pixels(ft, x0, y0, chunks, c0, c1, r1, r, ch0, True)
            a, d, _, ok = _alpha(surfel, lowpass, g, px, py, inside)
            if any_lane(ok):
                total += _take(state, last, (b, lo, b2, hi), a, d, ok, f, g[GEOM_DEPTH], position, distortion)
    else:
        # Whole rows, a column of chunks at a time (each pixel is one step's alone, so their order
        # is free), so that what the step computes from the columns alone can be hoisted out of the
        # loop over rows.
        for ch in range(ch0, ch1 + 1):
            for r in range(r0, r1 + 1):
                b, _, _, _, px, py, inside = _pixels(ft, x0, y0, chunks, c0, c1, r1, r, ch, False)
                a, d, _, ok = _alpha(surfel, lowpass, g, px, py, inside)
                if any_lane(ok):
                    total += _take(state, last, (b,), a, d, ok, f, g[GEOM_DEPTH], position, distortion)
    return total


@njit(cache=True, boundscheck=False, error_model="numpy")
def _take(state, last, at, a, d, ok, f, z, position, distortion):
    """One step of `_blend`: the Gaussian of alpha a (lanes ok) and pair depth d blended into the
    LANES pixels at `at` (`simd.load_at`: (row,) for a whole row, or two half rows). Returns how
    many pixels stopped. The place's type selects the loads and stores when compiling, so whole
    rows take one load and one store a run."""
    ft = state.dtype.type
    zero, one, two = ft(0.0), ft(1.0), ft(2.0)
    T = _get(state, at, S_T * LANES)
    T_next = T * (one - a)
    takes = ok & (T > zero)
    ends = takes & (T_next < ft(TRANSMITTANCE_MIN))
    blends = takes & (T_next >= ft(TRANSMITTANCE_MIN))
    w = select(blends, a * T, splat(zero))  # 0 adds nothing (the runs start at +0)
    _put(state, at, 0, fma(w, f[0], _get(state, at, 0)))
    _put(state, at, LANES, fma(w, f[1], _get(state, at, LANES)))
    _put(state, at, 2 * LANES, fma(w, f[2], _get(state, at, 2 * LANES)))
    _put(state, at, 3 * LANES, fma(w, f[3], _get(state, at, 3 * LANES)))
    _put(state, at, 4 * LANES, fma(w, f[4], _get(state, at, 4 * LANES)))
    _put(state, at, 5 * LANES, fma(w, f[5], _get(state, at, 5 * LANES)))
    _put(state, at, S_DEPTH * LANES, fma(w, d, _get(state, at, S_DEPTH * LANES)))
    if distortion is not None:
        # D += 2 w (z A - M) with the two running moments of 2DGS's rasterizer: A = 1 - T,
        # the weights in front, and M = sum w z in front.
        moment = _get(state, at, S_MOMENT * LANES)
        gap = fma(one - T, z, -moment)
        _put(state, at, S_DIST * LANES, fma(two * w, gap, _get(state, at, S_DIST * LANES)))
        _put(state, at, S_MOMENT * LANES, fma(w, z, moment))
    _put(state, at, S_T * LANES, select(blends, T_next, select(ends, -T, T)))
    _put(last, at, 0, select(blends, splat(position), _get(last, at, 0)))
    return count(ends)


@njit(cache=True, boundscheck=False, error_model="numpy")
def _composite_tile(
    surfel,
    lowpass,
    geom,
    features,
    box,
    ids,
    x0,
    y0,
    x1,
    y1,
    tile,
    state,
    last,
    out_color,
    out_normal,
    out_depth,
    out_trans,
    out_last,
    out_distortion,
):
    """Front-to-back compositing of one tile, its pixels x0..x1 - 1, y0..y1 - 1, whose Gaussians
    are ids (input indices, front to back), into the tile's part of the outputs (see
    `composite_forward`); state and last are the tile's scratch, set here."""
    ft = geom.dtype.type
    chunks = -(-tile // LANES)
    state[:] = ft(0.0)
    state[:, S_T * LANES : (S_T + 1) * LANES] = ft(1.0)
    last[:] = 0
    active = (x1 - x0) * (y1 - y0)
    n = ids.shape[0]
    for k in range(n):
        if active == 0:
            break  # every pixel of the tile has reached the transmittance floor
        if k + _AHEAD < n:
            ahead = ids[k + _AHEAD]
            _prefetch(geom, ahead)
            _prefetch(box, ahead)
            _prefetch(features, ahead)
        i = ids[k]
        c0, c1 = max(box[i, 0], x0), min(box[i, 1], x1 - 1)
        r0, r1 = max(box[i, 2], y0), min(box[i, 3], y1 - 1)
        if c0 <= c1 and r0 <= r1:
            active -= _blend(
                surfel,
                lowpass,
                geom[i],
                features[i],
                state,
                last,
                x0,
                y0,
                chunks,
                c0,
                c1,
                r0,
                r1,
                np.int32(k + 1),
                out_distortion,
            )
    # Read out, LANES pixels at a time (a tile row's last chunk masked).
    for r in range(y0, y1):
        for ch in range(chunks):
            x = x0 + ch * LANES
            n = min(LANES, x1 - x)
            if n <= 0:
                break
            b = (r - y0) * chunks + ch
            for f in range(3):
                store_first(out_color[f], r, x, load(state, b, f * LANES), n)
                store_first(out_normal[f], r, x, load(state, b, (3 + f) * LANES), n)
            store_first(out_depth, r, x, load(state, b, S_DEPTH * LANES), n)
            T = load(state, b, S_T * LANES)
            store_first(out_trans, r, x, select(T < ft(0.0), -T, T), n)
            store_first(out_last, r, x, load(last, b, 0), n)
            if out_distortion is not None:
                store_first(out_distortion[0], r, x, load(state, b, S_DIST * LANES), n)
                store_first(out_distortion[1], r, x, load(state, b, S_MOMENT * LANES), n)


@njit(parallel=True, cache=True, boundscheck=False, error_model="numpy")
def composite_forward(
    surfel,
    lowpass,
    geom,
    features,
    box,
    tile_start,
    tile_ids,
    width,
    height,
    tile,
    tiles_x,
    out_color,
    out_normal,
    out_depth,
    out_trans,
    out_last,
    out_distortion=None,
):
    """Front-to-back alpha compositing of every tile (tiles in parallel).

    geom [N, GEOM_SIZE], features [N, 6] and box [N, 4] of every Gaussian (input order); tile_ids
    lists each tile's survivors by input index, front to back.
    Writes the blended out_color [3, H, W], out_normal [3, H, W], out_depth [H, W], the final
    transmittance out_trans [H, W] and out_last [H, W] (1 + position in the tile list of the last
    blended Gaussian). Computes in the dtype of geom, which features and the float outputs share.
    Inside a tile the loop runs over its Gaussians, front to back, and for each over the chunks of
    the rows of its box; the tile stops once all of its pixels have.
    out_distortion: None, or [2, H, W] for 2DGS's depth distortion and the ray's moment sum w z
    (kept for the backward); None compiles the kernel without it (see `_blend`).
    """
    ft = geom.dtype.type
    lp = ft(lowpass)  # in the pixels' dtype once, so the pixel loop has no float64 arithmetic
    n_tiles = tile_start.shape[0] - 1
    chunks = -(-tile // LANES)
    runs = FORWARD_RUNS if out_distortion is None else FORWARD_RUNS + DISTORTION_RUNS
    for t in prange(n_tiles):
        x0, y0 = (t % tiles_x) * tile, (t // tiles_x) * tile
        _composite_tile(
            surfel,
            lp,
            geom,
            features,
            box,
            tile_ids[tile_start[t] : tile_start[t + 1]],
            x0,
            y0,
            min(x0 + tile, width),
            min(y0 + tile, height),
            tile,
            np.empty(((tile + 1) * chunks, runs * LANES), dtype=ft),
            np.empty(((tile + 1) * chunks, LANES), dtype=np.int32),
            out_color,
            out_normal,
            out_depth,
            out_trans,
            out_last,
            out_distortion,
        )


@njit(cache=True, boundscheck=False, error_model="numpy")
def _get(array, at, col):
    """The lanes at `at` ((b,) or (b, lo, b2, hi): `_pixels`, `simd.load_at`) of the run starting at
    column col of array."""
    return load_at(array, at, col)


@njit(cache=True, boundscheck=False, error_model="numpy")
def _put(array, at, col, value):
    """Store value to the lanes at `at` of the run starting at column col of array (`_get`)."""
    store_at(array, at, col, value)


@njit(cache=True, boundscheck=False, error_model="numpy")
def _unblend(state, last, at, a, d, position, f, z, distortion):
    """The compositing's chain rule at the LANES pixels at = (b, lo, b2, hi) of state (`_pixels`,
    `simd.load_at`) for one Gaussian of alpha a and pair depth d (features f, centre depth z), back
    to front.

    With w_i = a_i T_i and T_out = T_in prod (1 - a_i), for a loss L with dL/dw_i = g_i:
      dL/da_i = T_i g_i - (sum_{j>i} w_j g_j + dL/dT_out T_out) / (1 - a_i).
    A pixel takes part where alpha > 0 and the Gaussian is not behind its last blended one
    (position < last). It recovers T_i = T_{i+1} / (1 - a_i) and carries the sum behind in state.
    Returns (on, w, dL/d(pair depth) upstream, dL/d(log alpha) where it passes to rho and the
    opacity (0 elsewhere), the upstream feature gradients u0-u5, and dL/dz of the depth
    distortion (0 without it)). distortion: None, or an array (its type selects the variant, as in
    `_blend`) to add the depth distortion's gradients.
    """
    ft = state.dtype.type
    zero, one, two = ft(0.0), ft(1.0), ft(2.0)
    on = (a > zero) & (splat(position) < _get(last, at, 0))
    T_behind = _get(state, at, B_T * LANES)
    inv_one_minus = one / (one - a)
    T = T_behind * inv_one_minus
    w = a * T
    g_d = _get(state, at, B_GDEPTH * LANES)
    u0, u1, u2 = _get(state, at, 0), _get(state, at, LANES), _get(state, at, 2 * LANES)
    u3, u4, u5 = _get(state, at, 3 * LANES), _get(state, at, 4 * LANES), _get(state, at, 5 * LANES)
    # dL/dw: the upstream gradients times what the pair adds, summed as a tree (a shorter chain)
    g_w = (fma(g_d, d, u0 * f[0]) + fma(u1, f[1], u2 * f[2])) + (fma(u3, f[3], u4 * f[4]) + u5 * f[5])
    g_z = splat(zero)
    if distortion is not None:
        # D = 2 sum_i w_i (z_i A_i - M_i) is a function of the weights and depths alone, so its
        # dL/dw joins g_w and the chain rule that follows carries it to the alphas. With the ray's totals
        # W = sum w, M = sum w z and the moments A', M' up to and including i (A' = 1 - T behind):
        # dD/dw_i = 2 (2 (z_i A'_i - M'_i) + M - z_i W),  dD/dz_i = 2 w_i (2 A'_i - w_i - W).
        g_dist = _get(state, at, B_DIST_G * LANES)
        total_w = _get(state, at, B_DIST_W * LANES)
        moment = _get(state, at, B_DIST_MI * LANES)
        a_incl = one - T_behind
        spread = two * fma(a_incl, z, -moment) + (_get(state, at, B_DIST_M * LANES) - total_w * z)
        g_w = fma(two * g_dist, spread, g_w)
        _put(state, at, B_DIST_MI * LANES, select(on, moment - w * z, moment))
        g_z = select(on, two * g_dist * w * ((two * a_incl - w) - total_w), splat(zero))
    behind = _get(state, at, B_BEHIND * LANES)
    g_a = T * g_w - (behind + _get(state, at, B_GOUT * LANES)) * inv_one_minus
    _put(state, at, B_T * LANES, select(on, T, T_behind))
    _put(state, at, B_BEHIND * LANES, select(on, fma(w, g_w, behind), behind))
    # alpha = min(exp(.), 0.99): a clamped pair passes nothing on to rho or the opacity.
    g_log_alpha = select(on & (a < ft(ALPHA_MAX)), g_a * a, splat(zero))
    w = select(on, w, splat(zero))
    return on, w, g_d, g_log_alpha, u0, u1, u2, u3, u4, u5, g_z


@njit(cache=True, boundscheck=False, error_model="numpy")
def _unblend_box(
    surfel,
    lowpass,
    g,
    f,
    state,
    last,
    rows,
    x0,
    y0,
    chunks,
    c0,
    c1,
    r0,
    r1,
    position,
    distortion,
    pair_grads,
    k,
    abs_coef,
    i,
    abs_pairs,
):
    """`_unblend` for one Gaussian (geom row g, features f) over its box, in the steps of `_pixels`,
    with its geometry gradients in the same pass; row k of pair_grads [pairs, GRAD_SIZE] receives the sums
    over the box.

    abs_pairs: None, or [pairs, 2] (surfels) whose row k receives the sums over the box of each pixel's
    |dL_p/dc_x| and |dL_p/dc_y| divided by the centre depth z (AbsGS; the torch backend's
    `_abs_centre_gradients`), from row i of abs_coef [N, ABS_SIZE] (`surfel_abs_coefficients`). None
    compiles the function without it (see `_blend`).

    The sums are kept per lane in registers and summed over the lanes at the end in a fixed order
    (`simd.lane_sums`). Surfel, ray-splat branch (1 / hz != 0): rho = (hx^2 + hy^2) / hz^2 and
    depth = det / hz give dL/dh, kept as sums of g_h, dx g_h, dy g_h (h = A_c + dx B + dy C), and
    dL/ddet. Filter branch: rho = lowpass |p - c_lp|^2 gives dL/dc_lp (GRAD_CX, GRAD_CY), and the centre
    depth takes dL/ddepth (and, with `distortion`, the depth distortion's dL/dz). EWA:
    rho = d^T conic d gives dL/dconic and dL/dc, and the centre depth takes dL/ddepth.
    """
    ft = state.dtype.type
    zero, half, two = ft(0.0), ft(0.5), ft(2.0)
    cx, cy, lx, ly = g[GEOM_CX], g[GEOM_CY], g[GEOM_LP], g[GEOM_LP + 1]
    ca, cb, cc = g[GEOM_CONIC], g[GEOM_CONIC + 1], g[GEOM_CONIC + 2]
    A0, A1, b0, b1, C0, C1 = g[GEOM_A], g[GEOM_A + 1], g[GEOM_B], g[GEOM_B + 1], g[GEOM_C], g[GEOM_C + 1]
    z = g[GEOM_DEPTH]
    # Per-lane sums: surfel h (3), dx h (3), dy h (3), or EWA conic (3); then c_x, c_y, det, depth,
    # log opacity and the 6 features.
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = s9 = s10 = s11 = s12 = s13 = splat(zero)
    s14 = s15 = s16 = s17 = s18 = s19 = splat(zero)
    a0 = a1 = splat(zero)  # the absolute centre gradients' per-lane sums
    if abs_pairs is not None:
        U0, U1, V0, V1 = abs_coef[i, 0], abs_coef[i, 1], abs_coef[i, 2], abs_coef[i, 3]
        tw0, tw1, kk = abs_coef[i, 4], abs_coef[i, 5], abs_coef[i, 6]
        B2, C2 = g[GEOM_B + 2], g[GEOM_C + 2]
    ch0, ch1 = (c0 - x0) // LANES, (c1 - x0) // LANES
    packed = ch0 == ch1 and c1 - c0 < LANES // 2
    for r in range(r0, r1 + 1, 2 if packed else 1):
        if rows[r - y0] <= position and (not packed or r + 1 > r1 or rows[r + 1 - y0] <= position):
            continue
        for ch in range(ch0, ch1 + 1):
            b, lo, b2, hi, px, py, inside = _pixels(ft, x0, y0, chunks, c0, c1, r1, r, ch, packed)
            a, d, inv, ok = _alpha(surfel, lowpass, g, px, py, inside)
            if not any_lane(ok):
                continue
            on, w, g_d, g_log_alpha, u0, u1, u2, u3, u4, u5, g_z = _unblend(
                state, last, (b, lo, b2, hi), a, d, position, f, z, distortion
            )
            s13 = s13 + g_log_alpha
            s14, s15, s16 = fma(w, u0, s14), fma(w, u1, s15), fma(w, u2, s16)
            s17, s18, s19 = fma(w, u3, s17), fma(w, u4, s18), fma(w, u5, s19)
            g_rho = g_log_alpha * -half
            g_dpair = w * g_d
            dx, dy = px - cx, py - cy
            if surfel:
                hx = fma(dy, C0, fma(dx, b0, A0))  # as `_alpha` computes them
                hy = fma(dy, C1, fma(dx, b1, A1))
                sc = (two * g_rho) * (inv * inv)  # 0 on the filter branch and off the box
                g_hx, g_hy = sc * hx, sc * hy
                g_hz = -fma(sc, fma(hx, hx, hy * hy), g_dpair * d) * inv
                s0, s1, s2 = s0 + g_hx, s1 + g_hy, s2 + g_hz
                s3, s4, s5 = fma(dx, g_hx, s3), fma(dx, g_hy, s4), fma(dx, g_hz, s5)
                s6, s7, s8 = fma(g_hx, dy, s6), fma(g_hy, dy, s7), fma(g_hz, dy, s8)
                s11 = fma(g_dpair, inv, s11)
                filtered = on & (inv == zero)
                sc2 = select(filtered, g_rho * (two * lowpass), splat(zero))
                s9 = s9 - sc2 * (px - lx)
                s10 = s10 - sc2 * (py - ly)
                s12 = s12 + select(filtered, g_dpair, splat(zero)) + g_z
                if abs_pairs is not None:
                    # this pixel's dL/dT_x[2] and dL/dT_y[2] alone: through h = h_u x h_v (h_u = U + dx T_w,
                    # h_v = V + dy T_w), det T and the low-pass centre (`_abs_centre_gradients`)
                    g_det = g_dpair * inv
                    gx = g_hx * fma(dy, tw1, V1) - g_hy * fma(dy, tw0, V0)
                    gx = fma(g_det, B2, gx) - (kk * sc2) * (px - lx)
                    gy = fma(dx, tw0, U0) * g_hy - fma(dx, tw1, U1) * g_hx
                    gy = fma(g_det, C2, gy) - (kk * sc2) * (py - ly)
                    a0 = a0 + max(gx, -gx)
                    a1 = a1 + max(gy, -gy)
            else:
                s0 = fma(g_rho * dx, dx, s0)
                s1 = fma(two * g_rho * dx, dy, s1)
                s2 = fma(g_rho * dy, dy, s2)
                s9 = s9 - (two * g_rho) * fma(dx, ca, dy * cb)
                s10 = s10 - (two * g_rho) * fma(dx, cb, dy * cc)
                s12 = s12 + g_dpair
    store(pair_grads, k, 0, lane_sums((s0, s1, s2, s3, s4, s5, s6, s7, s8, s9, s10, s11, s12, s13, s14, s15)))
    rest = lane_sums((s16, s17, s18, s19))
    for j in range(GRAD_SIZE - LANES):
        pair_grads[k, LANES + j] = lane(rest, j)
    if abs_pairs is not None:
        sums = lane_sums((a0, a1))
        abs_pairs[k, 0] = lane(sums, 0)
        abs_pairs[k, 1] = lane(sums, 1)


@njit(parallel=True, cache=True, boundscheck=False, error_model="numpy")
def composite_backward(
    surfel,
    lowpass,
    geom,
    features,
    box,
    tile_start,
    tile_ids,
    width,
    height,
    tile,
    tiles_x,
    trans_final,
    last,
    g_color,
    g_normal,
    g_alpha,
    g_depth,
    pair_grads,
    distortion=None,
    abs_coef=None,
    abs_pairs=None,
):
    """Gradients of the compositing by back-to-front traversal of every tile (tiles in parallel).

    Walking back to front, each pixel recovers the transmittance in front of a Gaussian by dividing
    out its alpha and carries the weighted sum of what lies behind (`_unblend`), so nothing per
    pair is stored. g_color [3, H, W], g_normal [3, H, W], g_alpha [H, W] and g_depth [H, W] are
    the upstream gradients. pair_grads [pairs, GRAD_SIZE] receives, for every entry k of
    tile_ids, the gradient sums of that Gaussian over that tile's pixels (zeros where it
    contributed nothing), summed per lane and then over the lanes in a fixed order: each row is
    written once, by the one thread that owns the tile, so the result does not depend on
    scheduling. Computes in the dtype of geom, which every float argument shares.
    distortion: None, or [2, H, W] holding the upstream dL/d(depth distortion) and the forward's
    moment sum w z of each ray (surfels; None compiles the kernel without it, see `_blend`).
    abs_coef [N, ABS_SIZE] and abs_pairs [pairs, 2]: None, or the absolute centre gradients' constants and
    per-entry sums (`_unblend_box`; surfels).
    """
    ft = geom.dtype.type
    zero, one = ft(0.0), ft(1.0)
    lp = ft(lowpass)  # in the pixels' dtype once (`composite_forward`)
    n_tiles = tile_start.shape[0] - 1
    chunks = -(-tile // LANES)
    runs = BACKWARD_RUNS if distortion is None else BACKWARD_RUNS + DISTORTION_BACKWARD_RUNS
    for t in prange(n_tiles):
        x0, y0 = (t % tiles_x) * tile, (t // tiles_x) * tile
        x1, y1 = min(x0 + tile, width), min(y0 + tile, height)
        # One more tile row, of padding (`_pixels`).
        state = np.zeros(((tile + 1) * chunks, runs * LANES), dtype=ft)
        last_px = np.zeros(((tile + 1) * chunks, LANES), dtype=np.int32)
        rows = np.zeros(tile + 1, dtype=np.int64)  # the largest `last` of each tile row
        for r in range(y0, y1):
            for c in range(x0, x1):
                b, j = (r - y0) * chunks + (c - x0) // LANES, (c - x0) % LANES
                for f in range(3):
                    state[b, f * LANES + j] = g_color[f, r, c]
                    state[b, (3 + f) * LANES + j] = g_normal[f, r, c]
                state[b, B_T * LANES + j] = trans_final[r, c]
                state[b, B_GOUT * LANES + j] = -g_alpha[r, c] * trans_final[r, c]  # alpha = 1 - T_out
                state[b, B_GDEPTH * LANES + j] = g_depth[r, c]
                if distortion is not None:
                    state[b, B_DIST_G * LANES + j] = distortion[0, r, c]
                    state[b, B_DIST_W * LANES + j] = one - trans_final[r, c]
                    state[b, B_DIST_M * LANES + j] = distortion[1, r, c]
                    state[b, B_DIST_MI * LANES + j] = distortion[1, r, c]
                last_px[b, j] = last[r, c]
                rows[r - y0] = max(rows[r - y0], last[r, c])
        n_last = rows.max()
        start = tile_start[t]
        for k in range(start + n_last, tile_start[t + 1]):
            pair_grads[k, :] = zero  # behind every pixel's last blended Gaussian
            if abs_pairs is not None:
                abs_pairs[k, :] = zero
        for k in range(start + n_last - 1, start - 1, -1):
            if k - _AHEAD >= start:
                ahead = tile_ids[k - _AHEAD]
                _prefetch(geom, ahead)
                _prefetch(box, ahead)
                _prefetch(features, ahead)
            i = tile_ids[k]
            c0, c1 = max(box[i, 0], x0), min(box[i, 1], x1 - 1)
            r0, r1 = max(box[i, 2], y0), min(box[i, 3], y1 - 1)
            if c0 > c1 or r0 > r1:
                pair_grads[k, :] = zero
                if abs_pairs is not None:
                    abs_pairs[k, :] = zero
                continue
            position = np.int32(k - start)
            _unblend_box(
                surfel,
                lp,
                geom[i],
                features[i],
                state,
                last_px,
                rows,
                x0,
                y0,
                chunks,
                c0,
                c1,
                r0,
                r1,
                position,
                distortion,
                pair_grads,
                k,
                abs_coef,
                i,
                abs_pairs,
            )


# ---------------------------------------------------------------------------------------------
# Projection backward
# ---------------------------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def _surfel_backward(mu, R, s0, s1, R_cw, K, gr, cx, cy, lx, ly, lowpass_sigma, rotation, g_rot, g_scale):
    """Chain rule of the surfel projection: adds dL/ds and (`rotation` True) dL/d(R e1, R e2), returns dL/dmu.

    gr is the survivor's gradient row from the compositing (GRAD_* columns); (cx, cy) the
    projected centre the cross product was expanded around, (lx, ly) the low-pass centre.
    """
    tx0, tx1, tx2, ty0, ty1, ty2, tw0, tw1, tw2 = _surfel_matrix(mu, R, s0, s1, R_cw, K)
    # h = A + p_x B + p_y C = A_c + dx B + dy C: the centre cancels, so with dx = p_x - c_x
    # dL/dA = sum g_h, dL/dB = sum (dx + c_x) g_h, dL/dC = sum (dy + c_y) g_h.
    gA0, gA1, gA2 = gr[GRAD_H], gr[GRAD_H + 1], gr[GRAD_H + 2]
    gB0, gB1, gB2 = gr[GRAD_HX] + cx * gA0, gr[GRAD_HX + 1] + cx * gA1, gr[GRAD_HX + 2] + cx * gA2
    gC0, gC1, gC2 = gr[GRAD_HY] + cy * gA0, gr[GRAD_HY + 1] + cy * gA1, gr[GRAD_HY + 2] + cy * gA2
    g_det = gr[GRAD_DET]
    # For u = a x b: dL/da = b x g_u, dL/db = g_u x a; A = Tx x Ty, B = Ty x Tw, C = Tw x Tx,
    # and det = Tw . A adds g_det Tw to dL/dA and g_det A to dL/dTw.
    gdA0, gdA1, gdA2 = gA0 + g_det * tw0, gA1 + g_det * tw1, gA2 + g_det * tw2
    gx0 = ty1 * gdA2 - ty2 * gdA1 + gC1 * tw2 - gC2 * tw1
    gx1 = ty2 * gdA0 - ty0 * gdA2 + gC2 * tw0 - gC0 * tw2
    gx2 = ty0 * gdA1 - ty1 * gdA0 + gC0 * tw1 - gC1 * tw0
    gy0 = gdA1 * tx2 - gdA2 * tx1 + tw1 * gB2 - tw2 * gB1
    gy1 = gdA2 * tx0 - gdA0 * tx2 + tw2 * gB0 - tw0 * gB2
    gy2 = gdA0 * tx1 - gdA1 * tx0 + tw0 * gB1 - tw1 * gB0
    ax, ay, az = tx1 * ty2 - tx2 * ty1, tx2 * ty0 - tx0 * ty2, tx0 * ty1 - tx1 * ty0
    gw0 = gB1 * ty2 - gB2 * ty1 + tx1 * gC2 - tx2 * gC1 + g_det * ax
    gw1 = gB2 * ty0 - gB0 * ty2 + tx2 * gC0 - tx0 * gC2 + g_det * ay
    gw2 = gB0 * ty1 - gB1 * ty0 + tx0 * gC1 - tx1 * gC0 + g_det * az
    # Low-pass centre: the box centre c = (C02, C12) / C22 of the dual conic C = T diag(1, 1, e) T^T,
    # or the projected centre (Tx[2], Ty[2]) / mu_z; filter-branch depth Tw[2].
    g_cx, g_cy = gr[GRAD_CX], gr[GRAD_CY]
    g_mu_z = 0.0
    _, _, c22 = _lowpass_center(tx0, tx1, tx2, ty0, ty1, ty2, tw0, tw1, tw2, cx, cy, lowpass_sigma)
    if c22 != 0.0:
        e = -1.0 / (lowpass_sigma * lowpass_sigma)
        gx0 += g_cx * tw0 / c22
        gx1 += g_cx * tw1 / c22
        gx2 += g_cx * e * tw2 / c22
        gy0 += g_cy * tw0 / c22
        gy1 += g_cy * tw1 / c22
        gy2 += g_cy * e * tw2 / c22
        gw0 += (g_cx * (tx0 - 2.0 * lx * tw0) + g_cy * (ty0 - 2.0 * ly * tw0)) / c22
        gw1 += (g_cx * (tx1 - 2.0 * lx * tw1) + g_cy * (ty1 - 2.0 * ly * tw1)) / c22
        gw2 += e * (g_cx * (tx2 - 2.0 * lx * tw2) + g_cy * (ty2 - 2.0 * ly * tw2)) / c22
    elif abs(mu[2]) > _NEAR_ZERO:
        gx2 += g_cx / mu[2]
        gy2 += g_cy / mu[2]
        g_mu_z = -(g_cx * cx + g_cy * cy) / mu[2]
    gw2 += gr[GRAD_DEPTH]
    # T = K M with M = [u s0, v s1, mu]: dL/dM = K^T dL/dT (rows of dL/dT: gx, gy, gw).
    gm00 = K[0, 0] * gx0 + K[1, 0] * gy0 + K[2, 0] * gw0
    gm10 = K[0, 1] * gx0 + K[1, 1] * gy0 + K[2, 1] * gw0
    gm20 = K[0, 2] * gx0 + K[1, 2] * gy0 + K[2, 2] * gw0
    gm01 = K[0, 0] * gx1 + K[1, 0] * gy1 + K[2, 0] * gw1
    gm11 = K[0, 1] * gx1 + K[1, 1] * gy1 + K[2, 1] * gw1
    gm21 = K[0, 2] * gx1 + K[1, 2] * gy1 + K[2, 2] * gw1
    gm02 = K[0, 0] * gx2 + K[1, 0] * gy2 + K[2, 0] * gw2
    gm12 = K[0, 1] * gx2 + K[1, 1] * gy2 + K[2, 1] * gw2
    gm22 = K[0, 2] * gx2 + K[1, 2] * gy2 + K[2, 2] * gw2
    # Camera-frame tangents u = R_cw R e_col: dL/ds = u . dL/dM[:, col], dL/d(R e_col) = s R_cw^T dL/dM[:, col].
    for col in range(2):
        s = s0 if col == 0 else s1
        gc0 = gm00 if col == 0 else gm01
        gc1 = gm10 if col == 0 else gm11
        gc2 = gm20 if col == 0 else gm21
        cam0 = R_cw[0, 0] * R[0, col] + R_cw[0, 1] * R[1, col] + R_cw[0, 2] * R[2, col]
        cam1 = R_cw[1, 0] * R[0, col] + R_cw[1, 1] * R[1, col] + R_cw[1, 2] * R[2, col]
        cam2 = R_cw[2, 0] * R[0, col] + R_cw[2, 1] * R[1, col] + R_cw[2, 2] * R[2, col]
        g_scale[col] += cam0 * gc0 + cam1 * gc1 + cam2 * gc2
        if rotation:
            for row in range(3):
                g_rot[row, col] += s * (R_cw[0, row] * gc0 + R_cw[1, row] * gc1 + R_cw[2, row] * gc2)
    return gm02, gm12, gm22 + g_mu_z


@njit(cache=True, error_model="numpy")
def _ewa_backward(mu, cov, R_cw, K, lim_x, lim_y, dilation, gr, g_cov):
    """Chain rule of the EWA projection: adds dL/dSigma (world) to g_cov, returns dL/dmu.

    As in the torch backend, the 2D covariance's off-diagonal is its (0, 1) entry, so dL/dSigma =
    X^T [[g_a, g_b], [0, g_c]] X with X = J W; its antisymmetric part is harmless for a symmetric Sigma.
    """
    a, b, c, p0, p1, p2, q0, q1, q2, z = _ewa_cov2d(mu, cov, R_cw, K, lim_x, lim_y)
    a += dilation
    c += dilation
    det_raw = a * c - b * b
    det = max(det_raw, _CONIC_DET_MIN)
    G0, G1, G2 = gr[GRAD_CONIC], gr[GRAD_CONIC + 1], gr[GRAD_CONIC + 2]
    # conic = (c, -b, a) / det
    g_det = -(G0 * c - G1 * b + G2 * a) / (det * det) if det_raw >= _CONIC_DET_MIN else 0.0
    g_a = G2 / det + g_det * c
    g_c = G0 / det + g_det * a
    g_b = -G1 / det - 2.0 * b * g_det
    # cov2d = X Sigma X^T with rows p, q of X and G = [[g_a, g_b], [0, g_c]]:
    # dL/dX = G X Sigma^T + G^T X Sigma, whose rows are built from Sigma p, Sigma q, Sigma^T p, Sigma^T q.
    sp0 = cov[0, 0] * p0 + cov[0, 1] * p1 + cov[0, 2] * p2
    sp1 = cov[1, 0] * p0 + cov[1, 1] * p1 + cov[1, 2] * p2
    sp2 = cov[2, 0] * p0 + cov[2, 1] * p1 + cov[2, 2] * p2
    sq0 = cov[0, 0] * q0 + cov[0, 1] * q1 + cov[0, 2] * q2
    sq1 = cov[1, 0] * q0 + cov[1, 1] * q1 + cov[1, 2] * q2
    sq2 = cov[2, 0] * q0 + cov[2, 1] * q1 + cov[2, 2] * q2
    tp0 = cov[0, 0] * p0 + cov[1, 0] * p1 + cov[2, 0] * p2
    tp1 = cov[0, 1] * p0 + cov[1, 1] * p1 + cov[2, 1] * p2
    tp2 = cov[0, 2] * p0 + cov[1, 2] * p1 + cov[2, 2] * p2
    tq0 = cov[0, 0] * q0 + cov[1, 0] * q1 + cov[2, 0] * q2
    tq1 = cov[0, 1] * q0 + cov[1, 1] * q1 + cov[2, 1] * q2
    tq2 = cov[0, 2] * q0 + cov[1, 2] * q1 + cov[2, 2] * q2
    gp0 = g_a * (sp0 + tp0) + g_b * sq0
    gp1 = g_a * (sp1 + tp1) + g_b * sq1
    gp2 = g_a * (sp2 + tp2) + g_b * sq2
    gq0 = g_c * (sq0 + tq0) + g_b * tp0
    gq1 = g_c * (sq1 + tq1) + g_b * tp1
    gq2 = g_c * (sq2 + tq2) + g_b * tp2
    pp = (p0, p1, p2)
    qq = (q0, q1, q2)
    for r in range(3):
        for s in range(3):
            g_cov[r, s] += g_a * pp[r] * pp[s] + g_b * pp[r] * qq[s] + g_c * qq[r] * qq[s]
    # X = J W: dL/dJ = dL/dX W^T.
    gj00 = gp0 * R_cw[0, 0] + gp1 * R_cw[0, 1] + gp2 * R_cw[0, 2]
    gj01 = gp0 * R_cw[1, 0] + gp1 * R_cw[1, 1] + gp2 * R_cw[1, 2]
    gj02 = gp0 * R_cw[2, 0] + gp1 * R_cw[2, 1] + gp2 * R_cw[2, 2]
    gj11 = gq0 * R_cw[1, 0] + gq1 * R_cw[1, 1] + gq2 * R_cw[1, 2]
    gj12 = gq0 * R_cw[2, 0] + gq1 * R_cw[2, 1] + gq2 * R_cw[2, 2]
    if abs(mu[2]) <= _NEAR_ZERO:
        return 0.0, 0.0, 0.0
    fx, fy, skew = K[0, 0], K[1, 1], K[0, 1]
    m0, m1 = mu[0], mu[1]
    z2, z3 = z * z, z * z * z
    # J's x = m0 / z and y = m1 / z are clamped: a clamped one carries no gradient.
    x, y = m0 / z, m1 / z
    xc, yc = min(max(x, -lim_x), lim_x), min(max(y, -lim_y), lim_y)
    ix = 1.0 if xc == x else 0.0
    iy = 1.0 if yc == y else 0.0
    g0 = -gj02 * fx * ix / z2
    g1 = -gj02 * skew * iy / z2 - gj12 * fy * iy / z2
    g2 = (
        -(gj00 * fx + gj01 * skew + gj11 * fy) / z2
        + gj02 * ((fx * xc + skew * yc) / z2 + (fx * ix * m0 + skew * iy * m1) / z3)
        + gj12 * fy * (yc / z2 + iy * m1 / z3)
    )
    # Centre (fx m0 / z + s m1 / z + cx, fy m1 / z + cy).
    g_cx, g_cy = gr[GRAD_CX], gr[GRAD_CY]
    g0 += g_cx * fx / z
    g1 += (g_cx * skew + g_cy * fy) / z
    g2 -= (g_cx * (fx * m0 + skew * m1) + g_cy * fy * m1) / z2
    return g0, g1, g2 + gr[GRAD_DEPTH]


@njit(parallel=True, cache=True, error_model="numpy")
def sum_pair_rows(order, pair_start, pair_of, pair_grads, rows):
    """Each survivor's compositing gradient: rows[order[m]] = the sum of its per-tile rows
    pair_grads[pair_of[pair_start[m]:pair_start[m + 1]]] (from `composite_backward`), added in
    float64 in that fixed order, so gradients are bit-identical for any number of threads.

    The survivors are taken in their sorted order, so their lists are read sequentially and only
    the per-tile rows are scattered (fetched `_AHEAD` entries early); the sums land in input order
    (order [M] holds each survivor's input index), where `project_backward` reads them with the
    Gaussians' parameters. Rows of culled Gaussians are left as they are.
    """
    n_pairs = pair_of.shape[0]
    for m in prange(order.shape[0]):
        i = order[m]
        for j in range(GRAD_SIZE):
            rows[i, j] = 0.0
        for q in range(pair_start[m], pair_start[m + 1]):
            if q + _AHEAD < n_pairs:
                _prefetch(pair_grads, pair_of[q + _AHEAD])
                _prefetch_last(pair_grads, pair_of[q + _AHEAD])  # a row spans two cache lines
            k = pair_of[q]
            for j in range(GRAD_SIZE):
                rows[i, j] += pair_grads[k, j]


ABS_SIZE = 7  # columns of `surfel_abs_coefficients`: U (2), V (2), T_w[:2], k


@njit(parallel=True, cache=True, error_model="numpy")
def surfel_abs_coefficients(order, means, rotations, scales, R_cw, t_cw, K, lowpass_sigma, geom, out):
    """Per survivor (input indices `order`) the constants of its per-pixel centre gradients, row i of
    out [N, ABS_SIZE] (the compositing dtype): U = (c_x T_w - T_x)[:2], V = (c_y T_w - T_y)[:2] about the
    centre c as stored in geom (so h_u = U + dx T_w and h_v = V + dy T_w at the pixel's offset from it),
    T_w[:2], and k = d c_lp,x / d T_x[2] = d c_lp,y / d T_y[2] of the low-pass centre: e T_w[2] / C22 for
    the box centre, 1 / z for the projected one (the torch backend's `_abs_coefficients`)."""
    for m in prange(order.shape[0]):
        i = order[m]
        mu = _camera_point(means[i], R_cw, t_cw)
        tx0, tx1, tx2, ty0, ty1, ty2, tw0, tw1, tw2 = _surfel_matrix(
            mu, rotations[i], scales[i, 0], scales[i, 1], R_cw, K
        )
        cx, cy = float(geom[i, GEOM_CX]), float(geom[i, GEOM_CY])
        _, _, c22 = _lowpass_center(tx0, tx1, tx2, ty0, ty1, ty2, tw0, tw1, tw2, cx, cy, lowpass_sigma)
        if c22 != 0.0:
            kk = -tw2 / (lowpass_sigma * lowpass_sigma * c22)
        else:
            kk = 1.0 / (mu[2] if abs(mu[2]) > _NEAR_ZERO else 1.0)
        out[i, 0] = cx * tw0 - tx0
        out[i, 1] = cx * tw1 - tx1
        out[i, 2] = cy * tw0 - ty0
        out[i, 3] = cy * tw1 - ty1
        out[i, 4] = tw0
        out[i, 5] = tw1
        out[i, 6] = kk


@njit(parallel=True, cache=True, error_model="numpy")
def sum_pair_abs(order, pair_start, pair_of, abs_pairs, geom, out):
    """Each survivor's absolute centre gradients: out[order[m]] += z times the sum of its entries'
    rows of abs_pairs [pairs, 2] (`composite_backward`), in float64 and a fixed order (`sum_pair_rows`),
    z its centre depth; the rows of culled Gaussians get nothing."""
    for m in prange(order.shape[0]):
        i = order[m]
        x, y = 0.0, 0.0
        for q in range(pair_start[m], pair_start[m + 1]):
            k = pair_of[q]
            x += abs_pairs[k, 0]
            y += abs_pairs[k, 1]
        z = float(geom[i, GEOM_DEPTH])
        out[i, 0] += z * x
        out[i, 1] += z * y


@njit(parallel=True, cache=True, error_model="numpy")
def project_backward(
    surfel,
    geometry,
    shape,
    rank,
    rows,
    means,
    rotations,
    scales,
    opacities,
    sh,
    covariances,
    R_cw,
    t_cw,
    cam_center,
    K,
    width,
    height,
    lowpass_sigma,
    jacobian_clamp,
    dilation,
    geom,
    flip,
    lit,
    g_means,
    g_rotations,
    g_scales,
    g_opacities,
    g_sh,
    g_covariances,
    scratch,
    cov_scratch,
):
    """Chain rule from the survivors' compositing gradients to the Gaussian parameters.

    rank [N] is each Gaussian's position m among the sorted survivors (-1: culled); rows [N, GRAD_SIZE]
    holds each survivor's compositing gradient in input order (`sum_pair_rows`), and geom
    [N, GEOM_SIZE] the projection's coefficients in input order (as `project` wrote them). The loop
    runs in input order, so parameters, gradient rows, coefficients and outputs are all read and
    written sequentially. Outputs, to which this camera's gradients are added (culled Gaussians get
    nothing), so that one set of buffers, zeroed once, sums the cameras of a call in their order:
    g_means [N, 3], g_rotations [N, 3, 3], g_scales [N, 2], g_opacities [N], g_sh [N, 3, B],
    g_covariances [N, 3, 3] (explicit covariances only, else [0, 3, 3]). scratch [threads, >= 64]
    (SH basis and its derivatives) and cov_scratch [threads, 2, 3, 3] are per-thread work space.

    `geometry` False: the means and rotations get no gradient (their buffers are neither read nor
    written; the SH's view direction and the normal feature are not differentiated); `shape` False (with
    `geometry` False) the scales and covariances get none either, so the projection's chain rule is
    skipped and only SH and opacities are written. A fit of colours and opacities costs less.
    """
    n_bases = sh.shape[2]
    explicit = covariances.shape[0] > 0
    lim_x = jacobian_clamp * width / (2.0 * K[0, 0])
    lim_y = jacobian_clamp * height / (2.0 * K[1, 1])
    for i in prange(means.shape[0]):
        m = rank[i]
        if m < 0:
            continue
        tid = get_thread_id()
        gr = rows[i]
        R = rotations[i]
        mu = _camera_point(means[i], R_cw, t_cw)
        gm0, gm1, gm2 = 0.0, 0.0, 0.0
        if not (geometry or shape):
            pass
        elif surfel:
            gm0, gm1, gm2 = _surfel_backward(
                mu,
                R,
                scales[i, 0],
                scales[i, 1],
                R_cw,
                K,
                gr,
                geom[i, GEOM_CX],
                geom[i, GEOM_CY],
                geom[i, GEOM_LP],
                geom[i, GEOM_LP + 1],
                lowpass_sigma,
                geometry,
                g_rotations[i],
                g_scales[i],
            )
        else:
            if explicit:
                gm0, gm1, gm2 = _ewa_backward(mu, covariances[i], R_cw, K, lim_x, lim_y, dilation, gr, g_covariances[i])
            else:
                cov, g_cov = cov_scratch[tid, 0], cov_scratch[tid, 1]
                _thin_covariance(R, scales[i, 0], scales[i, 1], cov)
                g_cov[:] = 0.0
                gm0, gm1, gm2 = _ewa_backward(mu, cov, R_cw, K, lim_x, lim_y, dilation, gr, g_cov)
                # Sigma = R D R^T, D = diag(s0^2, s1^2, thin^2): dL/dR = (G + G^T) R D,
                # dL/ds_j = 2 s_j (R^T G R)_jj.
                var = (scales[i, 0] * scales[i, 0], scales[i, 1] * scales[i, 1], THIN_SCALE * THIN_SCALE)
                if geometry:
                    for r in range(3):
                        for j in range(3):
                            acc = 0.0
                            for k in range(3):
                                acc += (g_cov[r, k] + g_cov[k, r]) * R[k, j]
                            g_rotations[i, r, j] += acc * var[j]
                for j in range(2):
                    acc = 0.0
                    for r in range(3):
                        for k in range(3):
                            acc += R[r, j] * g_cov[r, k] * R[k, j]
                    g_scales[i, j] += 2.0 * scales[i, j] * acc
        g_opacities[i] += gr[GRAD_LOGO] / opacities[i]
        if geometry:
            # mu = R_cw x + t
            for r in range(3):
                g_means[i, r] += R_cw[0, r] * gm0 + R_cw[1, r] * gm1 + R_cw[2, r] * gm2
            # Normal feature = flip * R e3.
            for r in range(3):
                g_rotations[i, r, 2] += flip[i] * gr[GRAD_FEAT + 3 + r]
        # Colour feature = max(sum_k sh_k Y_k(d) + 0.5, 0), d = normalize(x - camera centre).
        dx = dy = dz = norm = 0.0  # degree 0 is the same from every direction
        if n_bases > 1:
            dx, dy, dz, norm = _view_direction(means[i], cam_center)
        Y, GX, GY, GZ = scratch[tid, 0:16], scratch[tid, 16:32], scratch[tid, 32:48], scratch[tid, 48:64]
        _sh_basis(dx, dy, dz, n_bases, Y)
        gd0, gd1, gd2 = 0.0, 0.0, 0.0
        direction = geometry and n_bases > 1
        if direction:
            _sh_basis_grad(dx, dy, dz, n_bases, GX, GY, GZ)
        # the clamp as the forward pass found it (`project`'s lit bits), not the SH summed again
        g_c0 = gr[GRAD_FEAT] if lit[i] & 1 else 0.0
        g_c1 = gr[GRAD_FEAT + 1] if lit[i] & 2 else 0.0
        g_c2 = gr[GRAD_FEAT + 2] if lit[i] & 4 else 0.0
        for k in range(n_bases):
            g_sh[i, 0, k] += g_c0 * Y[k]
            g_sh[i, 1, k] += g_c1 * Y[k]
            g_sh[i, 2, k] += g_c2 * Y[k]
        if direction:
            # the channels' weights of each basis function first: 3 products a basis, not 9
            for k in range(1, n_bases):
                w = g_c0 * sh[i, 0, k] + g_c1 * sh[i, 1, k] + g_c2 * sh[i, 2, k]
                gd0 += w * GX[k]
                gd1 += w * GY[k]
                gd2 += w * GZ[k]
        if direction and norm > 1e-12:
            # d = v / |v|: dL/dv = (dL/dd - d (d . dL/dd)) / |v|
            proj = dx * gd0 + dy * gd1 + dz * gd2
            g_means[i, 0] += (gd0 - dx * proj) / norm
            g_means[i, 1] += (gd1 - dy * proj) / norm
            g_means[i, 2] += (gd2 - dz * proj) / norm


# ---------------------------------------------------------------------------------------------
# Diagnostics
# ---------------------------------------------------------------------------------------------


@njit(parallel=True, cache=True, boundscheck=False, error_model="numpy")
def count_contributing_pairs(surfel, lowpass, geom, box, tile_start, tile_ids, width, height, tile, tiles_x):
    """Number of (pixel, Gaussian) pairs with alpha >= 1/255, ignoring early termination.

    A property of the scene and the view (the benchmark's measure of work), not of a backend.
    """
    n_tiles = tile_start.shape[0] - 1
    ft = geom.dtype.type
    lp = ft(lowpass)
    per_tile = np.zeros(n_tiles, dtype=np.int64)
    for t in prange(n_tiles):
        x0, y0 = (t % tiles_x) * tile, (t // tiles_x) * tile
        x1, y1 = min(x0 + tile, width), min(y0 + tile, height)
        total = 0
        for k in range(tile_start[t], tile_start[t + 1]):
            i = tile_ids[k]
            c0, c1 = max(box[i, 0], x0), min(box[i, 1], x1 - 1)
            r0, r1 = max(box[i, 2], y0), min(box[i, 3], y1 - 1)
            for r in range(r0, r1 + 1):
                for ch in range((c0 - x0) // LANES, (c1 - x0) // LANES + 1):
                    px, py, inside = _pixels(ft, x0, y0, 1, c0, c1, r1, r, ch, False)[4:7]
                    total += count(_alpha(surfel, lp, geom[i], px, py, inside)[3])
        per_tile[t] = total
    return per_tile.sum()


# ---------------------------------------------------------------------------------------------
# Forced-alpha normalization and background
# ---------------------------------------------------------------------------------------------


@njit(parallel=True, cache=True, boundscheck=False, error_model="numpy")
def normalize_forward(color, alpha, depth, normal, threshold, background, out_color, out_depth, out_normal, parts):
    """`render.normalize_by_alpha` and the background in one pass.

    color, normal [C, 3, H, W], alpha, depth [C, 1, H, W] un-normalized; threshold (inf: none) and
    background [3] in their dtype. Where alpha >= threshold colour, depth and normal are divided by
    alpha and the pixel counts as covered, elsewhere they stay and the coverage is alpha; the colour
    gets (1 - coverage) background. The same operations in the same order as the torch code, so the
    same bits; as torch ops they were some ten passes over the image forward and more backward.
    Each row goes LANES pixels at a time (`simd`; a row's last chunk masked). parts > 1 splits the
    image rows into that many runs taken by the threads (a parallel region wakes the other threads,
    which beside another busy process can cost more than a small image's pass: 1 runs it here).
    """
    cams, height, width = color.shape[0], color.shape[2], color.shape[3]
    # Rows of pixels: channel k of camera c, image row r is row (c * channels + k) * height + r.
    views = (
        color.reshape(-1, width),
        alpha.reshape(-1, width),
        depth.reshape(-1, width),
        normal.reshape(-1, width),
        out_color.reshape(-1, width),
        out_depth.reshape(-1, width),
        out_normal.reshape(-1, width),
    )
    rows = cams * height
    if parts <= 1:
        _normalize_forward_rows(*views, threshold, background, height, 0, rows)
    else:
        for j in prange(parts):
            _normalize_forward_rows(*views, threshold, background, height, *_run_bounds(j, parts, rows))


@njit(cache=True, boundscheck=False, error_model="numpy")
def _normalize_forward_rows(
    color, alpha, depth, normal, out_color, out_depth, out_normal, threshold, background, height, first, end
):
    """Rows first..end - 1 of `normalize_forward` (its arrays as rows of pixels)."""
    ft = color.dtype.type
    one = ft(1.0)
    width = color.shape[1]
    for row in range(first, end):
        c, r = row // height, row % height
        for x in range(0, width, LANES):
            n = min(LANES, width - x)
            a = load_first(alpha, row, x, n)
            mask = a >= threshold
            safe = select(mask, a, splat(one))
            rest = one - select(mask, splat(one), a)
            for k in range(3):
                i = (c * 3 + k) * height + r
                store_first(out_color, i, x, load_first(color, i, x, n) / safe + rest * background[k], n)
                store_first(out_normal, i, x, load_first(normal, i, x, n) / safe, n)
            store_first(out_depth, row, x, load_first(depth, row, x, n) / safe, n)


@njit(parallel=True, cache=True, boundscheck=False, error_model="numpy")
def normalize_backward(
    color,
    alpha,
    depth,
    normal,
    threshold,
    background,
    g_out_color,
    g_out_depth,
    g_out_normal,
    g_color,
    g_alpha,
    g_depth,
    g_normal,
    parts,
):
    """Chain rule of `normalize_forward`: dL/d(colour, depth, normal) and the alpha gradient they add.

    g_alpha [C, 1, H, W] holds dL/dalpha from alpha's own use on entry and gets the normalization's
    share added: -sum g_o o / alpha^2 over the divided maps where alpha >= threshold, else
    -g_colour . background. parts as in `normalize_forward`.
    """
    cams, height, width = color.shape[0], color.shape[2], color.shape[3]
    # Rows of pixels as in `normalize_forward`.
    views = (
        color.reshape(-1, width),
        alpha.reshape(-1, width),
        depth.reshape(-1, width),
        normal.reshape(-1, width),
        g_out_color.reshape(-1, width),
        g_out_depth.reshape(-1, width),
        g_out_normal.reshape(-1, width),
        g_color.reshape(-1, width),
        g_alpha.reshape(-1, width),
        g_depth.reshape(-1, width),
        g_normal.reshape(-1, width),
    )
    rows = cams * height
    if parts <= 1:
        _normalize_backward_rows(*views, threshold, background, height, 0, rows)
    else:
        for j in prange(parts):
            _normalize_backward_rows(*views, threshold, background, height, *_run_bounds(j, parts, rows))


@njit(cache=True, boundscheck=False, error_model="numpy")
def _normalize_backward_rows(
    color,
    alpha,
    depth,
    normal,
    g_out_color,
    g_out_depth,
    g_out_normal,
    g_color,
    g_alpha,
    g_depth,
    g_normal,
    threshold,
    background,
    height,
    first,
    end,
):
    """Rows first..end - 1 of `normalize_backward` (its arrays as rows of pixels)."""
    ft = color.dtype.type
    zero, one = ft(0.0), ft(1.0)
    width = color.shape[1]
    for row in range(first, end):
        c, r = row // height, row % height
        for x in range(0, width, LANES):
            n = min(LANES, width - x)
            a = load_first(alpha, row, x, n)
            mask = a >= threshold
            safe = select(mask, a, splat(one))
            divided, behind = splat(zero), splat(zero)
            for k in range(3):
                i = (c * 3 + k) * height + r
                go_c, go_n = load_first(g_out_color, i, x, n), load_first(g_out_normal, i, x, n)
                store_first(g_color, i, x, go_c / safe, n)
                store_first(g_normal, i, x, go_n / safe, n)
                divided = divided + (go_c * load_first(color, i, x, n) + go_n * load_first(normal, i, x, n))
                behind = behind + go_c * background[k]
            go_d = load_first(g_out_depth, row, x, n)
            store_first(g_depth, row, x, go_d / safe, n)
            divided = divided + go_d * load_first(depth, row, x, n)
            g_a = select(mask, -divided / (safe * safe), -behind)
            store_first(g_alpha, row, x, load_first(g_alpha, row, x, n) + g_a, n)
