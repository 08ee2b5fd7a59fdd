"""Training: losses, typed configs and presets, the loop, checkpoints, data-parallel plumbing.

    from surfsplat.train import fit, train_preset
    result = fit(train_preset("tiny", out_dir="runs/tiny"))    # ~200 CPU steps on synthetic rooms
    result.validation[result.step]["x1/psnr"]

`surfsplat train` is the command-line face of `fit`; `torchrun --nproc_per_node N -m surfsplat
train ...` runs the same loop data-parallel.
"""

from .checkpoint import CorruptCheckpoint, TrainingState, latest_checkpoint, list_checkpoints, verify_checkpoint
from .config import (
    TRAIN_PRESETS,
    DataConfig,
    ModelConfig,
    OptimConfig,
    TrainConfig,
    config_from_dict,
    override,
    train_preset,
)
from .loop import TrainResult, build_model, build_optimizer, fit, read_checkpoint_config
from .losses import ImageLoss, LossConfig, LossTerms, cascade_loss, cascade_weights
from .schedule import learning_rate

__all__ = [
    "TRAIN_PRESETS",
    "CorruptCheckpoint",
    "DataConfig",
    "ImageLoss",
    "LossConfig",
    "LossTerms",
    "ModelConfig",
    "OptimConfig",
    "TrainConfig",
    "TrainResult",
    "TrainingState",
    "build_model",
    "build_optimizer",
    "cascade_loss",
    "cascade_weights",
    "config_from_dict",
    "fit",
    "latest_checkpoint",
    "learning_rate",
    "list_checkpoints",
    "override",
    "read_checkpoint_config",
    "train_preset",
    "verify_checkpoint",
]
