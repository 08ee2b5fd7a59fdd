"""The SurfSplat network: encoder, Gaussian adapter, presets, checkpoint loading and named weights."""

from .adapter import AdapterConfig, AdapterOutput, GaussianAdapter
from .checkpoint import (
    describe_init,
    export_release_state_dict,
    load_checkpoint,
    load_depth_anything_v2,
    load_release_weights,
    load_unimatch,
    read_state_dict,
    save_checkpoint,
)
from .encoder import EncoderConfig, SurfSplatEncoder, ViTConfig
from .pretrained import load_pretrained
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
    "describe_init",
    "export_release_state_dict",
    "load_checkpoint",
    "load_depth_anything_v2",
    "load_pretrained",
    "load_release_weights",
    "load_unimatch",
    "read_state_dict",
    "save_checkpoint",
]
