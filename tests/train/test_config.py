"""Training configuration: presets carry the paper's values, JSON round trips, clear errors."""

from __future__ import annotations

import argparse
import json

import pytest

from surfsplat.commands import train as command
from surfsplat.train.config import TRAIN_PRESETS, TrainConfig, config_from_dict, override, train_preset
from surfsplat.train.data import build_train_batches
from surfsplat.utils.checks import SurfSplatInputError


def test_release_presets_carry_the_paper_values() -> None:
    # SPEC Sec. 8 / the release: AdamW lr 2e-4, ViT 2e-6, 1% warm-up, clip 0.5, batch 16 (small)
    # and 8 (base, large), 256x256, near 0.5, far 100, MSE + 0.05 LPIPS, flips with p = 1/2.
    for name, batch in (("small", 16), ("base", 8), ("large", 8)):
        c = train_preset(name)
        assert (c.model.preset, c.batch_size) == (name, batch)
        assert (c.optim.lr, c.optim.vit_lr, c.optim.weight_decay) == (2e-4, 2e-6, 0.01)
        assert (c.optim.warmup_fraction, c.optim.grad_clip) == (0.01, 0.5)
        assert c.data.image_shape == (256, 256) and (c.data.near, c.data.far) == (0.5, 100.0)
        assert c.loss.lpips_weight == 0.05 and c.loss.intermediate_weight == 0.9
        assert c.data.flip_probability == 0.5 and c.data.dataset == "chunks"


@pytest.mark.parametrize("name", sorted(TRAIN_PRESETS))
def test_json_round_trip(name: str) -> None:
    config = train_preset(name)
    assert config_from_dict(json.loads(json.dumps(config.to_dict()))) == config


def test_override_by_dotted_path() -> None:
    config = override(train_preset("tiny"), {"optim.lr": 3e-3, "data.image_shape": [96, 96], "steps": 7})
    assert (config.optim.lr, config.data.image_shape, config.steps) == (3e-3, (96, 96), 7)
    assert config.optim.vit_lr == train_preset("tiny").optim.vit_lr


@pytest.mark.parametrize(
    "change, message",
    [
        ({"optim.lr": "fast"}, "config.optim.lr: expected a number"),
        ({"data.image_shape": [60, 64]}, "data.image_shape: expected .H, W. multiples of 16"),
        ({"batch_size": 0}, "batch_size: expected at least 1"),
        ({"data.dataset": "imagenet"}, "config.data.dataset: expected one of"),
        ({"model.adapter.opacity_max": 2.0}, "adapter.opacity_max"),
        ({"optim.warmup": 0.1}, "optim.warmup: unknown configuration field"),
    ],
)
def test_errors_name_the_field(change: dict, message: str) -> None:
    with pytest.raises(SurfSplatInputError, match=message):
        override(train_preset("tiny"), change)


def test_unknown_json_field_is_an_error() -> None:
    data = TrainConfig().to_dict()
    data["data"]["shuffle_everything"] = True
    with pytest.raises(SurfSplatInputError, match=r"config.data: unknown fields \['shuffle_everything'\]"):
        config_from_dict(data)


def test_chunks_need_roots() -> None:
    with pytest.raises(SurfSplatInputError, match="data.roots: dataset 'chunks' needs at least one chunk folder"):
        build_train_batches(train_preset("small").data, 16, 0, 1, seed=0, start_step=0)


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    command.add_arguments(parser)
    return parser.parse_args(argv)


def test_command_line_overrides(tmp_path) -> None:
    args = _parse(
        [
            "--preset",
            "tiny",
            "--out",
            str(tmp_path),
            "--steps",
            "12",
            "--image-shape",
            "32",
            "48",
            "--set",
            "optim.grad_clip=1.5",
            "--set",
            "data.cache_samples=false",
            "--no-progress",
        ]
    )
    config, resume = command.build_config(args)
    assert resume is False
    assert (config.out_dir, config.steps, config.data.image_shape) == (str(tmp_path), 12, (32, 48))
    assert (config.optim.grad_clip, config.data.cache_samples, config.progress) == (1.5, False, False)


def test_command_line_needs_a_start() -> None:
    with pytest.raises(SurfSplatInputError, match="give --preset, --config or --resume"):
        command.build_config(_parse(["--steps", "3"]))
    with pytest.raises(SurfSplatInputError, match="no checkpoint"):
        command.build_config(_parse(["--resume", "--out", "/nonexistent/run"]))
