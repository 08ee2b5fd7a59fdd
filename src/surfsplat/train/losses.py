"""Training losses: MSE + lambda LPIPS (paper Sec. 3.5, Eq. 12) and the depth-cascade weighting.

L = MSE(I_render, I_gt) + lambda LPIPS(I_render, I_gt), lambda = 0.05 (pixelSplat, MVSplat,
DepthSplat, SurfSplat). As in the release both terms are means over the batch (Eq. 12 writes a
sum over the M batch items: a constant factor, which AdamW's gradient normalisation all but
cancels), and LPIPS takes images in [0, 1] (the lpips package's `normalize=True`).

Base and large models predict depth in a cascade (num_scales = 2) and the release renders the
Gaussians of every intermediate depth too: with n intermediate renders ordered coarse to fine,
intermediate i (0-based) is weighted 0.9^(n - i) and the final render 1 = 0.9^0.

Where the training data has exact geometry (procedural rooms, chunks that store depth) two optional
terms supervise it; both are off by default, so the paper's loss is unchanged (real datasets have no
dense depth):
- depth: mean relative error |d - d*| / d* of the predicted context depth, i.e. the AbsRel metric;
- normal: mean 1 - n . n* between the normals of the predicted and the true depth map, both taken
  from Sobel tangents of the unprojected depth exactly as the surface continuity prior takes them
  (Eq. 2-3), so a correct depth map gives zero and the term shapes what the surfels' rotations see.
Pixels without truth (depth 0) are left out; for normals, every pixel of the 3x3 stencil must have it.

Closed surfaces (beyond the paper; off by default). Supervising renders at the input's resolution only
lets a surfel of a third of a pixel look as good as a whole one (the 2DGS screen-space low-pass widens
it to about a pixel there, and forced alpha blending divides away the alpha it lacks), so nothing stops
the network from shrinking its surfels until a closer view sees gaps. Where native truth exists at s
times the resolution (procedural rooms, `data.highres_factor`), two terms see the close-up:
- highres: MSE of the render at s times the resolution against that truth (a window of it);
- closure: mean max(0, alpha_x1 - alpha_xs) over the window, the x1 render's alpha (no gradient)
  sampled at the window's pixels: a continuous surface keeps its alpha at any resolution.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor, nn

from ..metrics.lpips import Lpips, LpipsUnavailable, load_lpips
from ..model.adapter import sobel_tangents, unproject_depth
from ..utils.checks import SurfSplatInputError, check_tensor


@dataclass(frozen=True)
class LossConfig:
    """Image loss of the paper; the LPIPS term needs LPIPS-VGG v0.1 weights on disk."""

    mse_weight: float = 1.0  # weight of the per-pixel squared error
    lpips_weight: float = 0.05  # lambda of Eq. 12; 0 trains with MSE only and needs no weights
    lpips_vgg_path: str | None = None  # torchvision's vgg16-397923af.pth; None = torch hub cache
    lpips_lin_path: str | None = None  # the lpips package's v0.1 vgg.pth; None = installed packages
    intermediate_weight: float = 0.9  # base of the cascade weights 0.9^(n - i) (release default)
    depth_weight: float = 0.0  # context depth against true depth (relative L1); needs data with depth
    normal_weight: float = 0.0  # normals of the context depth against the true ones (1 - cos)
    highres_weight: float = 0.0  # MSE at data.highres_factor times the resolution against native truth
    closure_weight: float = 0.0  # alpha lost between the x1 render and the high-resolution one


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
        names = ("mse_weight", "lpips_weight", "intermediate_weight", "depth_weight", "normal_weight")
        for name in (*names, "highres_weight", "closure_weight"):
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


@dataclass
class GeometryTerms:
    """The weighted sum of the geometry terms and each term (scalars, None when its weight is 0)."""

    total: Tensor
    depth: Tensor | None
    normal: Tensor | None


def supervises_geometry(config: LossConfig) -> bool:
    """Whether the loss needs true depth in the training batches."""
    return config.depth_weight > 0 or config.normal_weight > 0


def depth_normals(depths: Tensor, K: Tensor) -> Tensor:
    """[..., H, W, 3] unit normals (t1 x t2, Sobel tangents of the unprojected depth, Eq. 2-3).

    Not reoriented: the predicted and the true map are compared with the same formula, so the sign
    convention cancels and the loss stays smooth where a surface turns edge-on.
    """
    t1, t2 = sobel_tangents(unproject_depth(depths, K))
    return torch.nn.functional.normalize(torch.linalg.cross(t1, t2, dim=-1), dim=-1, eps=1e-12)


def geometry_loss(config: LossConfig, depths: Tensor, true_depths: Tensor, K: Tensor) -> GeometryTerms:
    """Depth and normal supervision of the predicted context depth (see the module docstring).

    depths: [B, V, H, W] predicted camera-z depth; true_depths: [B, V, 1, H, W] (0 = unknown);
    K: [B, V, 3, 3] intrinsics of the H x W maps.
    """
    b, v, h, w = depths.shape
    check_tensor("true_depths", true_depths, (b, v, 1, h, w), finite=False)
    check_tensor("K", K, (b, v, 3, 3), finite=False)
    truth = true_depths[:, :, 0].to(depths.dtype)
    K = K.to(depths.dtype)
    known = truth > 0
    if not bool(known.any()):
        raise SurfSplatInputError("geometry loss: the batch has no pixel with a true depth")
    total = depths.new_zeros(())
    depth_term = normal_term = None
    if config.depth_weight > 0:
        relative = (depths - truth).abs() / truth.clamp_min(1e-6)
        depth_term = relative[known].mean()
        total = total + config.depth_weight * depth_term
    if config.normal_weight > 0:
        stencil = -torch.nn.functional.max_pool2d(-known.float().flatten(0, 1)[:, None], 3, 1, 1)
        inside = stencil.reshape(b, v, h, w) > 0.5
        safe = torch.where(known, truth, truth.new_ones(()))
        cos = (depth_normals(depths, K) * depth_normals(safe, K)).sum(-1)
        normal_term = (1 - cos)[inside].mean() if bool(inside.any()) else depths.new_zeros(())
        total = total + config.normal_weight * normal_term
    return GeometryTerms(total=total, depth=depth_term, normal=normal_term)


@dataclass
class HighresTerms:
    """The weighted sum of the close-up terms and each term (scalars, None when its weight is 0)."""

    total: Tensor
    highres: Tensor | None
    closure: Tensor | None


def supervises_highres(config: LossConfig) -> bool:
    """Whether the loss renders the targets at the high-resolution truth's scale."""
    return config.highres_weight > 0 or config.closure_weight > 0


