"""Surfels from the coarse depths of a depth cascade, for the release's intermediate supervision.

Base and large models refine depth in two cost-volume scales. While training, the release also
builds surfels from the coarser scale's depth - its softmax inverse depth, bilinearly upsampled
(align_corners=True) by that scale's stride to full resolution, with no learned residual - using the
same Gaussian-head output as the final surfels, renders them, and adds their loss weighted
0.9^(n - i) (`surfsplat.train.losses.cascade_loss`).

The network does not hand out its coarse depths, so they are recomputed here from the encoder's
recorded intermediates (`return_intermediates=True`): the scale-0 depth logits and the Gaussian-head
output. Only the first scale has global candidates (linear in inverse depth between far and near),
which is the only intermediate a two-scale cascade has.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..model.encoder.cost_volume import linear_inverse_depth_candidates
from ..model.encoder.encoder import MATCHING_STRIDE
from ..model.surfsplat import SurfSplat, SurfSplatPrediction
from ..utils.checks import SurfSplatInputError

_LOGITS = "depth_head_logits"  # the first scale's candidate logits [(B V), D, h, w]
_RAW = "gaussian_head_out"  # the Gaussian head's output [(B V), C, H, W]


def num_intermediate_depths(model: SurfSplat) -> int:
    """How many coarse depths the release supervises for this model (num_scales - 1)."""
    return model.cfg.encoder.num_scales - 1


def coarse_inverse_depth(logits: Tensor, near: Tensor, far: Tensor) -> Tensor:
    """The first scale's softmax inverse depth at its own resolution.

    logits: [N, D, h, w] candidate logits; near, far: [N]. Returns [N, 1, h, w]: the expectation of
    D inverse-depth planes spaced linearly from 1/far to 1/near under softmax(logits).
    """
    candidates = linear_inverse_depth_candidates(1.0 / far, 1.0 / near, logits.shape[1])  # [N, D]
    prob = torch.softmax(logits, dim=1)
    return (prob * candidates[:, :, None, None]).sum(dim=1, keepdim=True)


def intermediate_gaussians(
    model: SurfSplat,
    prediction: SurfSplatPrediction,
    images: Tensor,  # [B, V, 3, H, W] the context images the prediction was made from
    cameras: Cameras,  # the B*V context cameras
    near: Tensor,  # [B, V]
    far: Tensor,  # [B, V]
) -> list[Gaussians]:
    """Surfels of every intermediate depth, coarse to fine (empty for a one-scale model)."""
    count = num_intermediate_depths(model)
    if count == 0:
        return []
    inter = prediction.intermediates
    if inter is None or _LOGITS not in inter or _RAW not in inter:
        raise SurfSplatInputError(
            "prediction: intermediate supervision of a depth cascade needs the encoder's intermediates; "
            "call the model with return_intermediates=True"
        )
    if count != 1:
        raise SurfSplatInputError(
            f"model: intermediate supervision is implemented for two-scale cascades, got {count + 1} scales"
        )
    b, v, _, height, width = images.shape
    inv = coarse_inverse_depth(inter[_LOGITS], near.reshape(-1), far.reshape(-1))
    inv = F.interpolate(inv, scale_factor=MATCHING_STRIDE, mode="bilinear", align_corners=True)
    if inv.shape[-2:] != (height, width):
        raise SurfSplatInputError(
            f"prediction: coarse depth upsampled to {tuple(inv.shape[-2:])}, images are {height}x{width}"
        )
    depths = rearrange(1.0 / inv, "(b v) 1 h w -> b v h w", b=b)
    raw = rearrange(inter[_RAW], "(b v) c h w -> b v c h w", b=b)
    K = cameras.K.to(images).reshape(b, v, 3, 3)
    c2w = cameras.c2w.to(images).reshape(b, v, 4, 4)
    return [model.adapter(depths, raw, images, K, c2w).gaussians]
