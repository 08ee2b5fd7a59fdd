"""Renderer inputs and outputs shared by every backend."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, get_args

from torch import Tensor

RenderMode = Literal["surfel", "ewa"]
Backend = Literal["auto", "torch", "cpu", "gsplat"]
BACKENDS: tuple[str, ...] = get_args(Backend)

# Compositing constants shared with 3DGS/2DGS/gsplat so every backend computes the same function.
ALPHA_MIN = 1.0 / 255.0  # a Gaussian contributes to a pixel only if its alpha reaches this
LOG_ALPHA_MIN = math.log(ALPHA_MIN)
ALPHA_MAX = 0.99  # alpha is clamped here so transmittance never reaches exactly zero
TRANSMITTANCE_MIN = 1e-4  # a pixel stops accepting Gaussians once transmittance would drop below this
LOWPASS_RHO_SCALE = 2.0  # 2DGS screen-space filter: rho2d = 2 |p - c|^2 (a 1/sqrt(2) px radius)
EWA_DILATION = 0.3  # px^2 added to projected 2D covariances (3DGS)


@dataclass
class RenderOutput:
    """Rendered maps for C cameras.

    color:  [C, 3, H, W] (after forced-alpha normalization and background)
    alpha:  [C, 1, H, W] accumulated opacity (never normalized)
    depth:  [C, 1, H, W] camera-z depth: the ray-splat intersection (surfel) or the centre depth (ewa),
            blended by the compositing weights and normalized like colour
    normal: [C, 3, H, W] world-frame normals facing the camera, blended and normalized like colour
    """

    color: Tensor
    alpha: Tensor
    depth: Tensor
    normal: Tensor
