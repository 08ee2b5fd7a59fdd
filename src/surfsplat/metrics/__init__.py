"""Evaluation metrics: PSNR, SSIM (scikit-image's published call), LPIPS-VGG, depth errors, HRRC,
geometry (normals, point-set accuracy / completeness / Chamfer / F-score), DTU's surface protocol and
closure (does a surface of surfels keep its alpha when rendered at a higher resolution)."""

from .closure import ClosureAccumulator, ClosureMetrics, closure_metrics, format_closure_table
from .depth import SCANNET_DEPTH_RANGE, DepthMetrics, depth_metrics
from .dtu import DtuMetrics, DtuReference, dtu_chamfer, dtu_chamfer_mesh, load_dtu_reference
from .geometry import (
    NormalMetrics,
    SurfaceMetrics,
    ViewGeometry,
    angular_error_deg,
    normal_metrics,
    sample_mesh,
    surface_metrics,
    view_geometry,
)
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
    "ClosureAccumulator",
    "ClosureMetrics",
    "closure_metrics",
    "format_closure_table",
    "SCANNET_DEPTH_RANGE",
    "DepthMetrics",
    "DtuMetrics",
    "DtuReference",
    "HrrcConfig",
    "HrrcEvaluator",
    "HrrcReport",
    "Lpips",
    "LpipsUnavailable",
    "LpipsWeightPaths",
    "NormalMetrics",
    "SurfaceMetrics",
    "ViewGeometry",
    "angular_error_deg",
    "depth_metrics",
    "dtu_chamfer",
    "dtu_chamfer_mesh",
    "evaluate_hrrc",
    "find_lpips_weights",
    "format_hrrc_table",
    "load_dtu_reference",
    "load_lpips",
    "normal_metrics",
    "psnr",
    "render_at_scales",
    "sample_mesh",
    "ssim",
    "surface_metrics",
    "try_load_lpips",
    "upsample_ground_truth",
    "view_geometry",
]
