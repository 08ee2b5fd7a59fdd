"""Monocular branch: the DINOv2 / Depth Anything V2 Vision Transformer (paper Appendix A).

Parameter names follow DINOv2 (`patch_embed.proj`, `blocks.{i}.attn.qkv`, `ls1.gamma`, ...) so that
Depth Anything V2 weights (`pretrained.*`) and the release's `depth_predictor.pretrained.*` map onto
this module by a prefix. Only what the encoder uses is built (no mask token, no classification head), and
blocks after the last tapped one are not run.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn


@dataclass(frozen=True)
class ViTConfig:
    embed_dim: int = 384  # token width (ViT-S 384, ViT-B 768, ViT-L 1024)
    depth: int = 12  # number of transformer blocks
    num_heads: int = 6  # attention heads (head width 64 for the released backbones)
    mlp_ratio: float = 4.0  # hidden width of each block's MLP relative to embed_dim
    patch_size: int = 14  # DINOv2 patches are 14 x 14 pixels
    pos_grid: int = 37  # side of the learned position grid (DINOv2 trained at 518 = 37 * 14 px)
    taps: tuple[int, ...] = (2, 5, 8, 11)  # blocks whose normed tokens feed the DPT heads
    interpolate_offset: float = 0.1  # DINOv2's position-grid resize kludge (see _position_embedding)


VIT_CONFIGS: dict[str, ViTConfig] = {
    "vits": ViTConfig(embed_dim=384, depth=12, num_heads=6, taps=(2, 5, 8, 11)),
    "vitb": ViTConfig(embed_dim=768, depth=12, num_heads=12, taps=(2, 5, 8, 11)),
    "vitl": ViTConfig(embed_dim=1024, depth=24, num_heads=16, taps=(4, 11, 17, 23)),
}


class PatchEmbed(nn.Module):
    def __init__(self, patch_size: int, embed_dim: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(3, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: Tensor) -> Tensor:  # [N, 3, H, W] -> [N, h*w, C]
        return self.proj(x).flatten(2).transpose(1, 2)


class Attention(nn.Module):
    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, dim * 3)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor) -> Tensor:  # [N, T, C]
        n, t, c = x.shape
        q, k, v = self.qkv(x).reshape(n, t, 3, self.num_heads, c // self.num_heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(q, k, v)  # [N, heads, T, c/heads]
        return self.proj(out.transpose(1, 2).reshape(n, t, c))


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(self.act(self.fc1(x)))


class LayerScale(nn.Module):
    def __init__(self, dim: int, init: float = 1.0) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), init))

    def forward(self, x: Tensor) -> Tensor:
        return x * self.gamma


class Block(nn.Module):
    """Pre-norm transformer block with LayerScale (DINOv2)."""

    def __init__(self, cfg: ViTConfig) -> None:
        super().__init__()
        dim = cfg.embed_dim
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = Attention(dim, cfg.num_heads)
        self.ls1 = LayerScale(dim)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = Mlp(dim, int(dim * cfg.mlp_ratio))
        self.ls2 = LayerScale(dim)

    def forward(self, x: Tensor) -> Tensor:
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


class VisionTransformer(nn.Module):
    """DINOv2 ViT returning the normed patch tokens of the tapped blocks."""

    def __init__(self, cfg: ViTConfig) -> None:
        super().__init__()
        if not cfg.taps or max(cfg.taps) >= cfg.depth or min(cfg.taps) < 0:
            raise ValueError(f"ViTConfig.taps {cfg.taps} must index blocks 0..{cfg.depth - 1}")
        self.cfg = cfg
        dim = cfg.embed_dim
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, cfg.pos_grid**2 + 1, dim))
        self.patch_embed = PatchEmbed(cfg.patch_size, dim)
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.depth))
        self.norm = nn.LayerNorm(dim, eps=1e-6)
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.normal_(self.cls_token, std=1e-6)

    def _position_embedding(self, rows: int, cols: int) -> Tensor:
        """[1, 1 + rows*cols, C] position embedding for a rows x cols patch grid.

        Bicubic resize of the learned grid, as DINOv2 does it: the scale factor carries a +0.1
        offset and is passed to `interpolate` (not the output size), so sampling positions use that
        factor. Reproducing it exactly keeps released weights bit-compatible.
        """
        m = self.cfg.pos_grid
        if rows == m and cols == m:
            return self.pos_embed
        pos = self.pos_embed.float()
        grid = pos[:, 1:].reshape(1, m, m, -1).permute(0, 3, 1, 2)
        off = self.cfg.interpolate_offset
        grid = F.interpolate(grid, scale_factor=((rows + off) / m, (cols + off) / m), mode="bicubic")
        if grid.shape[-2:] != (rows, cols):
            raise RuntimeError(f"position grid resized to {tuple(grid.shape[-2:])}, expected {(rows, cols)}")
        grid = grid.permute(0, 2, 3, 1).reshape(1, rows * cols, -1)
        return torch.cat((pos[:, :1], grid), dim=1).to(self.pos_embed.dtype)

    def forward(self, x: Tensor) -> list[Tensor]:
        """x: [N, 3, H, W] with H, W multiples of the patch size -> per tap [N, h*w, C] tokens."""
        n, _, height, width = x.shape
        p = self.cfg.patch_size
        if height % p or width % p:
            raise ValueError(f"ViT input {height}x{width} is not a multiple of the patch size {p}")
        tokens = torch.cat((self.cls_token.expand(n, -1, -1), self.patch_embed(x)), dim=1)
        tokens = tokens + self._position_embedding(height // p, width // p)
        taps = set(self.cfg.taps)
        outputs = []
        for i in range(max(taps) + 1):  # blocks after the last tap would not change any output
            tokens = self.blocks[i](tokens)
            if i in taps:
                outputs.append(self.norm(tokens)[:, 1:])  # drop the class token
        return outputs


def vit_patch_grid(height: int, width: int, patch_size: int) -> tuple[int, int]:
    """The release resizes images down to the nearest multiple of the patch size."""
    return height // patch_size * patch_size, width // patch_size * patch_size


__all__ = ["VIT_CONFIGS", "ViTConfig", "VisionTransformer", "vit_patch_grid"]
