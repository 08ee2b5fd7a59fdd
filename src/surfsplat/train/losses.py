"""Training losses: MSE + lambda LPIPS (paper Sec. 3.5, Eq. 12) and the depth-cascade weighting.

L = MSE(I_render, I_gt) + lambda LPIPS(I_render, I_gt), lambda = 0.05 (pixelSplat, MVSplat,
DepthSplat, SurfSplat). As in the release both terms are means over the batch (Eq. 12 writes a
sum over the M batch items: a constant factor, which AdamW's gradient normalisation all but
cancels), and LPIPS takes images in [0, 1] (the lpips package's `normalize=True`).

Base and large models predict depth in a cascade (num_scales = 2) and the release renders the
Gaussians of every intermediate depth too: with n intermediate renders ordered coarse to fine,
intermediate i (0-based) is weighted 0.9^(n - i) and the final render 1 = 0.9^0.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor, nn

from ..checks import SurfSplatInputError, check_tensor
from ..metrics.lpips import Lpips, LpipsUnavailable, load_lpips


@dataclass(frozen=True)
class LossConfig:
    """Image loss of the paper; the LPIPS term needs LPIPS-VGG v0.1 weights on disk."""

    mse_weight: float = 1.0  # weight of the per-pixel squared error
    lpips_weight: float = 0.05  # lambda of Eq. 12; 0 trains with MSE only and needs no weights
    lpips_vgg_path: str | None = None  # torchvision's vgg16-397923af.pth; None = torch hub cache
    lpips_lin_path: str | None = None  # the lpips package's v0.1 vgg.pth; None = installed packages
    intermediate_weight: float = 0.9  # base of the cascade weights 0.9^(n - i) (release default)


@dataclass
class LossTerms:
    """The total loss and its parts (scalars), for logging."""

    total: Tensor
    mse: Tensor
    lpips: Tensor | None  # None when lpips_weight is 0


class ImageLoss(nn.Module):
    """MSE + lambda LPIPS between renders and ground truth.

    Construction fails at start-up, not mid-run, when lambda > 0 and the LPIPS weights cannot be
    loaded. `lpips` may pass an already loaded model (tests, or sharing one with evaluation).
    """

    def __init__(self, config: LossConfig = LossConfig(), lpips: Lpips | None = None) -> None:
        super().__init__()
        for name in ("mse_weight", "lpips_weight", "intermediate_weight"):
            value = getattr(config, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise SurfSplatInputError(f"config.{name}: expected a finite number >= 0, got {value!r}")
        self.config = config
        self.lpips: Lpips | None = None
        if lpips is not None and not isinstance(lpips, Lpips):
            raise SurfSplatInputError(f"lpips: expected an Lpips module or None, got {type(lpips).__name__}")
        if config.lpips_weight > 0:
            self.lpips = lpips if lpips is not None else _load_for_training(config)

    def forward(self, prediction: Tensor, target: Tensor) -> LossTerms:
        """prediction, target: [..., 3, H, W] (e.g. [B, V, 3, H, W]) in [0, 1]. Returns scalars."""
        if not isinstance(prediction, Tensor) or prediction.ndim < 4:
            raise SurfSplatInputError(
                f"prediction: expected a [..., 3, H, W] tensor with a batch axis, got {getattr(prediction, 'shape', type(prediction).__name__)}"
            )
        # Shapes only: a finiteness check would synchronise with the GPU every step, and a NaN
        # render shows up in the loss anyway.
        check_tensor("prediction", prediction, (None,) * (prediction.ndim - 3) + (3, None, None), finite=False)
        check_tensor("target", target, tuple(prediction.shape), finite=False)
        mse = (prediction - target).square().mean()
        total = self.config.mse_weight * mse
        lpips = None
        if self.lpips is not None:
            flat_pred = prediction.reshape(-1, *prediction.shape[-3:])
            flat_target = target.reshape(-1, *target.shape[-3:])
            lpips = self.lpips(flat_pred, flat_target).mean()
            total = total + self.config.lpips_weight * lpips
        return LossTerms(total=total, mse=mse, lpips=lpips)


def _load_for_training(config: LossConfig) -> Lpips:
    try:
        return load_lpips(config.lpips_vgg_path, config.lpips_lin_path)
    except LpipsUnavailable as err:
        hub = Path(torch.hub.get_dir()) / "checkpoints"
        raise LpipsUnavailable(
            f"{err.reason}. The training loss MSE + {config.lpips_weight} LPIPS needs LPIPS-VGG v0.1 weights: "
            f"put torchvision's vgg16-397923af.pth in {hub} and install the lpips package (or give both files "
            f"with lpips_vgg_path / lpips_lin_path), or set lpips_weight to 0 to train with MSE only"
        ) from err


def cascade_weights(num_renders: int, base: float = 0.9) -> list[float]:
    """Loss weights of a depth cascade's renders ordered coarse to final: base^(n - i), then 1.

    num_renders counts the final render too, so n = num_renders - 1 intermediates; one render
    (no cascade) gives [1.0]; two give [0.9, 1.0]; three give [0.81, 0.9, 1.0].
    """
    if not isinstance(num_renders, int) or num_renders < 1:
        raise SurfSplatInputError(f"num_renders: expected a positive integer, got {num_renders!r}")
    n = num_renders - 1
    return [base ** (n - i) for i in range(num_renders)]


def cascade_loss(loss: ImageLoss, renders: Sequence[Tensor], target: Tensor) -> tuple[Tensor, list[LossTerms]]:
    """Weighted sum of `loss` over cascade renders (coarse to final) against one target.

    renders: the images rendered from each cascade stage's Gaussians, each shaped like target
    ([..., 3, H, W]), the last one the final prediction. Returns (total, terms per render).
    """
    if len(renders) == 0:
        raise SurfSplatInputError("renders: expected at least the final render")
    weights = cascade_weights(len(renders), loss.config.intermediate_weight)
    terms = [loss(render, target) for render in renders]
    total = torch.stack([w * t.total for w, t in zip(weights, terms)]).sum()
    return total, terms
