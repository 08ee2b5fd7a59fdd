"""Messages of the command line: --quiet / --verbose through `logging`, progress as a bar only on a
terminal (periodic lines elsewhere, rank 0 only), and `surfsplat --version`."""

from __future__ import annotations

import importlib.metadata
import logging
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from tqdm import tqdm

import surfsplat
from surfsplat.cli import main
from surfsplat.utils import log


@pytest.fixture(autouse=True)
def restore_logging():
    """Each test configures the package's logging itself; leave it as it was found."""
    root = logging.getLogger(log.ROOT)
    handlers, level = list(root.handlers), root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


def _render_scene(tmp_path: Path) -> list[str]:
    return ["render-scene", "--out", str(tmp_path), "--resolution", "16", "--scales", "1", "2", "--backend", "torch"]


def test_version_is_the_installed_one(capsys) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    try:
        expected = importlib.metadata.version("surfsplat")
    except importlib.metadata.PackageNotFoundError:
        expected = surfsplat.__version__
    assert capsys.readouterr().out == f"surfsplat {expected}\n"


def test_info_by_default_quiet_hides_it_verbose_adds_debug(tmp_path: Path, capsys) -> None:
    argv = _render_scene(tmp_path)
    assert main(argv) == 0
    out, err = capsys.readouterr()
    assert out == f"wrote {tmp_path}/ (color_*.png, depth_*.png, normal_*.png, scene.ply, report.json)\n"
    lines = err.splitlines()  # info: one line per scale, plain text
    assert len(lines) == 2 and re.fullmatch(r"x1: 16x16 in [0-9.]+ s, hole fraction [0-9.]+", lines[0]), err
    assert lines[1].startswith("x2: 32x32 in ")

    for quiet in (["-q", *argv], [*argv, "--quiet"]):  # before or after the command
        assert main(quiet) == 0
        out, err = capsys.readouterr()
        assert out.startswith("wrote ") and err == ""

    for verbose in (["--verbose", *argv], [*argv, "-v"], ["-q", *argv, "-v"]):  # the later option wins
        assert main(verbose) == 0
        out, err = capsys.readouterr()
        assert out.startswith("wrote ")
        lines = err.splitlines()
        assert re.fullmatch(r"\d\d:\d\d:\d\d DEBUG +surfsplat\.cli: surfsplat \S+ on Python .*", lines[0]), err
        assert any(re.search(r"INFO +surfsplat\.commands\.render_scene: x2: 32x32", line) for line in lines), err


def test_quiet_and_verbose_together_is_a_usage_error(tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit) as stop:
        main([*_render_scene(tmp_path), "-q", "-v"])
    assert stop.value.code == 2
    assert "not allowed with argument" in capsys.readouterr().err


def test_warnings_are_named_and_other_ranks_keep_only_them(monkeypatch, capsys) -> None:
    logger = logging.getLogger("surfsplat.test")
    log.configure(logging.INFO)
    logger.info("starting")
    logger.warning("no held-out scenes")
    assert capsys.readouterr().err == "starting\nwarning: no held-out scenes\n"
    monkeypatch.setenv("RANK", "1")
    log.configure(logging.DEBUG)
    logger.info("starting")
    logger.warning("no held-out scenes")
    err = capsys.readouterr().err
    assert err.startswith("rank 1: ") and err.count("\n") == 1 and "WARNING" in err and "starting" not in err


class _Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_off_a_terminal_progress_is_a_line_per_tenth(monkeypatch, capsys) -> None:
    clock = _Clock()
    monkeypatch.setattr(log.time, "perf_counter", clock)
    log.configure(logging.INFO)
    bar = log.progress(range(50), desc="score", unit="room")
    assert isinstance(bar, log.LogProgress)  # pytest captures stderr: not a terminal
    count = 0
    for _ in bar:
        clock.now += 1.0  # a room a second: every tenth (5 rooms) is more than LINE_MIN_SECONDS apart
        count += 1
    assert count == 50
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = err.splitlines()
    assert [int(re.match(r"score: (\d+)/50 room \((\d+)%\)", line).group(1)) for line in lines] == list(
        range(5, 51, 5)
    ), err
    assert "eta" in lines[0] and "eta" not in lines[-1]  # the last line is the total, not a forecast


def test_off_a_terminal_a_fast_loop_logs_only_its_final_line(monkeypatch, capsys) -> None:
    clock = _Clock()
    monkeypatch.setattr(log.time, "perf_counter", clock)
    log.configure(logging.INFO)
    for _ in log.progress(range(36), desc="render", unit="frame"):
        clock.now += 0.01  # 0.36 s in all: percent lines would be noise
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("render: 36/36 frame (100%)"), lines


def test_off_a_terminal_a_long_loop_logs_every_few_seconds(monkeypatch, capsys) -> None:
    clock = _Clock()
    monkeypatch.setattr(log.time, "perf_counter", clock)
    log.configure(logging.INFO)
    counter = log.progress(total=None, desc="train", unit="step")  # no total: time alone paces the lines
    for _ in range(9):
        clock.now += 3.0
        counter.set_postfix(loss="0.1234")
        counter.update(1)
    counter.close()
    lines = capsys.readouterr().err.splitlines()
    # A line once LINE_SECONDS (10 s) have passed: after steps 4 and 8 (12 s, 24 s), then the final one.
    assert [line.split(",")[0] for line in lines] == ["train: 4 step", "train: 8 step", "train: 9 step"], lines
    assert lines[0] == "train: 4 step, 00:12, 3.00 s/step, loss 0.1234"


def test_progress_is_a_bar_on_a_terminal_and_nothing_when_quiet_or_not_rank_0(monkeypatch) -> None:
    log.configure(logging.INFO)
    monkeypatch.setattr(log, "_on_terminal", lambda: True)
    bar = log.progress(range(3), desc="render")
    assert type(bar) is tqdm and not bar.disable
    bar.close()
    log.configure(logging.WARNING)
    quiet = log.progress(range(3), desc="render")
    assert type(quiet) is tqdm and quiet.disable
    log.configure(logging.INFO)
    monkeypatch.setenv("RANK", "1")
    assert log.progress(range(3)).disable
    monkeypatch.delenv("RANK")
    assert log.progress(range(3), enabled=False).disable


def test_a_training_run_logged_to_a_file_has_lines_not_redraws(tmp_path: Path) -> None:
    # As under a job scheduler: stderr is a file. The run reports through log lines, the result on stdout.
    command = [sys.executable, "-m", "surfsplat", "train", "--preset", "tiny", "--out", str(tmp_path / "run")]
    command += ["--steps", "3", "--val-every", "0", "--checkpoint-every", "3", "--log-every", "1"]
    command += ["--image-shape", "32", "32", "--set", "data.synthetic_length=2", "--set", "data.num_target_views=1"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    with open(tmp_path / "stderr.log", "w") as stderr:
        proc = subprocess.run(command, stdout=subprocess.PIPE, stderr=stderr, text=True, env=env, timeout=300)
    err = (tmp_path / "stderr.log").read_text()
    assert proc.returncode == 0, err
    assert "\r" not in err
    steps = [int(m) for m in re.findall(r"^train: (\d)/3 step \(\d+%\)", err, flags=re.M)]
    # Three fast steps: no line is due before LINE_MIN_SECONDS, so the run reports its final line only.
    assert steps[-1] == 3 and len(steps) == len(set(steps)), err
    assert "loss " in err.splitlines()[-1]
    assert proc.stdout.startswith("trained steps 0..3: loss ")
