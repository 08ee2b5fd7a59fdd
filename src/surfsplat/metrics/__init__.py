"""Evaluation metrics: PSNR, SSIM (scikit-image's published call), LPIPS-VGG, depth errors, HRRC."""

from .depth import SCANNET_DEPTH_RANGE, DepthMetrics, depth_metrics
from .hrrc import (
    HrrcConfig,
    HrrcEvaluator,
    HrrcReport,
    evaluate_hrrc,
    format_hrrc_table,
    render_at_scales,
    upsample_ground_truth,
)
from .image import psnr, ssim
from .lpips import (
    Lpips,
    LpipsUnavailable,
    LpipsWeightPaths,
    find_lpips_weights,
    load_lpips,
    try_load_lpips,
)

__all__ = [
    "SCANNET_DEPTH_RANGE",
    "DepthMetrics",
    "HrrcConfig",
    "HrrcEvaluator",
    "HrrcReport",
    "Lpips",
    "LpipsUnavailable",
    "LpipsWeightPaths",
    "depth_metrics",
    "evaluate_hrrc",
    "find_lpips_weights",
    "format_hrrc_table",
    "load_lpips",
    "psnr",
    "render_at_scales",
    "ssim",
    "try_load_lpips",
    "upsample_ground_truth",
]
