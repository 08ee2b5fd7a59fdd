"""SSIM on the CPU as compiled loops (numba), forward and backward: its separable Gaussian filter
alone (`GaussianFilterValid`), and the whole of `metrics.ssim` fused (`SsimCpu`).

A fit's D-SSIM term filters 15 maps of the image a step, forward and backward. As a one-channel
conv2d that took most of a 368x496 fit step; as banded matrix products it still does some 30x the
multiply-adds of the 11-tap sums. Here each output is its 11 + 11 taps, in loops over contiguous
rows that LLVM vectorizes, and the backward is the filter's transpose. One thread: the call is a few
milliseconds, less than waking a second thread costs beside another busy process.

Filtered, the SSIM formula was still some thirty whole-image tensor ops forward and as many backward
(stack, squares, products, the map, the mean, and their chain rule): 44 ms of a 368x496 fit step's
L1 + D-SSIM, forward and backward, on one thread. `SsimCpu` does it in one pass each way: the
moments are formed inside the vertical filter pass, the map is summed as it is computed, and the
backward filters only the three moments a prediction enters (five when the target needs a gradient
too). No library offers SSIM with this exact (scikit-image's) definition as a fused CPU kernel.

Importing this module needs numba; `surfsplat.metrics.image` uses it only when numba imports.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit
from torch import Tensor


@njit(cache=True, boundscheck=False, error_model="numpy")
def _filter_valid(maps, taps, tmp, out):
    """out [M, H-2r, W-2r] = maps [M, H, W] filtered along H then W, valid part only (tmp [H-2r, W])."""
    k = taps.shape[0]
    zero = maps.dtype.type(0.0)
    for m in range(maps.shape[0]):
        rows, cols = out.shape[1], out.shape[2]
        for y in range(rows):
            for x in range(maps.shape[2]):
                tmp[y, x] = zero
            for i in range(k):
                t = taps[i]
                for x in range(maps.shape[2]):
                    tmp[y, x] += t * maps[m, y + i, x]
        for y in range(rows):
            for x in range(cols):
                out[m, y, x] = zero
            for i in range(k):
                t = taps[i]
                for x in range(cols):
                    out[m, y, x] += t * tmp[y, x + i]


@njit(cache=True, boundscheck=False, error_model="numpy")
def _filter_valid_transpose(grad_out, taps, tmp, grad_in):
    """grad_in [M, H, W] = the transpose of `_filter_valid` applied to grad_out [M, H-2r, W-2r]."""
    k = taps.shape[0]
    zero = grad_out.dtype.type(0.0)
    rows, cols = grad_out.shape[1], grad_out.shape[2]
    width = grad_in.shape[2]
    for m in range(grad_out.shape[0]):
        for y in range(rows):
            for x in range(width):
                tmp[y, x] = zero
            for i in range(k):
                t = taps[i]
                for x in range(cols):
                    tmp[y, x + i] += t * grad_out[m, y, x]
        for y in range(grad_in.shape[1]):
            for x in range(width):
                grad_in[m, y, x] = zero
        for y in range(rows):
            for i in range(k):
                t = taps[i]
                for x in range(width):
                    grad_in[m, y + i, x] += t * tmp[y, x]


class GaussianFilterValid(torch.autograd.Function):
    """[N, 1, H, W] maps -> [N, 1, H-2r, W-2r]: the valid separable filter with `taps` (2r + 1)."""

    @staticmethod
    def forward(ctx, maps: Tensor, taps: Tensor) -> Tensor:
        n, _, h, w = maps.shape
        k = taps.shape[0]
        x = maps.detach().reshape(n, h, w).contiguous().numpy()
        t = taps.detach().to(maps.dtype).contiguous().numpy()
        out = np.empty((n, h - k + 1, w - k + 1), dtype=x.dtype)
        _filter_valid(x, t, np.empty((h - k + 1, w), dtype=x.dtype), out)
        ctx.taps, ctx.shape = t, (n, h, w)
        return torch.from_numpy(out).reshape(n, 1, h - k + 1, w - k + 1)

    @staticmethod
    def backward(ctx, grad: Tensor):
        n, h, w = ctx.shape
        k = ctx.taps.shape[0]
        g = grad.reshape(n, h - k + 1, w - k + 1).contiguous().numpy()
        out = np.empty((n, h, w), dtype=g.dtype)
        _filter_valid_transpose(g, ctx.taps, np.empty((h - k + 1, w), dtype=g.dtype), out)
        return torch.from_numpy(out).reshape(n, 1, h, w), None


# ---------------------------------------------------------------------------------------------
# SSIM whole: the five moments filtered, the map, its mean and the gradients, fused
# ---------------------------------------------------------------------------------------------

TAPS = 11  # the fused kernels' filter length (SSIM's window, `metrics.image.SSIM_WIN_SIZE`)
LANES = 16  # running sums of the SSIM map (one AVX-512 register of float32)


@njit(cache=True, boundscheck=False, error_model="numpy")
def _vertical(src, t, out):
    """out [R, W] = sum_j t[j] src[r + j] over the 11 taps, row r of out from rows r..r+10 of src.
    The taps are written out, so each output is one expression and the loop over the columns
    vectorizes without a read-modify-write of out per tap; the sum runs in tap order, as the
    accumulating loops of `_filter_valid` do."""
    t0, t1, t2, t3, t4, t5, t6, t7, t8, t9, t10 = t[0], t[1], t[2], t[3], t[4], t[5], t[6], t[7], t[8], t[9], t[10]
    for r in range(out.shape[0]):
        s0, s1, s2, s3, s4, s5 = src[r], src[r + 1], src[r + 2], src[r + 3], src[r + 4], src[r + 5]
        s6, s7, s8, s9, s10 = src[r + 6], src[r + 7], src[r + 8], src[r + 9], src[r + 10]
        o = out[r]
        for c in range(out.shape[1]):
            o[c] = (
                t0 * s0[c] + t1 * s1[c] + t2 * s2[c] + t3 * s3[c] + t4 * s4[c] + t5 * s5[c]
                + t6 * s6[c] + t7 * s7[c] + t8 * s8[c] + t9 * s9[c] + t10 * s10[c]
            )  # fmt: skip


@njit(cache=True, boundscheck=False, error_model="numpy")
def _horizontal(src, t, out):
    """out [R, W] = sum_j t[j] src[:, c + j] over the 11 taps (`_vertical` along the rows)."""
    t0, t1, t2, t3, t4, t5, t6, t7, t8, t9, t10 = t[0], t[1], t[2], t[3], t[4], t[5], t[6], t[7], t[8], t[9], t[10]
    for r in range(out.shape[0]):
        s, o = src[r], out[r]
        for c in range(out.shape[1]):
            o[c] = (
                t0 * s[c] + t1 * s[c + 1] + t2 * s[c + 2] + t3 * s[c + 3] + t4 * s[c + 4] + t5 * s[c + 5]
                + t6 * s[c + 6] + t7 * s[c + 7] + t8 * s[c + 8] + t9 * s[c + 9] + t10 * s[c + 10]
            )  # fmt: skip


@njit(cache=True, inline="always", boundscheck=False, error_model="numpy")
def _ssim_terms(moments, r, c, c1, c2, cov_norm):
    """At window (r, c) of one plane's moments [5, H-10, W-10]: mx, my and the four factors of
    S = A1 B1 / (A2 B2), A1 = 2 mx my + c1, B1 = 2 cov + c2, A2 = mx^2 + my^2 + c1, B2 = vx + vy + c2
    (the sample covariances: cov_norm times the moments' differences). A pure scalar function,
    inlined, so the loops calling it still vectorize."""
    two = moments.dtype.type(2.0)
    mx, my = moments[0, r, c], moments[1, r, c]
    vx = cov_norm * (moments[2, r, c] - mx * mx)
    vy = cov_norm * (moments[3, r, c] - my * my)
    cxy = cov_norm * (moments[4, r, c] - mx * my)
    return mx, my, two * mx * my + c1, two * cxy + c2, mx * mx + my * my + c1, vx + vy + c2


@njit(cache=True, boundscheck=False, error_model="numpy")
def _ssim_forward(x, y, taps, c1, c2, cov_norm, moments, products, tmp, values, total):
    """Per plane p of x, y [P, H, W]: the five local moments E[x], E[y], E[x^2], E[y^2], E[xy] of
    the valid filter into moments [P, 5, H-10, W-10] (kept for the backward), and the sum of the
    SSIM map into total [P] (float64). Work space: products [3, H, W] (x^2, y^2, xy), tmp [H-10, W],
    values [W-10 rounded up to a multiple of LANES]."""
    ft = x.dtype.type
    zero = ft(0.0)
    rows, cols = moments.shape[2], moments.shape[3]
    lanes = np.empty(LANES, dtype=np.float64)
    for p in range(x.shape[0]):
        xp, yp = x[p], y[p]
        for r in range(x.shape[1]):
            for c in range(x.shape[2]):
                a, b = xp[r, c], yp[r, c]
                products[0, r, c] = a * a
                products[1, r, c] = b * b
                products[2, r, c] = a * b
        for m in range(5):
            _vertical(xp if m == 0 else (yp if m == 1 else products[m - 2]), taps, tmp)
            _horizontal(tmp, taps, moments[p, m])
        # The map a row at a time into values (a loop with no carried sum vectorizes), then summed in
        # LANES running sums, in a fixed order.
        for j in range(LANES):
            lanes[j] = 0.0
        for r in range(rows):
            for c in range(cols):
                mx, my, a1, b1, a2, b2 = _ssim_terms(moments[p], r, c, c1, c2, cov_norm)
                values[c] = (a1 * b1) / (a2 * b2)
            for c in range(cols, values.shape[0]):
                values[c] = zero
            for c0 in range(0, cols, LANES):
                for j in range(LANES):
                    lanes[j] += values[c0 + j]
        total[p] = lanes.sum()


@njit(cache=True, boundscheck=False, error_model="numpy")
def _ssim_backward(x, y, taps, c1, c2, cov_norm, moments, scale, grad_x, grad_y, padded, tall, g_full):
    """Gradients of sum_p scale[p] * (sum of plane p's SSIM map) with respect to x (grad_x [P, H, W])
    and, where grad_y has planes (else [0, H, W]), y.

    Per plane: dL/d(each moment) at each window, written into the middle of padded [5, H-10, W+10]
    (10 zero columns on each side, zeros from the allocation), then the filter's transpose as
    a correlation with the reversed taps: along the rows into the middle rows of tall [H+10, W]
    (10 zero rows above and below), then down the columns into g_full [5, H, W]; last the moments'
    own chain rule, dE[x] + 2 x dE[x^2] + y dE[xy] (and the mirror for y).

    With S = A1 B1 / (A2 B2), A1 = 2 mx my + c1, B1 = 2 k (E[xy] - mx my) + c2, A2 = mx^2 + my^2 + c1,
    B2 = k (E[x^2] - mx^2) + k (E[y^2] - my^2) + c2 (k the sample-covariance factor):
      dS/dmx = 2 my dS/dA1 - 2 k my dS/dB1 + 2 mx dS/dA2 - 2 k mx dS/dB2,
      dS/dE[x^2] = k dS/dB2,  dS/dE[xy] = 2 k dS/dB1,
    with dS/dA1 = B1 / (A2 B2), dS/dB1 = A1 / (A2 B2), dS/dA2 = -S / A2, dS/dB2 = -S / B2."""
    ft = x.dtype.type
    two = ft(2.0)
    rows, cols, height = moments.shape[2], moments.shape[3], x.shape[1]
    pad = TAPS - 1
    reversed_taps = taps[::-1].copy()
    with_y = grad_y.shape[0] > 0
    n_maps = 5 if with_y else 3  # 0: E[x], 1: E[x^2], 2: E[xy], 3: E[y], 4: E[y^2]
    for p in range(x.shape[0]):
        s = ft(scale[p])
        for r in range(rows):
            for c in range(cols):
                mx, my, a1, b1, a2, b2 = _ssim_terms(moments[p], r, c, c1, c2, cov_norm)
                inv = s / (a2 * b2)
                ssim = a1 * b1 / (a2 * b2)
                d_a1, d_b1 = b1 * inv, a1 * inv  # dS/dA1, dS/dB1 (times the scale)
                d_a2, d_b2 = -s * ssim / a2, -s * ssim / b2
                padded[0, r, pad + c] = two * (my * d_a1 - cov_norm * my * d_b1 + mx * d_a2 - cov_norm * mx * d_b2)
                padded[1, r, pad + c] = cov_norm * d_b2
                padded[2, r, pad + c] = two * cov_norm * d_b1
                padded[3, r, pad + c] = two * (mx * d_a1 - cov_norm * mx * d_b1 + my * d_a2 - cov_norm * my * d_b2)
                padded[4, r, pad + c] = cov_norm * d_b2
        for m in range(n_maps):
            _horizontal(padded[m], reversed_taps, tall[pad : pad + rows])
            _vertical(tall, reversed_taps, g_full[m, :height])
        for r in range(height):
            for c in range(x.shape[2]):
                a, b = x[p, r, c], y[p, r, c]
                grad_x[p, r, c] = g_full[0, r, c] + two * a * g_full[1, r, c] + b * g_full[2, r, c]
        if with_y:
            for r in range(height):
                for c in range(x.shape[2]):
                    a, b = x[p, r, c], y[p, r, c]
                    grad_y[p, r, c] = g_full[3, r, c] + two * b * g_full[4, r, c] + a * g_full[2, r, c]


class SsimCpu(torch.autograd.Function):
    """Mean SSIM per image of x, y [B, C, H, W] (float32 or float64) with 11 filter taps, the sample
    covariance factor `cov_norm` and stabilisers c1, c2: `metrics.ssim`'s formula as two compiled
    passes, forward and backward, instead of some thirty whole-image tensor ops each way."""

    @staticmethod
    def forward(ctx, x: Tensor, y: Tensor, taps: Tensor, c1: float, c2: float, cov_norm: float) -> Tensor:
        b, c, h, w = x.shape
        if taps.shape != (TAPS,):
            raise ValueError(f"taps: the fused SSIM kernels take {TAPS}, got {tuple(taps.shape)}")
        rows, cols = h - TAPS + 1, w - TAPS + 1
        xs = x.detach().reshape(b * c, h, w).contiguous().numpy()
        ys = y.detach().reshape(b * c, h, w).contiguous().numpy()
        t = taps.detach().to(x.dtype).contiguous().numpy()
        ft = xs.dtype.type
        moments = np.empty((b * c, 5, rows, cols), dtype=xs.dtype)
        total = np.empty(b * c, dtype=np.float64)
        work = (
            np.empty((3, h, w), xs.dtype),
            np.empty((rows, w), xs.dtype),
            np.empty(-(-cols // LANES) * LANES, xs.dtype),
        )
        _ssim_forward(xs, ys, t, ft(c1), ft(c2), ft(cov_norm), moments, *work, total)
        ctx.arrays = (xs, ys, t, moments)
        ctx.constants = (ft(c1), ft(c2), ft(cov_norm))
        ctx.count = c * rows * cols
        return torch.from_numpy(total.reshape(b, c).sum(axis=1) / ctx.count).to(x.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor):
        xs, ys, t, moments = ctx.arrays
        planes, h, w = xs.shape
        b = grad.shape[0]
        c = planes // b
        rows, cols = h - TAPS + 1, w - TAPS + 1
        scale = np.repeat(grad.detach().to(torch.float64).numpy() / ctx.count, c)
        with_y = ctx.needs_input_grad[1]
        grad_x = np.empty_like(xs)
        grad_y = np.empty_like(ys) if with_y else np.empty((0, h, w), dtype=xs.dtype)
        padded = np.zeros((5, rows, cols + 2 * (TAPS - 1)), xs.dtype)  # the zero margins are the padding
        tall = np.zeros((rows + 2 * (TAPS - 1), w), xs.dtype)
        g_full = np.empty((5, h, w), xs.dtype)
        _ssim_backward(xs, ys, t, *ctx.constants, moments, scale, grad_x, grad_y, padded, tall, g_full)
        shape = (b, c, h, w)
        gx = torch.from_numpy(grad_x).reshape(shape) if ctx.needs_input_grad[0] else None
        gy = torch.from_numpy(grad_y).reshape(shape) if with_y else None
        return gx, gy, None, None, None, None
