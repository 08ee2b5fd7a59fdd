"""Full-reference image metrics: PSNR and SSIM exactly as the published tables compute them.

Every feed-forward splatting paper of this family (pixelSplat, MVSplat, DepthSplat, SurfSplat)
reports SSIM from one call,
`skimage.metrics.structural_similarity(gt, pred, win_size=11, gaussian_weights=True,
channel_axis=0, data_range=1.0)`, which differs from Wang et al. (2004) in two ways: the
covariances are sample covariances (scaled by N / (N - 1), N = 11 * 11), and the mean is taken
over the map without a 5-pixel border. `ssim` below is that call in batched, differentiable
torch, so it runs on the GPU and inside a loss.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import Tensor

from ..utils.checks import SurfSplatInputError, check_tensor

SSIM_WIN_SIZE = 11  # the published call's win_size: the crop and N of the sample covariance
SSIM_SIGMA = 1.5  # scikit-image's Gaussian width when gaussian_weights=True
SSIM_TRUNCATE = 3.5  # scikit-image's truncation: radius = int(3.5 * 1.5 + 0.5) = 5, 11 taps
SSIM_K1 = 0.01  # stabilisers of Wang et al., C1 = (K1 L)^2, C2 = (K2 L)^2
SSIM_K2 = 0.03


def _check_pair(prediction: Tensor, target: Tensor, finite: bool = True) -> tuple[Tensor, Tensor]:
    check_tensor("prediction", prediction, ("B", "C", "H", "W"), finite=finite)
    check_tensor("target", target, tuple(prediction.shape), finite=finite)
    return prediction, target


def psnr(prediction: Tensor, target: Tensor) -> Tensor:
    """Peak signal-to-noise ratio in dB per image, both images clipped to [0, 1] first.

    prediction, target: [B, C, H, W]. Returns [B]; identical images give +inf, as the release's
    `compute_psnr` does. The reported number is the mean of these values over images.
    """
    prediction, target = _check_pair(prediction, target)
    # Clip like the release: renders may overshoot 1 (SH colours are only clamped at 0).
    diff = prediction.clamp(0.0, 1.0) - target.clamp(0.0, 1.0)
    mse = diff.square().mean(dim=(1, 2, 3))
    return -10.0 * torch.log10(mse)


def gaussian_taps(sigma: float = SSIM_SIGMA, truncate: float = SSIM_TRUNCATE, *, dtype=torch.float64) -> Tensor:
    """scipy.ndimage's normalised 1-D Gaussian: 2r + 1 taps, r = int(truncate * sigma + 0.5)."""
    radius = int(truncate * sigma + 0.5)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    taps = torch.exp(-0.5 * (x / sigma) ** 2)
    return (taps / taps.sum()).to(dtype)


# Sides up to this many pixels are filtered as one product with a banded matrix; longer ones as a
# sum of shifted copies (the product's work grows with the side, the sum's does not).
_BANDED_MAX_SIDE = 640


def _band(n: int, taps: Tensor) -> Tensor:
    """[n - 2r, n] matrix whose row i holds the taps at columns i..i+2r: the valid filter of a length-n axis."""
    k = taps.shape[0]
    band = torch.zeros(n - k + 1, n, dtype=taps.dtype, device=taps.device)
    rows = torch.arange(n - k + 1, device=taps.device)
    for i in range(k):
        band[rows, rows + i] = taps[i]
    return band


def _filter_axis(maps: Tensor, taps: Tensor, dim: int) -> Tensor:
    """The valid 1-D filter of `maps` along `dim` (-2 or -1)."""
    n, k = maps.shape[dim], taps.shape[0]
    if n <= _BANDED_MAX_SIDE:
        band = _band(n, taps)
        return band @ maps if dim == -2 else maps @ band.T
    out = taps[0] * maps.narrow(dim, 0, n - k + 1)
    for i in range(1, k):
        out = out + taps[i] * maps.narrow(dim, i, n - k + 1)
    return out


