"""Training meets NaN: a non-finite loss or gradient skips its step (named, counted), too many in a
row stop the run with the last good checkpoint, and weights holding NaN are never saved."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from surfsplat.cli import main
from surfsplat.model import SurfSplat, load_checkpoint, save_checkpoint
from surfsplat.train import fit
from surfsplat.train.checkpoint import list_checkpoints, verify_checkpoint
from tests.helpers.training import quick_config, quick_train_argv


# ------------------------------------------------------------------------------------- NaN in training
def _quick(out: Path, **changes) -> object:
    return quick_config(out, {"steps": 3, "checkpoint_every": 1, **changes})


def _poison_loss(monkeypatch, bad_calls: set[int]) -> None:
    """The loss of the given (1-based) steps becomes NaN, as a diverging batch would make it."""
    from surfsplat.train import loop

    real, calls = loop.cascade_loss, [0]

    def poisoned(*args, **kwargs):
        calls[0] += 1
        loss, terms = real(*args, **kwargs)
        return (loss * float("nan"), terms) if calls[0] in bad_calls else (loss, terms)

    monkeypatch.setattr(loop, "cascade_loss", poisoned)


def _weights(checkpoint: Path) -> dict[str, torch.Tensor]:
    return load_file(str(checkpoint / "model.safetensors"))


def test_nonfinite_loss_skips_the_step_and_counts_it(tmp_path, monkeypatch):
    _poison_loss(monkeypatch, {2})
    result = fit(_quick(tmp_path / "run", max_nonfinite_steps=1))
    assert result.step == 3 and result.nonfinite_steps == [(2, "loss is nan")]
    assert [s for s, _ in result.losses] == [0, 2]  # the skipped step has no loss entry
    first, second, third = (_weights(p) for p in list_checkpoints(tmp_path / "run"))
    for key in first:  # step 2 changed nothing, steps 1 and 3 did; every checkpoint is finite
        assert torch.equal(first[key], second[key]) and bool(torch.isfinite(third[key]).all())
    assert any(not torch.equal(second[k], third[k]) for k in second)
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert {"step": 2, "train/nonfinite_steps": 1.0} in rows  # also a TensorBoard scalar of that name


def test_nonfinite_gradient_is_named_by_parameter(tmp_path, monkeypatch):
    from surfsplat.train import loop

    real_build = loop.build_model
    named = {}

    def build(config):
        model = real_build(config)
        name, param = next((n, p) for n, p in model.named_parameters() if n.endswith("weight"))
        named["name"] = name
        param.register_hook(lambda g: torch.full_like(g, float("inf")))
        return model

    monkeypatch.setattr(loop, "build_model", build)
    with pytest.raises(FloatingPointError) as caught:
        fit(_quick(tmp_path / "run", max_nonfinite_steps=1))
    message = str(caught.value)
    assert f"gradient of {named['name']} holds NaN or inf" in message and "2 steps in a row" in message
    # Step 1 was skipped, so its checkpoint holds the initial weights: finite, the last good one.
    assert "last good checkpoint:" in message and message.endswith("step-00000001 (lower optim.lr, or check the data)")
    assert [p.name for p in list_checkpoints(tmp_path / "run")] == ["step-00000001"]


def test_too_many_nonfinite_steps_stop_with_the_last_good_checkpoint(tmp_path, monkeypatch, capsys):
    _poison_loss(monkeypatch, {2, 3})
    out = tmp_path / "run"
    assert main(quick_train_argv(out, max_nonfinite_steps=1, steps=3)) == 1
    warning, *err = capsys.readouterr().err.strip().splitlines()
    assert "step 2: skipped, loss is nan (1 in a row)" in warning  # a skipped step is a warning
    # Step 2 was skipped (one in a row is allowed), so its checkpoint holds step 1's weights; step 3 stops.
    good = out / "checkpoints" / "step-00000002"
    assert len(err) == 1 and "2 steps in a row not finite" in err[0] and f"last good checkpoint: {good}" in err[0]
    assert list_checkpoints(out) == [out / "checkpoints" / "step-00000001", good]
    verify_checkpoint(good)
    load_checkpoint(good / "model")  # loading refuses NaN/inf tensors, so this proves the weights finite


def test_a_model_holding_nan_is_never_saved(tmp_path):
    model = SurfSplat.from_preset("tiny")
    with torch.no_grad():
        next(model.parameters()).view(-1)[0] = float("nan")
    with pytest.raises(FloatingPointError, match="not written, the weights hold NaN"):
        save_checkpoint(model, tmp_path / "m")
    assert list(tmp_path.iterdir()) == []
