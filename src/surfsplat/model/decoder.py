"""Decoder: render a batch of predicted scenes into their target views.

    views = render_views(prediction.gaussians, target_cameras, width, height,
                         mode=decoder_mode(model.cfg.adapter), alpha_threshold=prediction.alpha_threshold)
    views.color  # [B, V, 3, H, W]

The network predicts one set of surfels per scene (`Gaussians` with a batch axis); the renderer
draws one unbatched scene at a time, so the decoder splits the batch, renders each scene from its
own target cameras and stacks the results. Which rasterization applies follows from the adapter:

- "surfel" (the paper): exact ray-splat intersection of 2DGS for the paper-mode surfels;
- "ewa" (the release and 3DGS baselines): the release renders surfels as thin 3D Gaussians with
  3DGS's EWA splatting (its covariances travel as `explicit_covariances`), and 3D-Gaussian ablations
  need EWA anyway.

Forced alpha blending (paper Sec. 3.4, Eq. 11) is part of rendering: the adapter says which
tau_alpha applies (0.1 while training, 0.001 at evaluation, None for "w/o FAB"), and the decoder
passes it through unchanged.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..render import render
from ..render.types import Backend, RenderMode
from ..utils.checks import SurfSplatInputError
from .adapter import AdapterConfig


@dataclass
class DecodedViews:
    """Rendered target views of a batch of scenes."""

    color: Tensor  # [B, V, 3, H, W] after forced-alpha normalization and background
    alpha: Tensor  # [B, V, 1, H, W] accumulated opacity
    depth: Tensor  # [B, V, 1, H, W] camera-z depth
    normal: Tensor  # [B, V, 3, H, W] world-frame normals facing the camera


def decoder_mode(adapter: AdapterConfig, requested: Literal["auto", "surfel", "ewa"] = "auto") -> RenderMode:
    """The rasterization for an adapter: surfel for paper surfels, ewa for the release's adapter and
    for 3D Gaussians. An explicit request wins unless it cannot draw the primitives."""
    if requested not in ("auto", "surfel", "ewa"):
        raise SurfSplatInputError(f"mode: expected 'auto', 'surfel' or 'ewa', got {requested!r}")
    if adapter.primitive == "gaussian3d" and requested == "surfel":
        raise SurfSplatInputError("mode: 3D Gaussians (adapter.primitive='gaussian3d') render with 'ewa', not 'surfel'")
    if requested != "auto":
        return requested
    return "ewa" if adapter.mode == "official" or adapter.primitive == "gaussian3d" else "surfel"


def render_views(
    gaussians: Gaussians,  # batched: means [B, N, 3]
    cameras: Cameras,  # B * V target cameras, batch-major (scene b owns cameras b*V .. b*V + V - 1)
    width: int,
    height: int,
    *,
    mode: RenderMode = "surfel",
    alpha_threshold: float | None,
    background: Tensor | Sequence[float] | None = None,
    backend: Backend = "auto",
) -> DecodedViews:
    """Render every scene of a batch from its own cameras; differentiable like `surfsplat.render`.

    `alpha_threshold` has no default on purpose: it is the adapter's tau_alpha of the current mode
    (`prediction.alpha_threshold`), and rendering with another one changes the image.
    """
    if not isinstance(gaussians, Gaussians):
        raise SurfSplatInputError(f"gaussians: expected surfsplat.Gaussians, got {type(gaussians).__name__}")
    if gaussians.means.ndim != 3:
        raise SurfSplatInputError(
            f"gaussians: expected a batch of scenes with means [B, N, 3], got {tuple(gaussians.means.shape)}"
        )
    if not isinstance(cameras, Cameras):
        raise SurfSplatInputError(f"cameras: expected surfsplat.Cameras, got {type(cameras).__name__}")
    b = gaussians.means.shape[0]
    if b == 0 or len(cameras) % b:
        raise SurfSplatInputError(f"cameras: expected a multiple of the batch size {b} (B * V), got {len(cameras)}")
    v = len(cameras) // b
    outs = [
        render(
            gaussians.select(i),
            cameras[i * v : (i + 1) * v],
            width,
            height,
            mode=mode,
            alpha_threshold=alpha_threshold,
            background=background,
            backend=backend,
        )
        for i in range(b)
    ]
    return DecodedViews(
        color=torch.stack([o.color for o in outs]),
        alpha=torch.stack([o.alpha for o in outs]),
        depth=torch.stack([o.depth for o in outs]),
        normal=torch.stack([o.normal for o in outs]),
    )
