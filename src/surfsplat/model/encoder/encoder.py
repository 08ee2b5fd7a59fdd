"""DepthSplat's dual-branch encoder as SurfSplat uses it (paper Sec. 3.2 and Appendix A).

    images ─┬─ ViT (DINOv2 / Depth Anything V2) ── 4 taps ──────────────┬── DPT (depth) ── inverse depth
            └─ CNN (stride 4) ── multi-view transformer ── cost volume ─┘     (full resolution)
                    ...all of the above ── DPT (features) ── Gaussian head ── raw per-pixel parameters

Depth is regressed as a softmax over inverse-depth candidates from a U-Net on the concatenated
(cost volume, CNN, multi-view, monocular) features, refined by an optional second, finer cascade
scale (base / large), and brought to full resolution by bilinear upsampling plus a DPT residual.
The module computes exactly the release's function, so released weights load through
`surfsplat.model.checkpoint` and reproduce its outputs.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import Tensor, nn

from ...utils import precision
from ...utils.checks import SurfSplatInputError
from .chunking import items_per_block
from .cnn import CNNEncoder
from .conv import ReplicateConv2d
from .cost_volume import (
    gathered_cost_volume,
    linear_inverse_depth_candidates,
    local_inverse_depth_candidates,
    plane_sweep_cost_volume,
    prefers_gathered_cost_volume,
)
from .dpt import DPTHead, DPTLayout, FeaturePyramid
from .gaussian_head import GaussianHead
from .mv_transformer import MultiViewTransformer, select_neighbours
from .unet import UNet
from .vit import VisionTransformer, ViTConfig, vit_patch_grid

# ImageNet statistics: both the ViT and the CNN were pretrained on images normalised with them.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

# The encoder's parts, each of which can run in float32 under bf16 autocast (`float32_parts`).
PARTS = ("vit", "cnn", "transformer", "depth_regressor", "depth_upsampler", "feature_upsampler", "gaussian_head")
# Those that do by default, measured on the golden case (benchmarks/precision.py): a bf16 CNN
# perturbs the features the cost volume correlates (relative L2 2e-2) and a bf16 depth regressor its
# logits; with everything else in bf16 depths move by 1.7e-2 in relative L2, with these two in
# float32 by 3.1e-3 (adding the transformer: 2.0e-4). The ViT, the multi-view transformer, the DPT
# heads and the Gaussian head run in bf16.
DEFAULT_FLOAT32_PARTS = ("cnn", "depth_regressor")

# Stride of the cost volume and of the multi-view features (the release's lowest_feature_resolution).
MATCHING_STRIDE = 4


@dataclass(frozen=True)
class EncoderConfig:
    vit: ViTConfig = field(default_factory=ViTConfig)  # monocular backbone
    cnn_dims: tuple[int, int, int] = (64, 96, 128)  # CNN stage widths (1/2, 1/2, 1/4 resolution)
    feature_channels: int = 128  # width of the matching features (CNN output, transformer)
    transformer_layers: int = 6  # self + cross attention layers
    ffn_expansion: int = 4  # transformer MLP width = 2 * feature_channels * ffn_expansion
    attn_splits: int = 2  # the transformer attends within attn_splits^2 windows
    num_depth_candidates: int = 128  # inverse-depth planes of the (first) cost volume
    num_scales: int = 1  # 1: cost volume at 1/4 (small); 2: cascade 1/4 -> 1/2 (base, large)
    unet_channels: int = 128  # U-Net width at the first scale (halved at the second)
    unet_channel_mult: tuple[int, ...] = (1, 1, 1)  # per U-Net level; the second scale adds a level
    unet_attention_levels: tuple[int, ...] = (4,)  # downsampling rates with cross-view attention
    unet_head_channels: int = 32  # U-Net attention head width
    depth_dpt_features: int = 32  # RefineNet width of the depth DPT head
    feature_dpt_features: int = 64  # RefineNet width of the feature DPT head (= upsampled feature width)
    dpt_out_channels: tuple[int, int, int, int] = (48, 96, 192, 384)  # ViT tap projections at 1/2..1/16
    gaussian_hidden: int = 64  # width of the Gaussian regressor
    max_neighbours: int = 2  # with more than 3 views, match each view with its nearest cameras only

    @property
    def upsample_factor(self) -> int:
        """Resolution ratio between the finest cost volume and the image."""
        return MATCHING_STRIDE // 2 ** (self.num_scales - 1)

    @property
    def size_multiple(self) -> int:
        """Input height and width must be multiples of this: the DPT heads resize ViT features to
        1/8 and upsample them 4x onto the 1/2 CNN features; the transformer splits the 1/4 map into
        attn_splits windows; every U-Net level halves its scale's map (16 for all presets)."""
        unet_levels = len(self.unet_channel_mult) - 1
        unet = [MATCHING_STRIDE // 2**i * 2 ** (unet_levels + i) for i in range(self.num_scales)]
        return math.lcm(8, MATCHING_STRIDE * self.attn_splits, *unet)


@dataclass
class EncoderOutput:
    depths: Tensor  # [B, V, H, W] camera z-depth
    raw: Tensor  # [B, V, C, H, W] Gaussian head output (adapter input)
    intermediates: dict[str, Tensor] | None = None  # golden-fixture names, [B*V, ...] tensors


class DepthScale(nn.Module):
    """One cascade scale: U-Net regressor (+ 1x1 shortcut) and the depth-candidate head."""

    def __init__(self, in_channels: int, channels: int, candidates: int, unet: UNet) -> None:
        super().__init__()
        self.regressor = nn.Sequential(
            nn.Conv2d(in_channels, channels, 3, padding=1),
            nn.GroupNorm(8, channels),
            nn.GELU(),
            unet,
            nn.Conv2d(channels, channels, 3, padding=1),
        )
        self.residual = nn.Conv2d(in_channels, channels, 1)
        self.depth_head = nn.Sequential(
            ReplicateConv2d(channels, 2 * channels, 3, padding=1),
            nn.GELU(),
            ReplicateConv2d(2 * channels, candidates, 3, padding=1),
        )

    def forward(self, parts: Sequence[Tensor], num_views: int) -> Tensor:
        """parts: [(B V), C_i, h, w] maps with sum(C_i) = C_in -> depth-candidate logits [(B V), D, h, w]."""
        x = precision.cat(parts, dim=1)
        conv_in, norm, act, unet, conv_out = self.regressor
        hidden = conv_out(unet(act(norm(conv_in(x))), num_views)) + self.residual(x)
        return self.depth_head(hidden)


class SurfSplatEncoder(nn.Module):
    def __init__(self, cfg: EncoderConfig, num_raw_channels: int) -> None:
        super().__init__()
        if cfg.num_scales not in (1, 2):
            raise ValueError(f"EncoderConfig.num_scales must be 1 or 2, got {cfg.num_scales}")
        self.cfg = cfg
        self.num_raw_channels = num_raw_channels
        vit_dim = cfg.vit.embed_dim
        self.vit = VisionTransformer(cfg.vit)
        self.cnn = CNNEncoder(cfg.cnn_dims, cfg.feature_channels)
        self.transformer = MultiViewTransformer(
            cfg.feature_channels, cfg.transformer_layers, cfg.ffn_expansion, cfg.attn_splits
        )
        if cfg.num_scales == 2:
            self.mv_pyramid = FeaturePyramid(cfg.feature_channels)
            self.mono_pyramid = FeaturePyramid(vit_dim)
        # CNN outputs, highest resolution first: layer1 and layer2 at 1/2, the projection at 1/4
        cnn_channels = (cfg.cnn_dims[0], cfg.cnn_dims[1], cfg.feature_channels)
        scales = []
        for i in range(cfg.num_scales):
            candidates = cfg.num_depth_candidates // 4**i
            # concat(cost volume, CNN features, multi-view features, monocular features)
            in_channels = candidates + cnn_channels[2 - i] + cfg.feature_channels // 2**i + vit_dim // 2**i
            channels = cfg.unet_channels // 2**i
            unet = UNet(
                channels,
                channel_mult=tuple(cfg.unet_channel_mult) + (1,) * i,
                attention_levels=tuple(r * 2**i for r in cfg.unet_attention_levels),
                head_channels=cfg.unet_head_channels,
            )
            scales.append(DepthScale(in_channels, channels, candidates, unet))
        self.scales = nn.ModuleList(scales)
        mv_channels = tuple(cfg.feature_channels // 2**i for i in reversed(range(cfg.num_scales)))
        layout = dict(
            vit_channels=vit_dim,
            out_channels=tuple(cfg.dpt_out_channels),
            cnn_channels=cnn_channels,
            mv_channels=mv_channels,
            upsample_factor=cfg.upsample_factor,
        )
        self.depth_upsampler = DPTHead(DPTLayout(features=cfg.depth_dpt_features, **layout), predict_depth=True)
        self.feature_upsampler = DPTHead(DPTLayout(features=cfg.feature_dpt_features, **layout), predict_depth=False)
        self.gaussian_head = GaussianHead(cfg.feature_dpt_features, cfg.gaussian_hidden, num_raw_channels)
        self.float32_parts: frozenset[str] = frozenset(DEFAULT_FLOAT32_PARTS)
        self.register_buffer("image_mean", torch.tensor(IMAGENET_MEAN).view(3, 1, 1), persistent=False)
        self.register_buffer("image_std", torch.tensor(IMAGENET_STD).view(3, 1, 1), persistent=False)

    def keep_float32(self, parts: tuple[str, ...] | list[str] | frozenset[str]) -> None:
        """Run `parts` (names from PARTS) in float32 under bf16 autocast; the rest runs in bf16."""
        unknown = sorted(set(parts) - set(PARTS))
        if unknown:
            raise SurfSplatInputError(f"float32 parts: expected names from {', '.join(PARTS)}, got {unknown}")
        self.float32_parts = frozenset(parts)

    def _run(self, part: str, fn: Callable[..., Any], *args: Any) -> Any:
        """fn(*args), in float32 (autocast off, float tensors and lists of them cast up) where
        autocast is on and `part` is one of `float32_parts`; as it is otherwise."""
        device_type = self.image_mean.device.type
        if part not in self.float32_parts or precision.reduced_precision(device_type) is None:
            return fn(*args)
        with precision.without_autocast(device_type):
            return fn(*[precision.float32(a) for a in args])

    def forward(
        self,
        images: Tensor,  # [B, V, 3, H, W] in [0, 1]
        K: Tensor,  # [B, V, 3, 3] intrinsics in pixels of the H x W images
        c2w: Tensor,  # [B, V, 4, 4] camera-to-world, OpenCV axes
        near: Tensor,  # [B, V]
        far: Tensor,  # [B, V]
        return_intermediates: bool = False,
    ) -> EncoderOutput:
        cfg = self.cfg
        b, v, _, height, width = images.shape
        m = cfg.size_multiple
        if height % m or width % m:
            raise SurfSplatInputError(f"images: height and width must be multiples of {m}, got {height}x{width}")
        if v < 2:
            raise SurfSplatInputError(f"images: the encoder matches views, expected at least 2 views, got {v}")
        inter: dict[str, Tensor] | None = {} if return_intermediates else None
        device_type = images.device.type
        # Under bf16 autocast the parts whose precision decides the depth (cost-volume correlation,
        # the softmax over candidates, regression, upsampling and clamping of inverse depth) run in
        # float32 (`precision.without_autocast` on `.float()` tensors, no-ops in float32 runs).
        amp = precision.reduced_precision(device_type)
        flat = ((images - self.image_mean) / self.image_std).flatten(0, 1)  # [(B V), 3, H, W]
        inv_min = (1.0 / far).reshape(-1)  # the far plane is the smallest inverse depth
        inv_max = (1.0 / near).reshape(-1)

        # ---- multi-view branch: CNN, then windowed self/cross attention between views
        cnn = self._run("cnn", self.cnn, flat)  # [1/2 (dims[0]), 1/2 (dims[1]), 1/4 (feature_channels)]
        neighbours = select_neighbours(c2w[..., :3, 3], cfg.max_neighbours)  # [B, V, M]
        features = rearrange(cnn[-1], "(b v) c h w -> b v c h w", b=b)
        mv = self._run("transformer", self.transformer, features, neighbours).flatten(0, 1)  # [(B V), C, H/4, W/4]
        mv_scales = self.mv_pyramid(mv) if cfg.num_scales == 2 else [mv]  # coarse to fine
        cnn_scales = [cnn[2], cnn[1]][: cfg.num_scales]

        # ---- monocular branch: ViT on the image resized to a multiple of the patch size
        vit_h, vit_w = vit_patch_grid(height, width, cfg.vit.patch_size)
        vit_in = F.interpolate(flat, (vit_h, vit_w), mode="bilinear", align_corners=True)
        grid = (vit_h // cfg.vit.patch_size, vit_w // cfg.vit.patch_size)
        taps = self._run("vit", self.vit, vit_in)
        mono_taps = [
            F.interpolate(
                rearrange(t, "n (h w) c -> n c h w", h=grid[0], w=grid[1]),
                (height // 8, width // 8),
                mode="bilinear",
                align_corners=True,
            )
            for t in taps
        ]
        mono = F.interpolate(mono_taps[-1], scale_factor=2, mode="bilinear", align_corners=True)  # 1/4
        mono_scales = self.mono_pyramid(mono) if cfg.num_scales == 2 else [mono]
        if inter is not None:
            inter["dinov2_input_resized_normalized"] = vit_in
            inter.update({f"dinov2_intermediate_tokens.{i}": t for i, t in enumerate(taps)})
            inter["features_cnn_all_scales.0"] = cnn[2]
            inter.update({f"features_mv.{i}": f for i, f in enumerate(mv_scales)})

        # ---- cost volumes and softmax depth, coarse to fine
        neighbour_index = (neighbours + torch.arange(b, device=neighbours.device).view(b, 1, 1) * v).reshape(b * v, -1)
        c2w_flat = c2w.flatten(0, 1)
        inv_depth = prob = None
        for i, scale in enumerate(self.scales):
            stride = MATCHING_STRIDE // 2**i
            K_scale = K.flatten(0, 1).clone()
            K_scale[:, :2] = K_scale[:, :2] / stride
            feats = mv_scales[i]
            count = cfg.num_depth_candidates // 4**i
            if i == 0:
                candidates = linear_inverse_depth_candidates(inv_min, inv_max, count)  # [(B V), D]
            else:
                coarse = F.interpolate(inv_depth, scale_factor=2, mode="bilinear", align_corners=True).detach()
                interval = (inv_max - inv_min) / (cfg.num_depth_candidates - 1) / 2**i
                candidates = local_inverse_depth_candidates(coarse, inv_min, inv_max, count, interval)
            correlate = plane_sweep_cost_volume  # the float32 path stays the release's computation
            if amp is not None and prefers_gathered_cost_volume(*feats.shape[-2:], count):
                correlate = gathered_cost_volume
            with precision.without_autocast(device_type):
                feats32 = feats.float()
                cost = correlate(
                    feats32, feats32[neighbour_index], K_scale, c2w_flat, c2w_flat[neighbour_index], candidates
                )
            parts = (cost, cnn_scales[i], feats, mono_scales[i])
            logits = self._run("depth_regressor", scale, parts, v)
            with precision.without_autocast(device_type):
                prob = torch.softmax(logits.float(), dim=1)
                weights = candidates if candidates.dim() == 4 else candidates[:, :, None, None]
                inv_depth = (prob * weights).sum(dim=1, keepdim=True)  # [(B V), 1, h, w]
            if inter is not None:
                suffix = "" if i == 0 else f".{i}"
                inter[f"cost_volume{suffix}"] = cost
                inter[f"depth_head_logits{suffix}"] = logits

        # ---- full resolution: bilinear upsampling plus a learned DPT residual (inverse depth)
        mv_fine_first = mv_scales[::-1]
        residual = self._run("depth_upsampler", self.depth_upsampler, mono_taps, cnn, mv_fine_first, inv_depth)
        with precision.without_autocast(device_type):
            residual = residual.float()
            upsampled = F.interpolate(inv_depth, scale_factor=cfg.upsample_factor, mode="bilinear", align_corners=True)
            inv_full = (upsampled + residual).clamp(min=inv_min.view(-1, 1, 1, 1), max=inv_max.view(-1, 1, 1, 1))
            depth = 1.0 / inv_full  # [(B V), 1, H, W]

        # ---- per-pixel Gaussian parameters
        confidence = F.interpolate(prob.max(dim=1, keepdim=True).values, size=(height, width), mode="nearest")
        images_flat = images.flatten(0, 1)
        # the full-resolution tail holds the network's largest tensors (the head's input concat)
        head_in = self.gaussian_head.head[0].in_channels
        step = items_per_block(b * v, head_in * height * width * images.element_size(), images.device)
        raw = torch.cat(
            [
                self._run(
                    "gaussian_head",
                    self.gaussian_head,
                    images_flat[i : i + step],
                    depth[i : i + step],
                    confidence[i : i + step],
                    self._run(
                        "feature_upsampler",
                        self.feature_upsampler,
                        [t[i : i + step] for t in mono_taps],
                        [t[i : i + step] for t in cnn],
                        [t[i : i + step] for t in mv_fine_first],
                    ),
                )
                for i in range(0, b * v, step)
            ]
        )
        raw = raw.float()  # the adapter's input; a no-op in float32 runs
        if inter is not None:
            inter["mv_upsampler_coarse_invdepth"] = inv_depth
            inter["mv_upsampler_residual_invdepth"] = residual
            inter["gaussian_head_out"] = raw
        return EncoderOutput(
            depths=depth.view(b, v, height, width),
            raw=raw.view(b, v, -1, height, width),
            intermediates=inter,
        )
