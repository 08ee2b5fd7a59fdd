"""Multi-view branch, step 2: six layers of windowed self- and cross-attention (paper Appendix A).

UniMatch's multi-view Swin transformer as DepthSplat uses it: the stride-4 feature map of every
view is cut into attn_splits x attn_splits windows (odd layers shift them by half a window, with
the Swin mask); each layer is self-attention within a view, then cross-attention from each view to
the same window of its neighbour views followed by an MLP. Single head, no biases.

Facts reproduced from the release (they change the function, so released weights need them):
- a sine position code, computed for one window and added to every window, precedes the layers;
- cross-attention keys come from the neighbours' features *before* the current layer;
- with several neighbours one softmax runs over all their window tokens together;
- masked scores get -100 (not -inf), and for 3+ views the shifted-window mask is tiled along the
  release's (pixel, view)-interleaved key order, so it is misaligned with the keys it masks.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import Tensor, nn

from .chunking import items_per_block


def sine_position_code(height: int, width: int, channels: int, device, dtype) -> Tensor:
    """[channels, height, width] DETR-style sine code normalised to (0, 2 pi] over the grid."""
    npf = channels // 2
    ones = torch.ones(height, width, device=device, dtype=torch.float32)
    y = ones.cumsum(0)
    x = ones.cumsum(1)
    eps, scale = 1e-6, 2 * math.pi
    y = y / (y[-1:, :] + eps) * scale
    x = x / (x[:, -1:] + eps) * scale
    dim_t = torch.arange(npf, dtype=torch.float32, device=device)
    dim_t = 10000 ** (2 * (dim_t // 2) / npf)

    def code(p: Tensor) -> Tensor:  # even channels sin, odd channels cos of the same frequency
        p = p[..., None] / dim_t
        return torch.stack((p[..., 0::2].sin(), p[..., 1::2].cos()), dim=-1).flatten(-2)

    return torch.cat((code(y), code(x)), dim=-1).permute(2, 0, 1).to(dtype)


def add_window_position(features: Tensor, splits: int) -> Tensor:
    """features [N, C, H, W] + the position code of one window, repeated over all windows."""
    n, c, h, w = features.shape
    pos = sine_position_code(h // splits, w // splits, c, features.device, features.dtype)
    return features + pos.repeat(1, splits, splits)


def window_order(height: int, width: int, splits: int, shift: bool, device) -> Tensor:
    """[H*W] row-major token indices listed window by window (windows and their pixels row-major).

    With `shift` the windows are those of the map cyclically rolled by half a window up and left,
    as Swin (and the release, with torch.roll) does it; gathering tokens in this order once replaces
    the roll and the window partition.
    """
    wh, ww = height // splits, width // splits
    dy, dx = (wh // 2, ww // 2) if shift else (0, 0)
    rows = (torch.arange(height, device=device) + dy) % height
    cols = (torch.arange(width, device=device) + dx) % width
    index = rows[:, None] * width + cols[None, :]  # rolled map: position (i, j) holds token index[i, j]
    return rearrange(index, "(kh wh) (kw ww) -> (kh kw wh ww)", kh=splits, kw=splits)


def shifted_window_mask(height: int, width: int, splits: int, device) -> Tensor:
    """[splits^2, L, L] additive Swin mask (0 inside a region, -100 across regions), L = window tokens."""
    wh, ww = height // splits, width // splits
    sh, sw = wh // 2, ww // 2
    region = torch.zeros(height, width, device=device)
    label = 0
    for rows in (slice(0, -wh), slice(-wh, -sh), slice(-sh, None)):
        for cols in (slice(0, -ww), slice(-ww, -sw), slice(-sw, None)):
            region[rows, cols] = label
            label += 1
    windows = rearrange(region, "(kh wh) (kw ww) -> (kh kw) (wh ww)", kh=splits, kw=splits)
    diff = windows[:, None, :] - windows[:, :, None]
    return torch.where(diff != 0, -100.0, 0.0)  # Python scalars: no tensor uploaded from the host


def release_cross_view_mask(mask: Tensor, num_neighbours: int) -> Tensor:
    """The shifted-window mask for keys laid out neighbour-major ([M * L]), as the release applies it.

    The release orders keys (pixel, neighbour)-interleaved and tiles the [L, L] mask M times along
    them, so key (pixel p, neighbour m) receives column (p * M + m) mod L. With one neighbour this is
    the plain mask.
    """
    if num_neighbours == 1:
        return mask
    tiled = mask.repeat(1, 1, num_neighbours)  # column j of the interleaved order -> mask[..., j % L]
    return rearrange(tiled, "w q (p m) -> w q (m p)", m=num_neighbours)


class AttentionLayer(nn.Module):
    """Single-head windowed attention; with `ffn` it is the cross-attention + MLP half of a block."""

    def __init__(self, dim: int, ffn: bool, ffn_expansion: int = 4) -> None:
        super().__init__()
        self.q_proj = nn.Linear(dim, dim, bias=False)
        self.k_proj = nn.Linear(dim, dim, bias=False)
        self.v_proj = nn.Linear(dim, dim, bias=False)
        self.merge = nn.Linear(dim, dim, bias=False)
        self.norm1 = nn.LayerNorm(dim)
        if ffn:
            hidden = 2 * dim * ffn_expansion
            self.mlp = nn.Sequential(
                nn.Linear(2 * dim, hidden, bias=False), nn.GELU(), nn.Linear(hidden, dim, bias=False)
            )
            self.norm2 = nn.LayerNorm(dim)
        else:
            self.mlp = None

    def project(self, x: Tensor, *names: str) -> tuple[Tensor, ...]:
        """Several of the q/k/v projections of the same tokens in one matrix product."""
        weight = torch.cat([getattr(self, f"{n}_proj").weight for n in names])
        return F.linear(x, weight).chunk(len(names), dim=-1)

    def forward(
        self, source: Tensor, keys: Tensor, values: Tensor, mask: Tensor | None, query: Tensor | None = None
    ) -> Tensor:
        """Tokens in window order. source [N, W, L, C]; keys, values [N, W, S, C] already projected;
        mask [1, W, L, S] or None; query: q_proj(source) when already computed -> [N, W, L, C]."""
        query = self.q_proj(source) if query is None else query
        message = F.scaled_dot_product_attention(query, keys, values, attn_mask=mask)
        message = self.norm1(self.merge(message))
        if self.mlp is not None:
            # the MLP's hidden layer is the transformer's largest tensor
            hidden_bytes = source[0].numel() * self.mlp[0].out_features // source.shape[-1] * source.element_size()
            step = items_per_block(source.shape[0], hidden_bytes, source.device)
            message = torch.cat(
                [
                    self.norm2(self.mlp(torch.cat((s, m), dim=-1)))
                    for s, m in zip(source.split(step), message.split(step))
                ]
            )
        return source + message


class TransformerBlock(nn.Module):
    def __init__(self, dim: int, ffn_expansion: int) -> None:
        super().__init__()
        self.self_attn = AttentionLayer(dim, ffn=False)
        self.cross_attn = AttentionLayer(dim, ffn=True, ffn_expansion=ffn_expansion)


class MultiViewTransformer(nn.Module):
    """features [B, V, C, H, W] -> multi-view aware features of the same shape."""

    def __init__(self, dim: int = 128, num_layers: int = 6, ffn_expansion: int = 4, splits: int = 2) -> None:
        super().__init__()
        self.splits = splits
        self.layers = nn.ModuleList(TransformerBlock(dim, ffn_expansion) for _ in range(num_layers))
        for p in self.parameters():
            if p.dim() > 1:
                nn.init.xavier_uniform_(p)

    def forward(self, features: Tensor, neighbours: Tensor) -> Tensor:
        """features [B, V, C, H, W]; neighbours [B, V, M] indices of each view's partner views."""
        b, v, c, h, w = features.shape
        s = self.splits
        if h % s or w % s:
            raise ValueError(f"feature map {h}x{w} does not split into {s}x{s} windows")
        m = neighbours.shape[-1]
        windows, length = s * s, (h // s) * (w // s)
        x = rearrange(add_window_position(features.flatten(0, 1), s), "(b v) c h w -> b v (h w) c", b=b)
        index = neighbours.reshape(b, v * m)[..., None, None].expand(-1, -1, h * w, c)
        orders = [window_order(h, w, s, shift, features.device) for shift in (False, True)]
        inverse = [torch.argsort(order) for order in orders]
        mask = shifted_window_mask(h, w, s, features.device).to(features.dtype)
        self_mask = mask[None]  # a 4-D mask keeps SDPA on its fused CPU/GPU kernels
        cross_mask = release_cross_view_mask(mask, m)[None]
        for i, layer in enumerate(self.layers):
            shift = s > 1 and i % 2 == 1  # Swin: every other layer shifts the windows by half
            xw = x.index_select(2, orders[shift])  # [B, V, L_all, C] in this layer's window order
            flat = xw.reshape(b * v, windows, length, c)
            # self-attention within each view's windows
            sa = layer.self_attn
            q, k, vv = sa.project(flat, "q", "k", "v")
            x_self = sa(flat, k, vv, self_mask if shift else None, query=q)
            # cross-attention to the same windows of the neighbours, using their features from
            # before this layer; one softmax over all neighbours' tokens
            ca = layer.cross_attn
            k, vv = ca.project(xw, "k", "v")
            keys = torch.gather(k, 1, index)  # [B, V*M, L_all, C]
            values = torch.gather(vv, 1, index)
            keys = rearrange(keys, "b (v m) (w l) c -> (b v) w (m l) c", v=v, w=windows)
            values = rearrange(values, "b (v m) (w l) c -> (b v) w (m l) c", v=v, w=windows)
            xw = ca(x_self, keys, values, cross_mask if shift else None)
            x = xw.reshape(b, v, h * w, c).index_select(2, inverse[shift])
        return rearrange(x, "b v (h w) c -> b v c h w", h=h)


def select_neighbours(centers: Tensor, max_neighbours: int) -> Tensor:
    """[B, V, M] partner views for cross-attention and the cost volume.

    Up to three views every view uses all others (in view order). With more views the release
    keeps the `max_neighbours` nearest camera centres (excluding the view itself).
    centers: [B, V, 3] camera positions.
    """
    b, v, _ = centers.shape
    if v <= 3:
        # Row i holds 0..v-1 without i, made on the device (a table from Python data would be uploaded).
        slots = torch.arange(v - 1, device=centers.device)
        others = slots[None] + (slots[None] >= torch.arange(v, device=centers.device)[:, None])
        return others.expand(b, -1, -1)
    with torch.no_grad():
        distance = torch.cdist(centers, centers)
        order = torch.argsort(distance, dim=-1, stable=True)
    return order[..., 1 : max_neighbours + 1]
