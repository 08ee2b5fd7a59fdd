"""Depth error metrics (Eigen et al. 2014) where ground-truth depth exists (synthetic, ScanNet).

Per image, over the pixels of a mask: abs rel = mean |d - d*| / d*, sq rel = mean (d - d*)^2 / d*,
RMSE = sqrt(mean (d - d*)^2), log RMSE = sqrt(mean (log d - log d*)^2) and the threshold accuracies
delta_k = fraction of pixels with max(d / d*, d* / d) < 1.25^k, k = 1, 2, 3 (d predicted, d*
ground truth). The release evaluates ScanNet with ground truth in (0.5, 10) m (`SCANNET_DEPTH_RANGE`).
A predicted depth <= 0 inside the mask (a hole in a render) is a failure for every delta and
makes log RMSE +inf: the number is reported as it is, not hidden.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from ..utils.checks import SurfSplatInputError, check_tensor

SCANNET_DEPTH_RANGE = (0.5, 10.0)  # the release's eval_min_depth / eval_max_depth for ScanNet
DELTA_BASE = 1.25  # threshold accuracy: ratio < 1.25^k


@dataclass(frozen=True)
class DepthMetrics:
    """Per-image depth errors, each [B]; images without valid pixels hold NaN."""

    abs_rel: Tensor
    sq_rel: Tensor
    rmse: Tensor
    log_rmse: Tensor
    delta1: Tensor
    delta2: Tensor
    delta3: Tensor
    num_valid: Tensor  # [B] int64, pixels that entered each image's metrics

    def mean(self) -> dict[str, float]:
        """Mean over the images that have valid pixels, plus how many did."""
        keep = self.num_valid > 0
        if not bool(keep.any()):
            raise SurfSplatInputError("depth metrics: no image has a valid ground-truth pixel")
        out = {
            f.name: float(getattr(self, f.name)[keep].double().mean()) for f in fields(self) if f.name != "num_valid"
        }
        out["num_images"] = int(keep.sum())
        return out


def depth_metrics(
    prediction: Tensor,
    target: Tensor,
    mask: Tensor | None = None,
    *,
    min_depth: float = 0.0,
    max_depth: float = math.inf,
) -> DepthMetrics:
    """Depth errors per image.

    prediction, target: [B, H, W] or [B, 1, H, W] z-depth. mask: optional bool of the same shape.
    A pixel counts where the mask holds and min_depth < target < max_depth (the target must be
    finite there); min_depth is at least 0, so target <= 0 (no measurement) never counts.
    """
    if prediction.ndim == 4:
        check_tensor("prediction", prediction, ("B", 1, "H", "W"))
        prediction = prediction[:, 0]
    check_tensor("prediction", prediction, ("B", "H", "W"))
    if target.ndim == 4:
        check_tensor("target", target, (prediction.shape[0], 1, *prediction.shape[1:]), finite=False)
        target = target[:, 0]
    check_tensor("target", target, tuple(prediction.shape), finite=False)
    if not 0.0 <= min_depth < max_depth:
        raise SurfSplatInputError(f"min_depth, max_depth: expected 0 <= min < max, got {min_depth}, {max_depth}")
    valid = torch.isfinite(target) & (target > min_depth) & (target < max_depth)
    if mask is not None:
        if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
            raise SurfSplatInputError(
                f"mask: expected a bool tensor, got {getattr(mask, 'dtype', type(mask).__name__)}"
            )
        if mask.ndim == 4 and mask.shape[1] == 1:
            mask = mask[:, 0]
        if tuple(mask.shape) != tuple(prediction.shape):
            raise SurfSplatInputError(f"mask: expected shape {tuple(prediction.shape)}, got {tuple(mask.shape)}")
        valid = valid & mask

    d = prediction.double()
    gt = torch.where(valid, target.double(), torch.ones_like(d))  # placeholder 1 outside the mask
    w = valid.double()
    count = w.sum(dim=(1, 2))
    denom = count.clamp(min=1.0)  # empty images become NaN below, not a division warning

    def masked_mean(values: Tensor) -> Tensor:
        total = torch.where(valid, values, torch.zeros_like(values)).sum(dim=(1, 2))
        return torch.where(count > 0, total / denom, torch.full_like(total, math.nan))

    err = d - gt
    # max(d/d*, d*/d) with d <= 0 a failure: its ratio is +inf.
    ratio = torch.where(d > 0, torch.maximum(d / gt, gt / d.clamp(min=torch.finfo(d.dtype).tiny)), math.inf)
    log_err = torch.where(d > 0, torch.log(d.clamp(min=torch.finfo(d.dtype).tiny)) - torch.log(gt), math.inf)
    return DepthMetrics(
        abs_rel=masked_mean(err.abs() / gt),
        sq_rel=masked_mean(err.square() / gt),
        rmse=masked_mean(err.square()).sqrt(),
        log_rmse=masked_mean(log_err.square()).sqrt(),
        delta1=masked_mean((ratio < DELTA_BASE).double()),
        delta2=masked_mean((ratio < DELTA_BASE**2).double()),
        delta3=masked_mean((ratio < DELTA_BASE**3).double()),
        num_valid=count.long(),
    )
