"""SSIM's separable Gaussian filter on the CPU as compiled loops (numba), forward and backward.

A fit's D-SSIM term filters 15 maps of the image a step, forward and backward. As a one-channel
conv2d that took most of a 368x496 fit step; as banded matrix products it still does some 30x the
multiply-adds of the 11-tap sums. Here each output is its 11 + 11 taps, in loops over contiguous
rows that LLVM vectorizes, and the backward is the filter's transpose. One thread: the call is a few
milliseconds, less than waking a second thread costs beside another busy process.

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