def _gaussian_filter_valid(maps: Tensor, taps: Tensor) -> Tensor:
    """Separable Gaussian filter of [N, 1, H, W] maps where the window fits: [N, 1, H-2r, W-2r].

    scikit-image filters with padding and then crops r = (win_size - 1) / 2 pixels off the SSIM
    map; with win_size 11 and sigma 1.5 the filter radius is also 5, so no kept pixel ever sees
    the padding and an unpadded ("valid") filter gives the same numbers for less work. On the CPU
    the compiled loops of `_filter_cpu` (where numba imports), else products with banded matrices:
    a one-channel 11-tap conv2d and its backward took 20x longer there, most of a fit step at
    368x496. Other devices keep the convolution.
    """
    if maps.device.type != "cpu":
        vertical = F.conv2d(maps, taps.view(1, 1, -1, 1))
        return F.conv2d(vertical, taps.view(1, 1, 1, -1))
    compiled = _compiled_filter()
    if compiled is not None and maps.dtype in (torch.float32, torch.float64):
        return compiled.apply(maps, taps)
    return _filter_axis(_filter_axis(maps, taps, -2), taps, -1)


@functools.cache
def _compiled_filter():
    """`_filter_cpu.GaussianFilterValid`, or None without numba."""
    try:
        from ._filter_cpu import GaussianFilterValid
    except ImportError:
        return None
    return GaussianFilterValid


def ssim(prediction: Tensor, target: Tensor, *, data_range: float = 1.0, check_finite: bool = True) -> Tensor:
    """Mean SSIM per image, identical to scikit-image's Gaussian-window call (module docstring).

    prediction, target: [B, C, H, W] with H, W >= 11; no clipping (the published call has none).
    Computed in the inputs' dtype (at least float32); pass float64 for bit-level agreement with
    scikit-image on float64 arrays. Returns [B]: per channel the mean of the SSIM map without a
    5-pixel border, then the mean over channels. Differentiable. `check_finite=False` skips the
    check that every value is finite: a fit's loss, called every step on its own renders, saves two
    passes over the images (and on a GPU two waits for the device).
    """
    prediction, target = _check_pair(prediction, target, check_finite)
    height, width = prediction.shape[-2:]
    if min(height, width) < SSIM_WIN_SIZE:
        raise SurfSplatInputError(
            f"prediction: SSIM needs images of at least {SSIM_WIN_SIZE}x{SSIM_WIN_SIZE} pixels, got {height}x{width}"
        )
    if not data_range > 0:
        raise SurfSplatInputError(f"data_range: expected a positive number, got {data_range}")
    dtype = torch.promote_types(prediction.dtype, torch.float32)
    x, y = prediction.to(dtype), target.to(dtype)
    n = SSIM_WIN_SIZE**2
    cov_norm = n / (n - 1)  # scikit-image's use_sample_covariance=True
    c1 = (SSIM_K1 * data_range) ** 2
    c2 = (SSIM_K2 * data_range) ** 2
    fused = _compiled_ssim() if x.device.type == "cpu" else None
    if fused is not None:
        return fused.apply(x, y, gaussian_taps(dtype=dtype), c1, c2, cov_norm)
    return _ssim_tensor_ops(x, y, c1, c2, cov_norm)


@functools.cache
def _compiled_ssim():
    """`_filter_cpu.SsimCpu` (the formula below fused into two compiled passes), or None without numba."""
    try:
        from ._filter_cpu import SsimCpu
    except ImportError:
        return None
    return SsimCpu


def _ssim_tensor_ops(x: Tensor, y: Tensor, c1: float, c2: float, cov_norm: float) -> Tensor:
    """`ssim` as tensor ops (any device; the reference `SsimCpu` is checked against)."""
    batch = x.shape[0]

    # All five local moments in one depthwise pass: E[x], E[y], E[x^2], E[y^2], E[xy].
    moments = torch.stack([x, y, x * x, y * y, x * y], dim=1)  # [B, 5, C, H, W]
    flat = rearrange(moments, "b m c h w -> (b m c) 1 h w")
    taps = gaussian_taps(dtype=x.dtype).to(x.device)
    filtered = rearrange(_gaussian_filter_valid(flat, taps), "(b m c) 1 h w -> m b c h w", b=batch, m=5)
    mu_x, mu_y, mu_xx, mu_yy, mu_xy = filtered.unbind(0)

    var_x = cov_norm * (mu_xx - mu_x * mu_x)
    var_y = cov_norm * (mu_yy - mu_y * mu_y)
    cov_xy = cov_norm * (mu_xy - mu_x * mu_y)
    numerator = (2 * mu_x * mu_y + c1) * (2 * cov_xy + c2)
    denominator = (mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2)
    ssim_map = numerator / denominator  # [B, C, H - 10, W - 10]: scikit-image's cropped map
    return ssim_map.mean(dim=(1, 2, 3))
