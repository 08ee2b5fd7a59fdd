"""The 2D U-Net that regresses depth-candidate features (paper Appendix A, "U-Net and Depth Prediction").

A latent-diffusion style U-Net without time embedding, as DepthSplat builds it: pre-norm residual
blocks (GroupNorm, SiLU, 3x3 conv), strided-conv downsampling, nearest + conv upsampling, and
multi-head self-attention at the coarse levels whose tokens span *all views of a scene* (views are
folded into the token axis), which is a cheap extra exchange of information between views.

Module names follow the LDM layout (`input_blocks`, `middle_block`, `output_blocks`, `in_layers`,
`out_layers`, `skip_connection`, `op`, `qkv`, `proj_out`) so released weights map one to one.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import Tensor, nn


def group_norm(channels: int) -> nn.GroupNorm:
    """8 groups (4 when the width is not a multiple of 8), as the release's U-Net uses."""
    return nn.GroupNorm(8 if channels % 8 == 0 else 4, channels)


class ResBlock(nn.Module):
    def __init__(self, channels: int, out_channels: int) -> None:
        super().__init__()
        self.in_layers = nn.Sequential(group_norm(channels), nn.SiLU(), nn.Conv2d(channels, out_channels, 3, padding=1))
        # index 2 held a p=0 dropout in the release; Identity keeps `out_layers.3` as the conv
        self.out_layers = nn.Sequential(
            group_norm(out_channels), nn.SiLU(), nn.Identity(), nn.Conv2d(out_channels, out_channels, 3, padding=1)
        )
        self.skip_connection = nn.Identity() if out_channels == channels else nn.Conv2d(channels, out_channels, 1)
        nn.init.zeros_(self.out_layers[-1].weight)  # residual branch starts as identity
        nn.init.zeros_(self.out_layers[-1].bias)

    def forward(self, x: Tensor) -> Tensor:
        return self.skip_connection(x) + self.out_layers(self.in_layers(x))


class CrossViewAttentionBlock(nn.Module):
    """Self-attention over the tokens of all V views of a scene; input [(B V), C, H, W]."""

    def __init__(self, channels: int, head_channels: int) -> None:
        super().__init__()
        if channels % head_channels:
            raise ValueError(f"U-Net attention width {channels} is not a multiple of the head width {head_channels}")
        self.num_heads = channels // head_channels
        self.norm = group_norm(channels)
        self.qkv = nn.Conv1d(channels, 3 * channels, 1)
        self.proj_out = nn.Conv1d(channels, channels, 1)
        nn.init.zeros_(self.proj_out.weight)
        nn.init.zeros_(self.proj_out.bias)

    def forward(self, x: Tensor, num_views: int) -> Tensor:
        bv, c, h, w = x.shape
        tokens = x.reshape(bv, c, h * w)
        qkv = rearrange(self.qkv(self.norm(tokens)), "(b v) n t -> b n (v t)", v=num_views)
        # the release's "legacy" head split: heads first, then (q, k, v) inside each head
        q, k, v = rearrange(qkv, "b (heads three ch) t -> three b heads t ch", heads=self.num_heads, three=3)
        out = F.scaled_dot_product_attention(q, k, v)  # [B, heads, V*T, ch]
        out = rearrange(out, "b heads (v t) ch -> (b v) (heads ch) t", v=num_views)
        return (tokens + self.proj_out(out)).reshape(bv, c, h, w)


class Downsample(nn.Module):
    def __init__(self, channels: int) -> None:
        super().__init__()
        self.op = nn.Conv2d(channels, channels, 3, stride=2, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        return self.op(x)


class Upsample(nn.Module):
    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv(F.interpolate(x, scale_factor=2, mode="nearest"))


class UNet(nn.Module):
    """[(B V), C, H, W] -> same shape; H and W must be divisible by 2^(len(channel_mult) - 1)."""

    def __init__(
        self,
        channels: int,
        channel_mult: tuple[int, ...] = (1, 1, 1),
        attention_levels: tuple[int, ...] = (4,),
        head_channels: int = 32,
        num_res_blocks: int = 1,
    ) -> None:
        super().__init__()
        self.depth = len(channel_mult) - 1

        def level_layers(ch_in: int, ch_out: int, downsample_rate: int) -> list[nn.Module]:
            layers: list[nn.Module] = [ResBlock(ch_in, ch_out)]
            if downsample_rate in attention_levels:
                layers.append(CrossViewAttentionBlock(ch_out, head_channels))
            return layers

        self.input_blocks = nn.ModuleList([nn.Sequential(nn.Conv2d(channels, channels, 3, padding=1))])
        skip_channels = [channels]
        ch, rate = channels, 1
        for level, mult in enumerate(channel_mult):
            for _ in range(num_res_blocks):
                self.input_blocks.append(nn.Sequential(*level_layers(ch, mult * channels, rate)))
                ch = mult * channels
                skip_channels.append(ch)
            if level != len(channel_mult) - 1:
                self.input_blocks.append(nn.Sequential(Downsample(ch)))
                skip_channels.append(ch)
                rate *= 2
        # index 1 was a no-op placeholder in the release; Identity keeps `middle_block.2` as named
        self.middle_block = nn.Sequential(ResBlock(ch, ch), nn.Identity(), ResBlock(ch, ch))
        self.output_blocks = nn.ModuleList()
        for level, mult in reversed(list(enumerate(channel_mult))):
            for i in range(num_res_blocks + 1):
                layers = level_layers(ch + skip_channels.pop(), channels * mult, rate)
                ch = channels * mult
                if level and i == num_res_blocks:
                    layers.append(Upsample(ch))
                    rate //= 2
                self.output_blocks.append(nn.Sequential(*layers))
        self.out = nn.Sequential(group_norm(ch), nn.SiLU(), nn.Conv2d(ch, channels, 3, padding=1))
        nn.init.zeros_(self.out[-1].weight)
        nn.init.zeros_(self.out[-1].bias)

    @staticmethod
    def _run(block: nn.Sequential, h: Tensor, num_views: int) -> Tensor:
        for layer in block:
            h = layer(h, num_views) if isinstance(layer, CrossViewAttentionBlock) else layer(h)
        return h

    def forward(self, x: Tensor, num_views: int) -> Tensor:
        factor = 2**self.depth
        if x.shape[-2] % factor or x.shape[-1] % factor:
            raise ValueError(f"U-Net input {tuple(x.shape[-2:])} is not divisible by {factor}")
        skips = []
        h = x
        for block in self.input_blocks:
            h = self._run(block, h, num_views)
            skips.append(h)
        h = self.middle_block(h)
        for block in self.output_blocks:
            h = self._run(block, torch.cat((h, skips.pop()), dim=1), num_views)
        return self.out(h)
