"""The SurfSplat network: posed context images -> world-frame surfels (paper Sec. 3, Fig. 2).

    prediction = SurfSplat.from_preset("small", adapter="paper")(images, cameras, near, far)
    prediction.gaussians  # batched surfsplat.Gaussians, N = V * H * W per scene
    prediction.depths     # [B, V, H, W]

The encoder (`surfsplat.model.encoder`) predicts depth and raw per-pixel parameters; the adapter
(`surfsplat.model.adapter`) applies the surface continuity prior and the opacity bound. Presets are
data: `small`, `base` and `large` are the release's configurations (their state dicts load from
released checkpoints), `tiny` is a 1M-parameter model for fast CPU tests.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import Tensor, nn

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..utils.checks import SurfSplatInputError, check_tensor
from ..utils.configio import dataclass_from_dict
from ..utils.precision import without_autocast
from .adapter import AdapterConfig, AdapterOutput, GaussianAdapter
from .encoder.encoder import EncoderConfig, SurfSplatEncoder
from .encoder.vit import VIT_CONFIGS, ViTConfig


@dataclass(frozen=True)
class SurfSplatConfig:
    encoder: EncoderConfig = field(default_factory=EncoderConfig)  # network up to the raw head output
    adapter: AdapterConfig = field(default_factory=AdapterConfig)  # raw output -> surfels (prior, FAB)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: object, source: str = "config") -> SurfSplatConfig:
        return dataclass_from_dict(cls, data, source)


PRESETS: dict[str, EncoderConfig] = {
    # Our own: every component at toy width, for tests and CPU smoke runs (2x64x64 in well under 1 s).
    "tiny": EncoderConfig(
        vit=ViTConfig(embed_dim=64, depth=4, num_heads=2, pos_grid=16, taps=(0, 1, 2, 3)),
        cnn_dims=(16, 24, 32),
        feature_channels=32,
        transformer_layers=2,
        num_depth_candidates=32,
        unet_channels=32,
        unet_head_channels=16,
        depth_dpt_features=16,
        feature_dpt_features=16,
        dpt_out_channels=(16, 24, 32, 64),
        gaussian_hidden=16,
    ),
    # The release's config/model/encoder/depthsplat.yaml (ViT-S, one cost-volume scale).
    "small": EncoderConfig(),
    # The release's training scripts for base/large: num_scales 2, upsample_factor 2.
    "base": EncoderConfig(
        vit=VIT_CONFIGS["vitb"],
        num_scales=2,
        depth_dpt_features=48,
        feature_dpt_features=96,
        dpt_out_channels=(96, 192, 384, 768),
    ),
    "large": EncoderConfig(
        vit=VIT_CONFIGS["vitl"],
        num_scales=2,
        depth_dpt_features=64,
        feature_dpt_features=128,
        dpt_out_channels=(128, 256, 512, 1024),
    ),
}


@dataclass
class SurfSplatPrediction:
    gaussians: Gaussians  # batched: means [B, N, 3], N = V*H*W in (view, row, column) order
    depths: Tensor  # [B, V, H, W] camera z-depth of every context pixel
    adapter_output: AdapterOutput  # scale multipliers, normals, full scales, raw rotations
    alpha_threshold: float | None  # tau_alpha the renderer should normalise with (None: FAB off)
    intermediates: dict[str, Tensor] | None = None  # encoder internals (golden-fixture names)


class SurfSplat(nn.Module):
    def __init__(self, cfg: SurfSplatConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg if cfg is not None else SurfSplatConfig()
        self.adapter = GaussianAdapter(self.cfg.adapter)
        self.encoder = SurfSplatEncoder(self.cfg.encoder, num_raw_channels=self.adapter.num_raw_channels)

    @classmethod
    def from_preset(
        cls, name: str, adapter: Literal["paper", "official"] = "paper", **adapter_fields: object
    ) -> SurfSplat:
        """A randomly initialised model of preset `name` (tiny, small, base, large).

        `adapter` picks the adapter mode ("official" reproduces the release, for released weights);
        further keyword arguments set other `AdapterConfig` fields (e.g. opacity_max=1.0).
        """
        if name not in PRESETS:
            raise SurfSplatInputError(f"preset: expected one of {sorted(PRESETS)}, got {name!r}")
        try:
            adapter_cfg = AdapterConfig(mode=adapter, **adapter_fields)
        except TypeError as err:
            raise SurfSplatInputError(f"adapter: {err}") from None
        return cls(SurfSplatConfig(encoder=PRESETS[name], adapter=adapter_cfg))

    def forward(
        self,
        images: Tensor,  # [B, V, 3, H, W] in [0, 1]
        cameras: Cameras,  # B*V cameras, batch-major; K in pixels of the H x W images
        near: float | Tensor,  # scalar or [B, V]
        far: float | Tensor,  # scalar or [B, V]
        return_intermediates: bool = False,
        validate: bool = True,
    ) -> SurfSplatPrediction:
        """`validate`: check the values too (finite images in [0, 1], finite positive near < far, finite
        pinhole K and rigid c2w). Each check reads a device value on the host, so a GPU waits for it:
        the training loop, whose batches were checked where they were read, passes False; shapes and
        types are checked either way."""
        check_tensor("images", images, ("B", "V", 3, "H", "W"), finite=validate)
        b, v, _, height, width = images.shape
        if validate:
            lo, hi = float(images.min()), float(images.max())
            if lo < 0 or hi > 1:
                raise SurfSplatInputError(f"images: expected values in [0, 1], got [{lo:.4g}, {hi:.4g}]")
        if not isinstance(cameras, Cameras):
            raise SurfSplatInputError(f"cameras: expected surfsplat.Cameras, got {type(cameras).__name__}")
        if len(cameras) != b * v:
            raise SurfSplatInputError(f"cameras: expected {b * v} cameras (B*V = {b}*{v}), got {len(cameras)}")
        near_t = _depth_bound("near", near, b, v, images, validate)
        far_t = _depth_bound("far", far, b, v, images, validate)
        if validate and bool((near_t >= far_t).any()):
            raise SurfSplatInputError("near/far: expected near < far for every view")
        K = cameras.K.to(images).reshape(b, v, 3, 3)
        c2w = cameras.c2w.to(images).reshape(b, v, 4, 4)
        enc = self.encoder(images, K, c2w, near_t, far_t, return_intermediates=return_intermediates)
        # The adapter's geometry (unprojection, Sobel tangents, rotations) runs in float32 under
        # autocast too: bf16 matrix products there would move surfels by ~0.4% of their depth.
        with without_autocast(images.device.type):
            out = self.adapter(
                enc.depths.float(), enc.raw.float(), images.float(), K.float(), c2w.float(), validate=validate
            )
        return SurfSplatPrediction(
            gaussians=out.gaussians,
            depths=enc.depths,
            adapter_output=out,
            alpha_threshold=self.adapter.alpha_threshold(),
            intermediates=enc.intermediates,
        )


def _depth_bound(name: str, value: float | Tensor, b: int, v: int, like: Tensor, validate: bool = True) -> Tensor:
    """A near/far plane as a positive [B, V] tensor (its values checked with `validate`)."""
    if isinstance(value, Tensor):
        if value.shape != (b, v):
            raise SurfSplatInputError(
                f"{name}: expected a float or a [{b}, {v}] tensor, got shape {tuple(value.shape)}"
            )
        t = value.to(like)
    elif isinstance(value, (int, float)):
        t = torch.full((b, v), float(value), dtype=like.dtype, device=like.device)
    else:
        raise SurfSplatInputError(f"{name}: expected a float or a [B, V] tensor, got {type(value).__name__}")
    if validate and (not bool(torch.isfinite(t).all()) or bool((t <= 0).any())):
        raise SurfSplatInputError(f"{name}: expected finite positive depths")
    return t
