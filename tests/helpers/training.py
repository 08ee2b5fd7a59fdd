"""The tiny training preset cut down to seconds, shared by the training, checkpoint, weights and
reliability tests: 32x32 synthetic rooms, one target view, two scenes, no progress bar."""

from __future__ import annotations

import json
from pathlib import Path

from surfsplat.train import TrainConfig, override, train_preset

QUICK = {
    "steps": 2,
    "log_every": 1,
    "checkpoint_every": 2,
    "val_every": 0,
    "image_every": 0,
    "progress": False,
    "data.image_shape": [32, 32],
    "data.num_target_views": 1,
    "data.synthetic_length": 2,
}


def quick_config(out: Path, changes: dict | None = None, **more) -> TrainConfig:
    """`train_preset("tiny")` writing to `out` with QUICK's settings, then `changes` (dotted keys)
    and `more` (top-level fields) over them."""
    return override(train_preset("tiny"), {"out_dir": str(out), **QUICK, **(changes or {}), **more})


def quick_train_argv(out: Path, **sets) -> list[str]:
    """`surfsplat train` of QUICK's tiny preset for three steps with a checkpoint each, `sets` over it."""
    settings = {**QUICK, "steps": 3, "checkpoint_every": 1, **sets}
    argv = ["train", "--preset", "tiny", "--out", str(out), "--no-progress"]
    for key, value in settings.items():
        argv += ["--set", f"{key}={json.dumps(value)}"]
    return argv


def validated_quick_config(out: Path, **changes) -> TrainConfig:
    """The quick config with validation and images at step 2 (x1 and x2)."""
    validation = {"val_every": 2, "image_every": 2, "val_factors": [1, 2], "data.val_samples": 1}
    return quick_config(out, {**validation, **changes})
