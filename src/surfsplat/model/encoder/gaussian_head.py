"""Attribute prediction (paper Appendix A): per-pixel raw Gaussian parameters at full resolution.

Two small conv stacks, as in the release: a regressor on (image, depth, match confidence,
upsampled features), then a head on (regressor output, image, features, match confidence) whose
channels the Gaussian adapter turns into opacity, sub-pixel offset, scale multipliers and SH
(channel layout: 0 opacity logit, 1-2 offsets, 3-4 scale multipliers, 5.. SH).
"""

from __future__ import annotations

from torch import Tensor, nn

from ...utils import precision
from .conv import ReplicateConv2d


class GaussianHead(nn.Module):
    def __init__(self, feature_channels: int, hidden: int, out_channels: int) -> None:
        super().__init__()
        # regressor input: image (3) + depth (1) + match confidence (1) + features
        self.regressor = nn.Sequential(
            nn.Conv2d(3 + 1 + 1 + feature_channels, hidden, 3, padding=1),
            nn.GELU(),
            nn.Conv2d(hidden, hidden, 3, padding=1),
        )
        # head input: regressor output + image (3) + features + match confidence (1)
        self.head = nn.Sequential(
            ReplicateConv2d(hidden + 3 + feature_channels + 1, out_channels, 3, padding=1),
            nn.GELU(),
            ReplicateConv2d(out_channels, out_channels, 3, padding=1),
        )
        # Start from the image colours (SH) and constant scale multipliers; opacity and offsets stay
        # random. (The release zeroes rows [3:6] and [10:], a DepthSplat channel layout left over.)
        nn.init.zeros_(self.head[-1].weight[3:])
        nn.init.zeros_(self.head[-1].bias[3:])

    def forward(self, images: Tensor, depth: Tensor, confidence: Tensor, features: Tensor) -> Tensor:
        """images [N, 3, H, W] in [0, 1]; depth, confidence [N, 1, H, W]; features [N, F, H, W]
        -> raw [N, out_channels, H, W]."""
        hidden = self.regressor(precision.cat((images, depth, confidence, features), dim=1))
        return self.head(precision.cat((hidden, images, features, confidence), dim=1))
