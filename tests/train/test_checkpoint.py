"""Training checkpoints: exact round trip, verification, atomic publication under SIGKILL, and the
environment a resume compares (thread count, precision, code and library versions)."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from surfsplat.model.surfsplat import SurfSplat
from surfsplat.train import checkpoint as checkpoint_module
from surfsplat.train import fit
from surfsplat.train.checkpoint import (
    CorruptCheckpoint,
    TrainingState,
    capture_environment,
    capture_rng,
    changed_entries,
    latest_checkpoint,
    list_checkpoints,
    load_training_checkpoint,
    read_environment,
    restore_rng,
    save_training_checkpoint,
    source_digest,
    verify_checkpoint,
)
from surfsplat.train.config import override
from surfsplat.utils.checks import SurfSplatInputError
from tests.helpers.training import quick_config


def _trained_model_and_optimizer(seed: int = 0) -> tuple[SurfSplat, torch.optim.AdamW]:
    torch.manual_seed(seed)
    model = SurfSplat.from_preset("tiny")
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3)
    # Give every parameter a gradient so AdamW creates its moments (state to round-trip).
    for p in model.parameters():
        p.grad = torch.randn_like(p)
    optimizer.step()
    optimizer.zero_grad()
    return model, optimizer


def _state(step: int, optimizer: torch.optim.Optimizer) -> TrainingState:
    return TrainingState(
        step=step,
        config={"note": "test"},
        optimizer=optimizer.state_dict(),
        rng=[capture_rng()],
        data=[{"kind": "stream", "epoch": 3, "batches": 17}],
        extra={"validation": {"10": {"x1/psnr": 20.5}}},
        environment=[capture_environment("fp32")],
    )


def test_round_trip_is_exact(tmp_path: Path) -> None:
    model, optimizer = _trained_model_and_optimizer()
    torch.manual_seed(123)
    np.random.seed(7)
    random.seed(9)
    state = _state(40, optimizer)
    expected_draws = (torch.rand(5), np.random.rand(3), random.random())
    path = save_training_checkpoint(tmp_path, model, state)
    assert path == tmp_path / "checkpoints" / "step-00000040"

    torch.manual_seed(999)  # different weights and generators; the load must overwrite all of it
    fresh = SurfSplat.from_preset("tiny")
    loaded = load_training_checkpoint(path, fresh)
    for (name, a), b in zip(model.state_dict().items(), fresh.state_dict().values()):
        assert torch.equal(a, b), name
    new_optimizer = torch.optim.AdamW(fresh.parameters(), lr=1e-3)
    new_optimizer.load_state_dict(loaded.optimizer)
    for pid, slot in optimizer.state_dict()["state"].items():
        for key, value in slot.items():
            assert torch.equal(new_optimizer.state_dict()["state"][pid][key], value), (pid, key)
    assert new_optimizer.state_dict()["param_groups"] == json.loads(json.dumps(optimizer.state_dict()["param_groups"]))
    assert (loaded.step, loaded.data, loaded.extra) == (40, state.data, state.extra)
    assert loaded.environment == state.environment == read_environment(path)
    assert loaded.environment[0]["cpu_threads"] == torch.get_num_threads()

    restore_rng(loaded.rng[0])
    draws = (torch.rand(5), np.random.rand(3), random.random())
    assert torch.equal(draws[0], expected_draws[0])
    assert np.array_equal(draws[1], expected_draws[1]) and draws[2] == expected_draws[2]


def test_newest_by_listing_and_keep(tmp_path: Path) -> None:
    model, optimizer = _trained_model_and_optimizer()
    for step in (5, 10, 15, 20):
        save_training_checkpoint(tmp_path, model, _state(step, optimizer), keep=2)
    assert [p.name for p in list_checkpoints(tmp_path)] == ["step-00000015", "step-00000020"]
    assert latest_checkpoint(tmp_path).name == "step-00000020"


def test_unfinished_folders_are_ignored_then_removed(tmp_path: Path) -> None:
    model, optimizer = _trained_model_and_optimizer()
    save_training_checkpoint(tmp_path, model, _state(5, optimizer))
    leftover = tmp_path / "checkpoints" / ".tmp-step-00000010-4242"  # a writer killed mid-save
    leftover.mkdir()
    (leftover / "model.safetensors").write_bytes(b"half")
    assert latest_checkpoint(tmp_path).name == "step-00000005"
    save_training_checkpoint(tmp_path, model, _state(10, optimizer))
    assert not leftover.exists()
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["step-00000005", "step-00000010"]


def test_republishing_a_step_replaces_it(tmp_path: Path) -> None:
    # A run killed after publishing step 10 but resumed from step 5 reaches step 10 again.
    model, optimizer = _trained_model_and_optimizer()
    save_training_checkpoint(tmp_path, model, _state(10, optimizer))
    with torch.no_grad():
        next(model.parameters()).add_(1.0)
    path = save_training_checkpoint(tmp_path, model, _state(10, optimizer))
    fresh = SurfSplat.from_preset("tiny")
    load_training_checkpoint(path, fresh)
    assert torch.equal(next(fresh.parameters()), next(model.parameters()))


@pytest.mark.parametrize("victim", ["model.safetensors", "train_state.safetensors", "train_state.json"])
def test_damage_is_detected(tmp_path: Path, victim: str) -> None:
    model, optimizer = _trained_model_and_optimizer()
    path = save_training_checkpoint(tmp_path, model, _state(5, optimizer))
    data = bytearray((path / victim).read_bytes())
    data[len(data) // 2] ^= 0x01
    (path / victim).write_bytes(bytes(data))
    with pytest.raises(CorruptCheckpoint, match=f"{victim}: contents do not match the manifest"):
        load_training_checkpoint(path, SurfSplat.from_preset("tiny"))


def test_missing_manifest_and_other_model(tmp_path: Path) -> None:
    model, optimizer = _trained_model_and_optimizer()
    path = save_training_checkpoint(tmp_path, model, _state(5, optimizer))
    other = SurfSplat.from_preset("tiny", opacity_max=1.0)
    with pytest.raises(SurfSplatInputError, match="model configuration differs"):
        load_training_checkpoint(path, other)
    (path / "manifest.json").unlink()
    with pytest.raises(CorruptCheckpoint, match="manifest.json: missing"):
        verify_checkpoint(path)


def test_source_digest_sees_every_edit(tmp_path: Path) -> None:
    """The digest stands for the code of a run: any edited, added or renamed source changes it."""
    (tmp_path / "pkg" / "sub").mkdir(parents=True)
    (tmp_path / "pkg" / "a.py").write_text("x = 1\n")
    (tmp_path / "pkg" / "sub" / "b.py").write_text("y = 2\n")
    first = source_digest(tmp_path / "pkg")
    (tmp_path / "pkg" / "notes.txt").write_text("not code")
    assert source_digest(tmp_path / "pkg") == first
    (tmp_path / "pkg" / "a.py").write_text("x = 1.0\n")
    edited = source_digest(tmp_path / "pkg")
    assert edited != first
    (tmp_path / "pkg" / "sub" / "b.py").rename(tmp_path / "pkg" / "sub" / "c.py")
    assert source_digest(tmp_path / "pkg") not in (first, edited)
    identity = checkpoint_module.software_identity()
    assert len(identity["surfsplat"]) == 16 and identity["torch"] == torch.__version__


def test_environment_is_read_before_loading(tmp_path: Path) -> None:
    model, optimizer = _trained_model_and_optimizer()
    path = save_training_checkpoint(tmp_path, model, _state(5, optimizer))
    assert read_environment(path) == [capture_environment("fp32")]
    older = _state(10, optimizer)
    older.environment = None  # written before checkpoints recorded it
    assert read_environment(save_training_checkpoint(tmp_path, model, older)) == []
    assert read_environment(tmp_path / "checkpoints" / "step-00000099") == []
    saved = {"cpu_threads": 2, "precision": "bf16", "software": {"surfsplat": "a", "torch": "2.5"}}
    current = {"cpu_threads": 1, "precision": "bf16", "software": {"surfsplat": "b", "torch": "2.5"}}
    assert changed_entries(saved, current) == ["cpu_threads: 2 -> 1", "software.surfsplat: 'a' -> 'b'"]


def test_resume_names_other_code(tmp_path: Path, monkeypatch, caplog) -> None:
    """A resume with the code, libraries, threads and precision of the checkpoint says nothing;
    with other code (an edited working tree, another release) it warns that the bits will differ."""
    config = quick_config(
        tmp_path / "run",
        {"steps": 1, "checkpoint_every": 1},
    )
    fit(config)
    with caplog.at_level("WARNING", logger="surfsplat.train"):
        fit(override(config, {"steps": 2}), resume=True)
    assert "another environment" not in caplog.text
    edited = {**checkpoint_module.software_identity(), "surfsplat": "0123456789abcdef"}
    monkeypatch.setattr(checkpoint_module, "software_identity", lambda: edited)
    caplog.clear()
    with caplog.at_level("WARNING", logger="surfsplat.train"):
        fit(override(config, {"steps": 3}), resume=True)
    assert "another environment (software.surfsplat:" in caplog.text
    assert "-> '0123456789abcdef'" in caplog.text and "not bit-identical" in caplog.text


_SAVER = textwrap.dedent(
    """
    import sys, torch
    from surfsplat.model.surfsplat import SurfSplat
    from surfsplat.train.checkpoint import TrainingState, capture_rng, latest_checkpoint, save_training_checkpoint
    torch.set_num_threads(1)
    out = sys.argv[1]
    model = SurfSplat.from_preset("tiny")
    opt = torch.optim.AdamW(model.parameters())
    for p in model.parameters():
        p.grad = torch.ones_like(p)
    opt.step()
    latest = latest_checkpoint(out)
    step = 0 if latest is None else int(latest.name.split("-")[1])
    print("ready", flush=True)
    while True:
        step += 1
        with torch.no_grad():
            for p in model.parameters():
                p.add_(0.001)
        state = TrainingState(step=step, config={}, optimizer=opt.state_dict(), rng=[capture_rng()], data=[{}])
        save_training_checkpoint(out, model, state, keep=2)
    """
)


@pytest.mark.slow
def test_sigkill_while_saving_never_leaves_a_corrupt_checkpoint(tmp_path: Path) -> None:
    """A process doing nothing but save checkpoints is SIGKILLed at random moments; every
    published checkpoint must verify and load, and at least one kill must land mid-save."""
    script = tmp_path / "saver.py"
    script.write_text(_SAVER)
    out = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    rng = random.Random(0)
    landed_mid_save = 0
    for _ in range(3):
        proc = subprocess.Popen([sys.executable, str(script), str(out)], stdout=subprocess.PIPE, env=env, text=True)
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(rng.uniform(0.2, 1.0))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        assert proc.returncode == -signal.SIGKILL
        landed_mid_save += any(p.name.startswith(".tmp-") for p in (out / "checkpoints").iterdir())
        published = list_checkpoints(out)
        assert published, "no checkpoint was published before the kill"
        for path in published:
            verify_checkpoint(path)
        load_training_checkpoint(published[-1], SurfSplat.from_preset("tiny"))
    assert landed_mid_save >= 1
