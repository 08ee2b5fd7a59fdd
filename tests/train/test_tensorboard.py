"""A short training run's TensorBoard files, read back with TensorBoard's own event reader: the scalars
equal metrics.jsonl, the validation pictures are what the metrics scored, the text holds the config."""

from __future__ import annotations

import io
import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.util import tensor_util

from surfsplat.metrics.hrrc import upsample_ground_truth
from surfsplat.train import fit, train_preset
from surfsplat.train.config import override
from surfsplat.train.data import build_validation_samples
from surfsplat.train.schedule import learning_rate

SIZE = 32  # validation and training views are SIZE x SIZE
FACTORS = (1, 2, 4)


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> tuple[Path, object]:
    out = tmp_path_factory.mktemp("tb") / "run"
    config = override(
        train_preset("tiny"),
        {
            "out_dir": str(out),
            "steps": 3,
            "log_every": 1,
            "checkpoint_every": 3,
            "val_every": 3,
            "image_every": 3,
            "progress": False,
            "val_factors": list(FACTORS),
            "data.image_shape": [SIZE, SIZE],
            "data.num_target_views": 1,
            "data.synthetic_length": 2,
            "data.val_samples": 1,
            "optim.vit_lr": 4e-4,  # unlike the main rate, so that the two curves cannot be swapped
        },
    )
    fit(config)
    events = EventAccumulator(str(out / "tensorboard"), size_guidance={"scalars": 0, "images": 0, "tensors": 0})
    events.Reload()
    return out, config, events


def test_scalars_equal_the_logged_metrics(run) -> None:
    out, config, events = run
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    expected: dict[str, list[tuple[int, float]]] = {}
    for row in rows:
        for tag, value in row.items():
            if tag != "step":
                expected.setdefault(tag, []).append((row["step"], value))
    tags = set(events.Tags()["scalars"])
    assert tags == set(expected)
    # Training, learning rates, timing and validation at x1/x2/x4 are all there.
    assert {"loss/total", "loss/mse", "train/lr", "train/lr_vit", "train/grad_norm"} <= tags
    assert {"train/seconds_per_step", "train/samples_per_second"} <= tags
    assert {f"val/x{s}/{m}" for s in FACTORS for m in ("psnr", "ssim")} <= tags
    for tag, points in expected.items():
        read = [(e.step, e.value) for e in events.Scalars(tag)]
        assert [s for s, _ in read] == [s for s, _ in points], tag
        # TensorBoard stores float32: equal to the JSON's float64 to float32 precision.
        assert [v for _, v in read] == pytest.approx([v for _, v in points], rel=1e-6, abs=1e-12), tag
    # The learning rates are the schedule's for the step that was taken (logged after it).
    o = config.optim
    for tag, peak in (("train/lr", o.lr), ("train/lr_vit", o.vit_lr)):
        for e in events.Scalars(tag):
            rate = learning_rate(e.step - 1, peak, config.steps, o.warmup_fraction, o.initial_div, o.final_div)
            assert e.value == pytest.approx(rate, rel=1e-6), (tag, e.step)


def _decode(image_event) -> np.ndarray:
    array = iio.imread(io.BytesIO(image_event.encoded_image_string), extension=".png")
    assert array.shape == (image_event.height, image_event.width, 3)
    return array.astype(np.float64) / 255.0


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((a - b) ** 2)))


def test_validation_pictures_are_what_the_metrics_scored(run) -> None:
    out, config, events = run
    assert {f"val/x{s}" for s in FACTORS} | {"train/context_target_render"} <= set(events.Tags()["images"])
    (sample,) = build_validation_samples(config.data, 0, 1, config.seed)
    truth = sample.target.images[0, 0]  # [3, H, W], the held-out view validation scored
    for s in FACTORS:
        (image,) = events.Images(f"val/x{s}")
        n = SIZE * s  # two n x n cells in a 2-pixel white border
        assert (image.step, image.height, image.width) == (3, n + 4, 2 * n + 6)
        picture = _decode(image)
        left, right = picture[2 : 2 + n, 2 : 2 + n], picture[2 : 2 + n, n + 4 : 2 * n + 4]
        assert np.all(picture[:2] == 1) and np.all(picture[:, n + 2 : n + 4] == 1)
        # The left half is the truth the metric compares with: upsampled bicubically at s > 1.
        reference = upsample_ground_truth(truth, s).permute(1, 2, 0).double().numpy()
        assert np.abs(left - reference).max() <= 1.5 / 255
        # The right half is the render that was scored: its PSNR against the left is the logged one
        # (up to 8-bit rounding of the picture).
        (logged,) = events.Scalars(f"val/x{s}/psnr")
        assert _psnr(right, reference) == pytest.approx(logged.value, abs=0.05)
        assert logged.value < 40  # a 3-step model is far from the truth: not a copy of the left half
    # Training picture: context (2 views), target (1) and render rows of 32x32 views.
    (train_image,) = events.Images("train/context_target_render")
    assert (train_image.step, train_image.height, train_image.width) == (3, 3 * SIZE + 8, 2 * SIZE + 6)


def test_config_text_holds_the_run_configuration(run) -> None:
    out, config, events = run
    (event,) = events.Tensors("config/text_summary")
    text = tensor_util.make_ndarray(event.tensor_proto).item().decode()
    assert text.startswith("```json\n") and text.endswith("\n```")
    assert json.loads(text[len("```json\n") : -len("\n```")]) == json.loads(json.dumps(config.to_dict()))
    assert json.loads((out / "config.json").read_text()) == json.loads(json.dumps(config.to_dict()))
    assert event.step == 0
    assert len(list((out / "tensorboard").glob("events.out.tfevents.*"))) == 1
