"""CUDA backend through the gsplat library (optional extra: pip install 'surfsplat[gsplat]').

Colours (SH evaluated per camera) and camera-facing normals are computed here exactly as the
torch backend computes them and passed to gsplat as plain feature channels, so both backends
blend the same per-Gaussian values; gsplat supplies the rasterization (2DGS ray-splat
intersection or EWA splatting) and the accumulated depth ("RGB+D"). Forced-alpha normalization
and the background are applied by the caller, identically for every backend.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from ..gaussians import Gaussians
from ..geometry.cameras import Cameras
from ..geometry.sh import sh_to_color
from .types import EWA_DILATION, RenderMode


def render_gsplat(
    g: Gaussians, cameras: Cameras, width: int, height: int, mode: RenderMode
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Un-normalized colour [C, 3, H, W], alpha [C, 1, H, W], depth [C, 1, H, W], normal [C, 3, H, W]."""
    import gsplat

    w2c = cameras.w2c.to(g.means)
    K = cameras.K.to(g.means)
    centers = cameras.centers.to(g.means)
    normals_world = g.rotations[:, :, 2]
    colors, alphas, depths, normals = [], [], [], []
    # One camera per call: gsplat's 2DGS path converts normals with the first camera's pose only.
    for c in range(len(cameras)):
        dirs = F.normalize(g.means - centers[c], dim=-1)
        rgb = sh_to_color(g.sh, dirs)
        facing = torch.where(((normals_world * dirs).sum(-1, keepdim=True) > 0), -normals_world, normals_world)
        features = torch.cat((rgb, facing), dim=-1)  # [N, 6]
        if mode == "surfel":
            out = gsplat.rasterization_2dgs(
                means=g.means,
                quats=g.quats,
                scales=torch.cat((g.scales, torch.zeros_like(g.scales[:, :1])), -1),
                opacities=g.opacities,
                colors=features,
                viewmats=w2c[c : c + 1],
                Ks=K[c : c + 1],
                width=width,
                height=height,
                render_mode="RGB+D",
                near_plane=0.01,
            )
            rendered, alpha = out[0], out[1]
        else:
            covars = g.covariances
            rendered, alpha, _ = gsplat.rasterization(
                means=g.means,
                quats=g.quats,
                scales=torch.cat((g.scales, torch.full_like(g.scales[:, :1], 1e-10)), -1),
                opacities=g.opacities,
                colors=features,
                viewmats=w2c[c : c + 1],
                Ks=K[c : c + 1],
                width=width,
                height=height,
                render_mode="RGB+D",
                near_plane=0.01,
                eps2d=EWA_DILATION,
                covars=covars,
            )
        rendered = rendered[0].permute(2, 0, 1)  # [7, H, W]
        colors.append(rendered[0:3])
        normals.append(rendered[3:6])
        depths.append(rendered[6:7])
        alphas.append(alpha[0].permute(2, 0, 1))
    return torch.stack(colors), torch.stack(alphas), torch.stack(depths), torch.stack(normals)
