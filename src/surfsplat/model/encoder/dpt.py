"""DPT heads that bring features and depth to full resolution (paper Appendix A).

DepthSplat's variant of DPT (Ranftl et al. 2021): four ViT taps are projected and resized to
1/2, 1/4, 1/8 and 1/16 of the image, the CNN and multi-view features (and, for the depth head, the
coarse inverse depth) are concatenated in at 1/2 and 1/4 and mixed by 1x1 "concat projections",
then RefineNet fusion blocks upsample from 1/16 to full resolution. The depth head ends with a
small conv stack predicting an inverse-depth residual; the feature head returns the fused features.

Names follow DPT / Depth Anything (`projects`, `resize_layers`, `scratch.layerN_rn`,
`scratch.refinenetN.resConfUnitN`, `scratch.output_conv`) plus DepthSplat's `concat_projects`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch.nn.functional as F
from torch import Tensor, nn

from ...utils import precision
from .conv import ReplicateConv2d


@dataclass(frozen=True)
class DPTLayout:
    """Widths of everything the head fuses, derived from the encoder configuration."""

    vit_channels: int  # width of the ViT tokens
    out_channels: tuple[int, int, int, int]  # projected widths at 1/2, 1/4, 1/8, 1/16
    features: int  # width of the RefineNet path
    cnn_channels: tuple[int, int, int]  # CNN outputs, highest resolution first (1/2, 1/2, 1/4)
    mv_channels: tuple[int, ...]  # multi-view features, highest resolution first
    upsample_factor: int  # 4: coarse depth at 1/4 (one scale); 2: at 1/2 (two-scale cascade)


class ResidualConvUnit(nn.Module):
    def __init__(self, features: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, padding=1)
        self.conv2 = nn.Conv2d(features, features, 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv2(F.relu(self.conv1(F.relu(x)))) + x


class FeatureFusionBlock(nn.Module):
    def __init__(self, features: int, with_skip: bool = True) -> None:
        super().__init__()
        self.out_conv = nn.Conv2d(features, features, 1)
        if with_skip:
            self.resConfUnit1 = ResidualConvUnit(features)
        self.resConfUnit2 = ResidualConvUnit(features)

    def forward(self, x: Tensor, skip: Tensor | None = None, size: tuple[int, int] | None = None) -> Tensor:
        if skip is not None:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        if size is None:
            x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)
        else:
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=True)
        return self.out_conv(x)


class DPTHead(nn.Module):
    """With `predict_depth` returns [N, 1, H, W] inverse-depth residuals, else [N, features, H, W]."""

    def __init__(self, layout: DPTLayout, predict_depth: bool) -> None:
        super().__init__()
        self.layout = layout
        self.predict_depth = predict_depth
        out, cnn, mv = layout.out_channels, layout.cnn_channels, layout.mv_channels
        depth_channel = 1 if predict_depth else 0
        if layout.upsample_factor == 4:  # one scale: multi-view features and coarse depth at 1/4
            concat_in = (cnn[0] + cnn[1] + out[0], cnn[2] + out[1] + mv[0] + depth_channel, out[2])
        elif layout.upsample_factor == 2:  # two scales: finer multi-view features and depth at 1/2
            concat_in = (cnn[0] + cnn[1] + out[0] + mv[0] + depth_channel, cnn[2] + out[1] + mv[1], out[2])
        else:
            raise ValueError(f"DPT upsample_factor must be 2 or 4, got {layout.upsample_factor}")
        self.concat_projects = nn.ModuleList(nn.Conv2d(c, o, 1) for c, o in zip(concat_in, out[:3]))
        self.projects = nn.ModuleList(nn.Conv2d(layout.vit_channels, o, 1) for o in out)
        self.resize_layers = nn.ModuleList(
            [
                nn.ConvTranspose2d(out[0], out[0], 4, stride=4),  # 1/8 -> 1/2
                nn.ConvTranspose2d(out[1], out[1], 2, stride=2),  # 1/8 -> 1/4
                nn.Identity(),  # 1/8
                nn.Conv2d(out[3], out[3], 3, stride=2, padding=1),  # 1/8 -> 1/16
            ]
        )
        f = layout.features
        self.scratch = nn.Module()
        for i, o in enumerate(out, start=1):
            setattr(self.scratch, f"layer{i}_rn", nn.Conv2d(o, f, 3, padding=1, bias=False))
        self.scratch.refinenet1 = FeatureFusionBlock(f)
        self.scratch.refinenet2 = FeatureFusionBlock(f)
        self.scratch.refinenet3 = FeatureFusionBlock(f)
        self.scratch.refinenet4 = FeatureFusionBlock(f, with_skip=False)  # the coarsest has no skip input
        if predict_depth:
            self.scratch.output_conv = nn.Sequential(
                ReplicateConv2d(f, f // 2, 3, padding=1),
                nn.GELU(),
                ReplicateConv2d(f // 2, 16, 3, padding=1),
                nn.GELU(),
                nn.Conv2d(16, 1, 1),
            )
            nn.init.zeros_(self.scratch.output_conv[-1].weight)  # the residual starts at zero
            nn.init.zeros_(self.scratch.output_conv[-1].bias)

    def forward(
        self,
        vit_features: list[Tensor],
        cnn_features: list[Tensor],
        mv_features: list[Tensor],
        inv_depth: Tensor | None = None,
    ) -> Tensor:
        """vit_features: 4 x [N, Cvit, H/8, W/8]; cnn_features: [1/2, 1/2, 1/4] maps;
        mv_features: multi-view maps, highest resolution first; inv_depth: coarse inverse depth
        (depth head only) at the resolution of mv_features[0]."""
        if self.predict_depth != (inv_depth is not None):
            raise ValueError("the depth DPT head needs the coarse inverse depth, the feature head must not get it")
        layers = [resize(proj(x)) for proj, resize, x in zip(self.projects, self.resize_layers, vit_features)]
        extra = [inv_depth] if inv_depth is not None else []
        cnn = cnn_features
        if self.layout.upsample_factor == 4:
            concat = [
                (cnn[0], cnn[1], layers[0]),
                (cnn[2], layers[1], mv_features[0], *extra),
                (layers[2],),
            ]
        else:
            concat = [
                (cnn[0], cnn[1], mv_features[0], *extra, layers[0]),
                (cnn[2], layers[1], mv_features[1]),
                (layers[2],),
            ]
        for i, parts in enumerate(concat):
            layers[i] = self.concat_projects[i](precision.cat(parts, dim=1) if len(parts) > 1 else parts[0])
        s = self.scratch
        l1, l2, l3, l4 = (
            s.layer1_rn(layers[0]),
            s.layer2_rn(layers[1]),
            s.layer3_rn(layers[2]),
            s.layer4_rn(layers[3]),
        )
        path = s.refinenet4(l4, size=l3.shape[-2:])
        path = s.refinenet3(path, l3, size=l2.shape[-2:])
        path = s.refinenet2(path, l2, size=l1.shape[-2:])
        path = s.refinenet1(path, l1)  # x2: full resolution
        return s.output_conv(path) if self.predict_depth else path


class FeaturePyramid(nn.Module):
    """ViTDet's simple pyramid: [x, 2x-upsampled x at half the width] (two-scale models only)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.stages = nn.ModuleList(
            [
                nn.Sequential(),
                nn.Sequential(
                    nn.ConvTranspose2d(channels, channels // 2, 2, stride=2),
                    nn.GELU(),
                    nn.Conv2d(channels // 2, channels // 2, 3, padding=1),
                ),
            ]
        )

    def forward(self, x: Tensor) -> list[Tensor]:  # lowest resolution first
        return [stage(x) for stage in self.stages]
