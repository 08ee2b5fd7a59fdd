"""Training runs on every dataset layout: synthetic rooms, chunk folders (RealEstate10K-style, with
an evaluation index for validation), and real captures converted to chunks (LLFF, DTU)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from surfsplat.data.convert import convert
from surfsplat.data.synthetic import write_synthetic_chunks
from surfsplat.train import fit, train_preset
from surfsplat.train.config import override

# Short gaps: the test scenes have 8-49 frames, not RealEstate10K's hundreds.
_SAMPLER = {
    "num_context_views": 2,
    "num_target_views": 1,
    "min_distance_between_context_views": 2,
    "max_distance_between_context_views": 6,
    "warm_up_steps": 0,
}


def _chunk_config(out: Path, roots: list[Path], shape: tuple[int, int], **more):
    changes = {
        "out_dir": str(out),
        "steps": 2,
        "log_every": 1,
        "checkpoint_every": 2,
        "val_every": 0,
        "progress": False,
        "data.dataset": "chunks",
        "data.roots": [str(r) for r in roots],
        "data.image_shape": list(shape),
        "data.num_target_views": 1,
        "data.view_sampler": _SAMPLER,
    }
    changes.update(more)
    return override(train_preset("tiny"), changes)


def _check_trained(result, steps: int = 2) -> None:
    assert result.step == steps and result.checkpoint is not None
    assert all(0 < loss < 1 for _, loss in result.losses)


@pytest.mark.slow
def test_chunks_with_evaluation_index_validation(tmp_path: Path) -> None:
    index = write_synthetic_chunks(tmp_path / "train", num_scenes=3, image_shape=(32, 32), num_frames=8, supersample=1)
    held_out = write_synthetic_chunks(
        tmp_path / "test", num_scenes=2, seed=7, image_shape=(32, 32), num_frames=8, supersample=1
    )
    assert len(index) == 3
    eval_index = {key: {"context": [0, 7], "target": [3, 4]} for key in held_out}
    (tmp_path / "index.json").write_text(json.dumps(eval_index))
    config = _chunk_config(
        tmp_path / "run",
        [tmp_path / "train"],
        (32, 32),
        **{
            "val_every": 2,
            "val_factors": [1, 2],
            "data.val_roots": [str(tmp_path / "test")],
            "data.val_index": str(tmp_path / "index.json"),
            "data.val_samples": 2,
            "data.near": 0.5,
            "data.far": 15.0,
        },
    )
    result = fit(config)
    _check_trained(result)
    assert result.validation[2]["num_images"] == 4  # two held-out scenes x two indexed targets
    assert 5 < result.validation[2]["x1/psnr"] < 50


@pytest.mark.slow
@pytest.mark.parametrize("fmt, folder", [("llff", "llff_fern"), ("dtu", "dtu_scan24")])
def test_real_captures_converted_to_chunks(tmp_path: Path, preferred_samples, fmt: str, folder: str) -> None:
    images = preferred_samples.fern_images if fmt == "llff" else None
    report = convert(fmt, preferred_samples.root / folder, tmp_path / "chunks", images=images, image_format="jpeg")
    assert len(report.index) == 1
    result = fit(_chunk_config(tmp_path / "run", [tmp_path / "chunks"], (48, 64)))
    _check_trained(result)