def alpha_at_window(alpha: Tensor, K: Tensor, K_hr: Tensor, size: tuple[int, int]) -> Tensor:
    """The x1 alpha [B, V, 1, H, W] sampled (bilinear, edges clamped) at the pixel centres of the
    high-resolution windows with intrinsics K_hr [B, V, 3, 3] and (height, width) `size`.

    Both K describe one camera: a window pixel centre (x + 0.5, y + 0.5) sees the ray of x1 image
    point K K_hr^-1 (x + 0.5, y + 0.5, 1), an affine map for pinhole intrinsics.
    """
    b, v, _, h, w = alpha.shape
    hh, ww = size
    to_x1 = (K @ torch.linalg.inv(K_hr)).flatten(0, 1)  # [B*V, 3, 3]
    ys = torch.arange(hh, device=alpha.device, dtype=alpha.dtype) + 0.5
    xs = torch.arange(ww, device=alpha.device, dtype=alpha.dtype) + 0.5
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    pix = torch.stack((gx, gy, torch.ones_like(gx)), -1).reshape(-1, 3)  # [hh*ww, 3]
    uv = torch.einsum("nij,pj->npi", to_x1, pix)[..., :2]  # x1 pixel coordinates, centres at +0.5
    grid = torch.stack((2 * uv[..., 0] / w - 1, 2 * uv[..., 1] / h - 1), -1).reshape(b * v, hh, ww, 2)
    sampled = torch.nn.functional.grid_sample(
        alpha.flatten(0, 1), grid, mode="bilinear", padding_mode="border", align_corners=False
    )
    return sampled.reshape(b, v, 1, hh, ww)


def highres_loss(
    config: LossConfig, color_hr: Tensor, alpha_hr: Tensor, truth_hr: Tensor, alpha_x1_window: Tensor
) -> HighresTerms:
    """The close-up terms (module docstring). color_hr, truth_hr: [B, V, 3, h, w]; alpha_hr and
    alpha_x1_window: [B, V, 1, h, w] (the latter is treated as a constant)."""
    check_tensor("truth_hr", truth_hr, tuple(color_hr.shape), finite=False)
    total = color_hr.new_zeros(())
    highres = closure = None
    if config.highres_weight > 0:
        highres = (color_hr - truth_hr).square().mean()
        total = total + config.highres_weight * highres
    if config.closure_weight > 0:
        closure = (alpha_x1_window.detach() - alpha_hr).clamp_min(0).mean()
        total = total + config.closure_weight * closure
    return HighresTerms(total=total, highres=highres, closure=closure)


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
