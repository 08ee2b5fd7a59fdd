"""DepthSplat-style dual-branch encoder of SurfSplat (paper Appendix A)."""

from .encoder import EncoderConfig, EncoderOutput, SurfSplatEncoder
from .vit import VIT_CONFIGS, ViTConfig

__all__ = ["EncoderConfig", "EncoderOutput", "SurfSplatEncoder", "VIT_CONFIGS", "ViTConfig"]
