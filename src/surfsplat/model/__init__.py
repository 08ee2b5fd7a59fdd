"""The SurfSplat network: encoder, Gaussian adapter, presets and checkpoint loading."""

from .adapter import AdapterConfig, AdapterOutput, GaussianAdapter
from .checkpoint import (
    export_release_state_dict,
    load_checkpoint,
    load_depth_anything_v2,
    load_release_weights,
    read_state_dict,
    save_checkpoint,
)
from .encoder import EncoderConfig, SurfSplatEncoder, ViTConfig
from .surfsplat import PRESETS, SurfSplat, SurfSplatConfig, SurfSplatPrediction

__all__ = [
    "AdapterConfig",
    "AdapterOutput",
    "EncoderConfig",
    "GaussianAdapter",
    "PRESETS",
    "SurfSplat",
    "SurfSplatConfig",
    "SurfSplatEncoder",
    "SurfSplatPrediction",
    "ViTConfig",
    "export_release_state_dict",
    "load_checkpoint",
    "load_depth_anything_v2",
    "load_release_weights",
    "read_state_dict",
    "save_checkpoint",
]
