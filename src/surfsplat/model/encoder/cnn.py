"""Multi-view branch, step 1: a small ResNet turning each image into stride-4 features.

UniMatch's / DepthSplat's CNN (paper Appendix A, "lightweight ResNet-style backbone"): a 7x7
stride-2 stem, three stages of two residual blocks (the second stage keeps stride 2, the third
halves again), instance norm without affine parameters, and a 1x1 projection to the matching width.
All three stage outputs are returned because the DPT heads consume them as skip features.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn


def _instance_norm(x: Tensor) -> Tensor:
    # nn.InstanceNorm2d defaults: no affine parameters, no running statistics, eps 1e-5
    return F.instance_norm(x, eps=1e-5)


class ResidualBlock(nn.Module):
    def __init__(self, in_planes: int, planes: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_planes, planes, 3, stride=stride, padding=1, bias=False)
        self.conv2 = nn.Conv2d(planes, planes, 3, padding=1, bias=False)
        # index 0 of a Sequential so that the release's `downsample.0` names map one to one
        self.downsample = (
            nn.Sequential(nn.Conv2d(in_planes, planes, 1, stride=stride))
            if stride != 1 or in_planes != planes
            else None
        )

    def forward(self, x: Tensor) -> Tensor:
        y = F.relu(_instance_norm(self.conv1(x)))
        y = F.relu(_instance_norm(self.conv2(y)))
        if self.downsample is not None:
            x = _instance_norm(self.downsample(x))
        return F.relu(x + y)


class CNNEncoder(nn.Module):
    """[N, 3, H, W] -> features at 1/2, 1/2 and 1/4 resolution (highest resolution first)."""

    def __init__(self, dims: tuple[int, int, int] = (64, 96, 128), out_dim: int = 128) -> None:
        super().__init__()
        self.dims = dims
        self.conv1 = nn.Conv2d(3, dims[0], 7, stride=2, padding=3, bias=False)  # 1/2
        self.layer1 = self._stage(dims[0], dims[0], stride=1)  # 1/2
        self.layer2 = self._stage(dims[0], dims[1], stride=1)  # 1/2: lowest resolution is 1/4
        self.layer3 = self._stage(dims[1], dims[2], stride=2)  # 1/4
        self.conv2 = nn.Conv2d(dims[2], out_dim, 1)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    @staticmethod
    def _stage(in_planes: int, planes: int, stride: int) -> nn.Sequential:
        return nn.Sequential(ResidualBlock(in_planes, planes, stride), ResidualBlock(planes, planes, 1))

    def forward(self, x: Tensor) -> list[Tensor]:
        x = F.relu(_instance_norm(self.conv1(x)))
        half = self.layer1(x)
        half_wide = self.layer2(half)
        quarter = self.conv2(self.layer3(half_wide))
        return [half, half_wide, quarter]
