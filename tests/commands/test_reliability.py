"""Fail early, fail clean: a corpus of broken inputs and output paths across every command (exit code
2, exactly one stderr line naming the file or option the user gave, nothing written anywhere),
interruption mid-write (SIGINT and SIGTERM to a real process: one line, no partial file, earlier
files intact), a full disk (one line naming the file), NaN injected into training (skipped by name,
stopped after too many in a row, the checkpoint on disk finite) and degenerate scenes (no NaN in any
output). The README's reliability section tabulates the corpus."""

from __future__ import annotations

import errno
import http.client
import json
import logging
import os
import shutil
import signal
import struct
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from plyfile import PlyData
from safetensors.torch import load_file, save_file

from surfsplat import Cameras
from surfsplat.cli import main
from surfsplat.data.cameras import save_cameras
from surfsplat.data.synthetic import SyntheticDataset, SyntheticDatasetConfig, write_synthetic_chunks
from surfsplat.data.synthetic.surfel_scene import make_scene
from surfsplat.export.images import write_png
from surfsplat.export.mesh import load_mesh
from surfsplat.export.ply import load_ply, save_ply
from surfsplat.model import SurfSplat, save_checkpoint
from surfsplat.train.checkpoint import list_checkpoints, verify_checkpoint
from tests.helpers.files import no_temporaries
from tests.helpers.training import quick_train_argv

SIZE = 64  # every image of the corpus is 64 x 64
SLOW_WRITER = Path(__file__).resolve().parents[1] / "helpers" / "slow_writer.py"
FERN = Path(__file__).resolve().parents[1] / "data" / "llff_fern"  # a valid LLFF scene (read only)


@dataclass(frozen=True)
class World:
    """Valid inputs of every kind; each case breaks one of them (copies, never these files)."""

    root: Path
    images: tuple[Path, Path]  # two 64x64 views of a procedural room
    cameras: Path  # their JSON camera file
    checkpoint: Path  # a random tiny model (model.safetensors + model.json)
    ply: Path  # 512 surfels of the procedural scene
    ply_cameras: Path  # the scene's two source cameras
    chunks: Path  # two procedural rooms as chunks
    index: Path  # an evaluation index over them


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> World:
    root = tmp_path_factory.mktemp("world")
    sample = SyntheticDataset(
        SyntheticDatasetConfig(length=1, seed=3, image_shape=(SIZE, SIZE), num_target_views=1, supersample=1)
    )[0]
    images = (root / "view0.png", root / "view1.png")
    for path, image in zip(images, sample["context"]["image"]):
        write_png(path, image)
    cams = Cameras(sample["context"]["c2w"].double(), sample["context"]["K"].double())
    save_cameras(root / "cameras.json", cams, SIZE, SIZE, [p.name for p in images], near=0.5, far=15.0)
    torch.manual_seed(0)
    weights, _ = save_checkpoint(SurfSplat.from_preset("tiny"), root / "tiny" / "model")
    scene = make_scene(resolution=16)
    save_ply(scene.gaussians, root / "scene" / "surfels.ply")
    save_cameras(root / "scene" / "cameras.json", scene.sources, 16, 16, ["left.png", "right.png"])
    keys = sorted(write_synthetic_chunks(root / "chunks", 2, seed=5, image_shape=(32, 32), num_frames=4, supersample=1))
    (root / "index.json").write_text(json.dumps({keys[0]: {"context": [0, 3], "target": [1]}, keys[1]: None}))
    return World(
        root,
        images,
        root / "cameras.json",
        weights,
        root / "scene" / "surfels.ply",
        root / "scene" / "cameras.json",
        root / "chunks",
        root / "index.json",
    )


def _tree(*folders: Path) -> dict[str, tuple[int, int]]:
    """Every file under `folders`: relative name -> (size, modification time)."""
    out = {}
    for folder in folders:
        for path in folder.rglob("*"):
            if path.is_file():
                stat = path.stat()
                out[str(path)] = (stat.st_size, stat.st_mtime_ns)
            else:
                out[str(path)] = (-1, 0)
    return out


# ------------------------------------------------------------------------------ broken files, made per case
def _truncated_png(tmp: Path, w: World) -> Path:
    path = tmp / "view1.png"  # the name the camera file knows
    path.write_bytes(w.images[0].read_bytes()[:200])
    return path


def _small_pair(tmp: Path, w: World) -> tuple[Path, Path, Path]:
    """Two 8x8 photos with their camera file: too small for the network (multiples of 16)."""
    a, b = tmp / "small0.png", tmp / "small1.png"
    for path in (a, b):
        iio.imwrite(path, np.full((8, 8, 3), 120, np.uint8))
    doc = json.loads(w.cameras.read_text())
    doc["frames"][0]["name"], doc["frames"][1]["name"] = a.name, b.name
    (tmp / "small.json").write_text(json.dumps(doc))
    return a, b, tmp / "small.json"


def _colmap_cameras(tmp: Path, w: World, camera_line: str) -> Path:
    """A COLMAP text model of the world's two views whose one camera is `camera_line`'s model and parameters."""
    model = tmp / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text(f"1 {camera_line}\n")
    rows = [f"{i + 1} 1 0 0 0 {0.1 * i} 0 0 1 {p.name}\n\n" for i, p in enumerate(w.images)]
    (model / "images.txt").write_text("".join(rows))
    return model


def _listed_photos_missing(tmp: Path, w: World) -> Path:
    """A transforms.json whose photos were all left out by its publisher."""
    frames = [{"file_path": f"images/{p.name}", "transform_matrix": np.eye(4).tolist()} for p in w.images]
    (tmp / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames}))
    return tmp / "transforms.json"


def _odd_size(tmp: Path, w: World) -> Path:
    path = tmp / "view1.png"
    iio.imwrite(path, np.full((48, SIZE, 3), 90, np.uint8))
    return path


def _nan_cameras(tmp: Path, w: World) -> Path:
    doc = json.loads(w.cameras.read_text())
    doc["frames"][1]["c2w"][0][3] = float("nan")
    path = tmp / "nan_cameras.json"
    path.write_text(json.dumps(doc))  # Python writes the NaN token that JSON readers accept
    return path


def _nan_checkpoint(tmp: Path, w: World) -> Path:
    tensors = load_file(str(w.checkpoint))
    key = sorted(k for k, v in tensors.items() if v.is_floating_point())[3]
    tensors[key] = tensors[key].clone()
    tensors[key].view(-1)[0] = float("inf")
    path = tmp / "nan_model.safetensors"
    save_file(tensors, str(path))
    shutil.copy(w.checkpoint.with_suffix(".json"), path.with_suffix(".json"))
    return path


def _truncated_checkpoint(tmp: Path, w: World) -> Path:
    path = tmp / "cut.safetensors"
    path.write_bytes(w.checkpoint.read_bytes()[:5000])
    shutil.copy(w.checkpoint.with_suffix(".json"), path.with_suffix(".json"))
    return path


def _nan_ply(tmp: Path, w: World, column: str = "x") -> Path:
    ply = PlyData.read(str(w.ply))
    ply["vertex"].data[column][7] = np.inf if column == "opacity" else np.nan
    path = tmp / f"nan_{column}.ply"
    ply.write(str(path))
    return path


def _junk(tmp: Path, name: str, content: str = "not what it should be {") -> Path:
    path = tmp / name
    path.write_text(content)
    return path


def _folder_with(tmp: Path, name: str) -> Path:
    folder = tmp / name
    folder.mkdir()
    (folder / "keep.txt").write_text("an input the command must not touch\n")
    return folder


# ------------------------------------------------------------------------------------------- the corpus
def _reconstruct(w: World, *extra: str, images=None, cameras=None, checkpoint=None, out=None) -> list[str]:
    shown = images or w.images
    argv = ["reconstruct", "--checkpoint", str(checkpoint or w.checkpoint), "--images", *map(str, shown)]
    argv += ["--cameras", str(cameras or w.cameras), "--formats", "ply", "--no-progress", *extra]
    return argv + (["--out", str(out)] if out is not None else [])


def _render(w: World, ply=None, out=None, *extra: str) -> list[str]:
    return ["render", str(ply or w.ply), "--cameras", str(w.ply_cameras), "--out", str(out), *extra]


def _export(w: World, ply=None, out=None, *extra: str) -> list[str]:
    argv = ["export", str(ply or w.ply), "--cameras", str(w.ply_cameras), "--formats", "ply", "--no-progress"]
    return argv + (["--out", str(out)] if out is not None else []) + list(extra)


def _eval(w: World, out, *extra: str, checkpoint=None, index=None, data=None) -> list[str]:
    argv = ["eval", "--checkpoint", str(checkpoint or w.checkpoint), "--data", str(data or w.chunks)]
    return argv + ["--index", str(index or w.index), "--out", str(out), "--no-progress", *extra]


def _train(out: Path, **sets) -> list[str]:
    return quick_train_argv(out, **sets)


def _copied_ply(tmp: Path, w: World) -> Path:
    folder = tmp / "rec"
    folder.mkdir()
    shutil.copy(w.ply, folder / "surfels.ply")
    return folder / "surfels.ply"


# (id, family, argv from (world, tmp), words the one line must contain); bad files live in tmp
CASES = [
    # reconstruct
    ("reconstruct-out-is-file", "output", lambda w, t: _reconstruct(w, out=_junk(t, "out")), ["--out", "is a file"]),
    (
        "reconstruct-out-below-file",
        "output",
        lambda w, t: _reconstruct(w, out=_junk(t, "f") / "sub"),
        ["--out", "is a file"],
    ),
    (
        "reconstruct-out-overwrites-cameras",
        "output",
        lambda w, t: _reconstruct(w, cameras=shutil.copy(w.cameras, t / "cameras.json"), out=t),
        ["--out", "would overwrite the input", "cameras.json"],
    ),
    (
        "reconstruct-missing-image",
        "image",
        lambda w, t: _reconstruct(w, images=[w.images[0], t / "nope.png"], out=t / "o"),
        ["nope.png", "not found"],
    ),
    (
        "reconstruct-truncated-image",
        "image",
        lambda w, t: _reconstruct(w, images=[w.images[0], _truncated_png(t, w)], out=t / "o"),
        ["view1.png: cannot decode"],
    ),
    (
        "reconstruct-image-too-small",
        "image",
        lambda w, t: _reconstruct(w, images=_small_pair(t, w)[:2], cameras=t / "small.json", out=t / "o"),
        ["--images", "small0.png", "8x8"],
    ),
    (
        "reconstruct-image-of-a-size-no-camera-fits",
        "image",
        lambda w, t: _reconstruct(w, images=[w.images[0], _odd_size(t, w)], out=t / "o"),
        ["view1.png is 64x48 but the cameras are for 64x64"],
    ),
    (
        "reconstruct-one-image",
        "argument",
        lambda w, t: _reconstruct(w, images=[w.images[0]], out=t / "o"),
        ["--images", "at least 2"],
    ),
    (
        "reconstruct-nan-camera",
        "camera",
        lambda w, t: _reconstruct(w, cameras=_nan_cameras(t, w), out=t / "o"),
        ["nan_cameras.json", "NaN"],
    ),
    (
        "reconstruct-nan-distortion",
        "camera",
        lambda w, t: _reconstruct(
            w, cameras=_colmap_cameras(t, w, f"OPENCV {SIZE} {SIZE} 60 60 32 32 nan 0 0 0"), out=t / "o"
        ),
        ["cameras.txt:1: camera 1: camera model OPENCV: parameter k1 is NaN"],
    ),
    (
        "reconstruct-unknown-camera-model",
        "camera",
        lambda w, t: _reconstruct(
            w, cameras=_colmap_cameras(t, w, f"DIVISION {SIZE} {SIZE} 60 60 32 32 0.1"), out=t / "o"
        ),
        ["cameras.txt:1: camera 1 has camera model DIVISION, which is not supported"],
    ),
    (
        "reconstruct-every-listed-photo-missing",
        "camera",
        lambda w, t: _reconstruct(w, cameras=_listed_photos_missing(t, w), out=t / "o"),
        ["transforms.json: every photo listed in it is missing"],
    ),
    (
        "reconstruct-camera-file-missing",
        "camera",
        lambda w, t: _reconstruct(w, cameras=t / "none.json", out=t / "o"),
        ["none.json"],
    ),
    (
        "reconstruct-nan-checkpoint",
        "checkpoint",
        lambda w, t: _reconstruct(w, checkpoint=_nan_checkpoint(t, w), out=t / "o"),
        ["nan_model.safetensors", "NaN or inf"],
    ),
    (
        "reconstruct-truncated-checkpoint",
        "checkpoint",
        lambda w, t: _reconstruct(w, checkpoint=_truncated_checkpoint(t, w), out=t / "o"),
        ["cut.safetensors"],
    ),
    (
        "reconstruct-near-far",
        "argument",
        lambda w, t: _reconstruct(w, "--near", "5", "--far", "1", out=t / "o"),
        ["--near/--far"],
    ),
    (
        "reconstruct-size-not-multiple",
        "argument",
        lambda w, t: _reconstruct(w, "--size", "24", "24", out=t / "o"),
        ["--size", "multiples of 16"],
    ),
    # render
    ("render-out-is-file", "output", lambda w, t: _render(w, out=_junk(t, "out")), ["--out", "is a file"]),
    (
        "render-out-overwrites-ply",
        "output",
        lambda w, t: _render(w, shutil.copy(w.ply, t / "left_color.png"), t),
        ["--out", "would overwrite the input", "left_color.png"],
    ),
    ("render-nan-ply", "ply", lambda w, t: _render(w, _nan_ply(t, w), t / "o"), ["nan_x.ply", "'x'", "NaN"]),
    ("render-junk-ply", "ply", lambda w, t: _render(w, _junk(t, "junk.ply"), t / "o"), ["junk.ply", "not a readable"]),
    ("render-missing-ply", "ply", lambda w, t: _render(w, t / "none.ply", t / "o"), ["none.ply", "no such PLY"]),
    ("render-scale-zero", "argument", lambda w, t: _render(w, None, t / "o", "--scale", "0"), ["--scale"]),
    ("render-views-range", "argument", lambda w, t: _render(w, None, t / "o", "--views", "5"), ["--views", "[5]"]),
    # export
    ("export-out-is-file", "output", lambda w, t: _export(w, out=_junk(t, "out")), ["--out", "is a file"]),
    (
        "export-default-out-overwrites-ply",
        "output",
        lambda w, t: _export(w, _copied_ply(t, w)),
        ["--out (default: the PLY's folder)", "would overwrite the input", "surfels.ply"],
    ),
    (
        "export-nan-opacity-ply",
        "ply",
        lambda w, t: _export(w, _nan_ply(t, w, "opacity"), t / "o"),
        ["nan_opacity.ply", "'opacity'"],
    ),
    (
        "export-cameras-missing",
        "camera",
        lambda w, t: ["export", str(w.ply), "--cameras", str(t / "gone.json"), "--out", str(t / "o")],
        ["gone.json"],
    ),
    # eval
    ("eval-out-is-file", "output", lambda w, t: _eval(w, _junk(t, "out")), ["--out", "is a file"]),
    (
        "eval-out-is-data-folder",
        "output",
        lambda w, t: _eval(w, t / "data", data=shutil.copytree(w.chunks, t / "data")),
        ["--out", "is the input folder"],
    ),
    (
        "eval-index-malformed",
        "index",
        lambda w, t: _eval(w, t / "o", index=_junk(t, "index.json")),
        ["index.json", "not valid JSON"],
    ),
    (
        "eval-index-missing-key",
        "index",
        lambda w, t: _eval(w, t / "o", index=_junk(t, "i.json", '{"s": {"context": [0, 1]}}')),
        ["i.json", "'target'"],
    ),
    ("eval-data-missing", "dataset", lambda w, t: _eval(w, t / "o", data=t / "nodata"), ["nodata", "not found"]),
    ("eval-max-entries", "argument", lambda w, t: _eval(w, t / "o", "--max-entries", "0"), ["--max-entries"]),
    (
        "eval-nan-checkpoint",
        "checkpoint",
        lambda w, t: _eval(w, t / "o", checkpoint=_nan_checkpoint(t, w)),
        ["nan_model.safetensors", "NaN or inf"],
    ),
    # convert
    (
        "convert-out-is-src",
        "output",
        lambda w, t: ["convert", "llff", str(_folder_with(t, "scene")), str(t / "scene")],
        ["OUT", "is the input folder"],
    ),
    (
        "convert-out-is-file",
        "output",
        lambda w, t: ["convert", "llff", str(_folder_with(t, "scene")), str(_junk(t, "chunks"))],
        ["OUT", "is a file"],
    ),
    (
        "convert-src-not-a-scene",
        "dataset",
        lambda w, t: ["convert", "llff", str(_folder_with(t, "scene")), str(t / "chunks")],
        ["scene"],
    ),
    (
        "convert-out-holds-chunks",
        "dataset",
        lambda w, t: ["convert", "llff", str(FERN), str(shutil.copytree(w.chunks, t / "c"))],
        ["already holds", "chunks"],
    ),
    # poses
    (
        "poses-out-is-folder",
        "output",
        lambda w, t: ["poses", *map(str, w.images), "--out", str(_folder_with(t, "cams.json"))],
        ["--out", "is a folder"],
    ),
    (
        "poses-out-not-json",
        "argument",
        lambda w, t: ["poses", *map(str, w.images), "--out", str(t / "cams.txt")],
        ["--out", ".json"],
    ),
    (
        "poses-missing-image",
        "image",
        lambda w, t: ["poses", str(w.images[0]), str(t / "gone.png"), "--out", str(t / "c.json")],
        ["gone.png"],
    ),
    # demo
    ("demo-out-is-file", "output", lambda w, t: ["demo", "--out", str(_junk(t, "d"))], ["--out", "is a file"]),
    (
        "demo-image-size",
        "argument",
        lambda w, t: ["demo", "--out", str(t / "d"), "--image-size", "40"],
        ["--image-size", "multiple of 16"],
    ),
    # train
    (
        "train-out-is-file",
        "output",
        lambda w, t: ["train", "--preset", "tiny", "--out", str(_junk(t, "run"))],
        ["--out", "is a file"],
    ),
    (
        "train-steps-zero",
        "argument",
        lambda w, t: _train(t / "r", steps=0),
        ["steps"],
    ),
    (
        "train-max-nonfinite-negative",
        "argument",
        lambda w, t: _train(t / "r", max_nonfinite_steps=-1),
        ["max_nonfinite_steps"],
    ),
    (
        "train-config-malformed",
        "argument",
        lambda w, t: ["train", "--config", str(_junk(t, "config.json")), "--out", str(t / "r")],
        ["config.json", "not valid JSON"],
    ),
    # view
    ("view-missing", "ply", lambda w, t: ["view", str(t / "none.ply"), "--port", "0"], ["none.ply"]),
    ("view-nan-ply", "ply", lambda w, t: ["view", str(_nan_ply(t, w)), "--port", "0"], ["nan_x.ply", "'x'"]),
    ("view-port", "argument", lambda w, t: ["view", str(w.ply), "--port", "70000"], ["--port"]),
    # render-scene
    (
        "render-scene-out-is-file",
        "output",
        lambda w, t: ["render-scene", "--out", str(_junk(t, "o"))],
        ["--out", "is a file"],
    ),
    ("render-scene-resolution", "argument", lambda w, t: ["render-scene", "--resolution", "4"], ["--resolution"]),
]


@pytest.mark.parametrize("make, needles", [c[2:] for c in CASES], ids=[c[0] for c in CASES])
def test_corpus_case_is_one_line_exit_2_and_writes_nothing(make, needles, world, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # a default output folder would appear here
    argv = make(world, tmp_path)
    before = _tree(tmp_path, world.root)
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"surfsplat {argv[0]}: error: "), err
    for needle in needles:
        assert needle in lines[0], (needle, err)
    assert _tree(tmp_path, world.root) == before  # nothing created, nothing changed


def test_corpus_covers_every_command_and_family():
    commands = {c[0].split("-out")[0].split("-")[0] for c in CASES}
    families = {c[1] for c in CASES}
    assert len(CASES) >= 40
    assert {"reconstruct", "render", "export", "eval", "convert", "poses", "demo", "train", "view"} <= commands
    assert {"output", "image", "camera", "checkpoint", "ply", "argument", "dataset", "index"} <= families


def test_output_folder_that_cannot_be_written(world, tmp_path, capsys, monkeypatch):
    # Permission bits do not bind the root user, so the check's question to the system is answered here.
    locked = _folder_with(tmp_path, "locked")
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if Path(p) == locked else real_access(p, mode))
    for argv in (_reconstruct(world, out=locked / "o"), _export(world, out=locked), _eval(world, locked)):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and f"{locked} is not writable" in err and "--out" in err, err
    assert sorted(p.name for p in locked.iterdir()) == ["keep.txt"]


# ------------------------------------------------------------------------------------------ interruption
def _default_sigint() -> None:
    """In the child before exec: SIGINT back to its default action. A suite started in the
    background by a non-interactive shell (`nohup pytest &`) inherits SIGINT ignored, and Python
    then keeps ignoring it, as a user's `nohup surfsplat train &` should."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _interrupt(argv: list[str], hold: str, sig: int, tmp: Path) -> tuple[int, str]:
    """Run the command in a process, wait until the file `hold` is fully written but not yet renamed,
    send `sig`; returns (exit code, stderr)."""
    ready = tmp / "ready"
    proc = subprocess.Popen(
        [sys.executable, str(SLOW_WRITER), hold, str(ready), *argv, "--quiet"],  # progress lines off
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_default_sigint,
    )
    deadline = time.monotonic() + 240
    while not ready.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            pytest.fail(f"the command never reached {hold}: {proc.communicate()[1]}")
        time.sleep(0.05)
    assert Path(ready.read_text()).exists()  # the temporary file is there, complete, not yet renamed
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    return proc.returncode, err


def _assert_interrupted(code: int, err: str, command: str, sig: int) -> None:
    lines = err.strip().splitlines()
    assert code == 128 + sig, err
    assert len(lines) == 1 and lines[0].startswith(f"surfsplat {command}: interrupted ({signal.Signals(sig).name})")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_export_interrupted_mid_write_keeps_earlier_files_and_no_partial_one(world, tmp_path, sig):
    out = tmp_path / "out"
    argv = _export(world, None, out, "--formats", "ply", "mesh", "--frames", "2", "--mesh-resolution", "16")
    code, err = _interrupt(argv, "mesh.ply", sig, tmp_path)
    _assert_interrupted(code, err, "export", sig)
    assert not (out / "mesh.ply").exists()
    no_temporaries(out)
    # What was complete before the signal is intact: the surfels read back as they were written.
    torch.testing.assert_close(load_ply(out / "surfels.ply").means, load_ply(world.ply).means)
    assert json.loads((out / "cameras.json").read_text())["frames"]


def test_reconstruct_interrupted_has_no_summary(world, tmp_path):
    out = tmp_path / "rec"
    code, err = _interrupt(_reconstruct(world, out=out), "surfels_3dgs.ply", signal.SIGTERM, tmp_path)
    _assert_interrupted(code, err, "reconstruct", signal.SIGTERM)
    # reconstruction.json is written last: its absence tells a reader the run did not finish.
    assert (out / "surfels.ply").is_file() and not (out / "reconstruction.json").exists()
    assert len(load_ply(out / "surfels.ply")) == 2 * SIZE * SIZE
    no_temporaries(out)


def test_eval_interrupted_has_no_metrics(world, tmp_path):
    out = tmp_path / "eval"
    code, err = _interrupt(_eval(world, out, "--factors", "1"), "table.txt", signal.SIGINT, tmp_path)
    _assert_interrupted(code, err, "eval", signal.SIGINT)
    assert (out / "per_scene.csv").is_file() and not (out / "metrics.json").exists()  # metrics.json: the marker
    no_temporaries(out)


def test_train_interrupted_while_checkpointing_keeps_the_last_checkpoint(tmp_path):
    out = tmp_path / "run"
    argv = _train(out, steps=2)
    # The second checkpoint's weights are held: step 1 is published, step 2 is being written.
    ready = tmp_path / "ready"
    proc = subprocess.Popen(
        [sys.executable, "-c", _SECOND_WRITE, str(ready), *argv, "--quiet"], stderr=subprocess.PIPE, text=True
    )
    deadline = time.monotonic() + 240
    while not ready.exists():
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()[1]
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    _assert_interrupted(proc.returncode, err, "train", signal.SIGTERM)
    assert [p.name for p in list_checkpoints(out)] == ["step-00000001"]
    verify_checkpoint(out / "checkpoints" / "step-00000001")
    no_temporaries(out)


# Holds the second write of model.safetensors (the step-2 checkpoint) open, as helpers/slow_writer.py does the first.
_SECOND_WRITE = """
import sys, time
from pathlib import Path
from surfsplat.utils import atomic
from surfsplat.cli import main
ready, seen, real = Path(sys.argv[1]), [], atomic._fsync
def held(path):
    if "model.safetensors" in path.name:
        seen.append(path)
        if len(seen) == 2:
            ready.write_text(str(path))
            time.sleep(120)
    real(path)
atomic._fsync = held
sys.exit(main(sys.argv[2:]))
"""


def test_demo_interrupted_while_writing_its_data(tmp_path):
    out = tmp_path / "demo"
    code, err = _interrupt(["demo", "--quick", "--out", str(out)], ".torch", signal.SIGINT, tmp_path)
    _assert_interrupted(code, err, "demo", signal.SIGINT)
    assert not list(out.rglob("*.torch")) and not (out / "metrics.json").exists()
    no_temporaries(out)


# -------------------------------------------------------------------------------------------- full disk
def test_full_disk_is_one_line_naming_the_file(world, tmp_path, capsys, monkeypatch):
    """ENOSPC as a file system reports it when the data reaches the disk: the export stops with one
    line naming the file, which is absent; the files written before it are intact."""
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        if os.readlink(f"/proc/self/fd/{fd}").endswith(".mesh.ply.tmp"):
            raise OSError(errno.ENOSPC, "No space left on device")
        real_fsync(fd)

    if not Path("/proc/self/fd").is_dir():
        pytest.skip("needs /proc to name the file being synced")
    monkeypatch.setattr(os, "fsync", fsync)
    out = tmp_path / "out"
    argv = _export(world, None, out, "--formats", "ply", "mesh", "--frames", "2", "--mesh-resolution", "16")
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [
        f"surfsplat export: error: {out / 'mesh.ply'}: cannot write (no space left on the device); "
        "nothing was written under this name"
    ]
    assert not (out / "mesh.ply").exists() and len(load_ply(out / "surfels.ply")) == len(load_ply(world.ply))
    no_temporaries(out)


def test_full_disk_while_checkpointing_keeps_the_last_checkpoint(tmp_path, capsys, monkeypatch):
    from surfsplat.train import checkpoint

    real, calls = checkpoint.save_file, [0]

    def save_file(*args, **kwargs):  # the training state of the second checkpoint meets a full disk
        calls[0] += 1
        if calls[0] == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(*args, **kwargs)

    monkeypatch.setattr(checkpoint, "save_file", save_file)
    out = tmp_path / "run"
    assert main(_train(out, steps=2)) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"surfsplat train: error: {out / 'checkpoints' / 'step-00000002'}: cannot write (no space left on the "
        "device); nothing was written under this name"
    ]
    assert [p.name for p in list_checkpoints(out)] == ["step-00000001"]
    verify_checkpoint(out / "checkpoints" / "step-00000001")
    no_temporaries(out)


# ----------------------------------------------------------------------------------- degenerate scenes
def _all_finite_outputs(out: Path) -> None:
    """Every PLY reads back (the reader refuses NaN/inf), the mesh's vertices and the JSON are finite."""
    for ply in out.glob("surfels*.ply"):
        load_ply(ply)
    if (out / "mesh.ply").exists():
        assert bool(torch.isfinite(load_mesh(out / "mesh.ply").vertices).all())
    for doc in out.glob("*.json"):
        constants: list[str] = []  # NaN, Infinity: Python's JSON writer spells non-finite floats so
        json.loads(doc.read_text(), parse_constant=constants.append)
        assert not constants, (doc, constants)


@pytest.mark.parametrize("scene", ["flat-textureless", "coincident-cameras"])
def test_degenerate_scene_reconstructs_without_nan(world, tmp_path, scene):
    images, cameras = list(world.images), world.cameras
    if scene == "flat-textureless":  # nothing to match: one grey everywhere
        images = [tmp_path / "grey0.png", tmp_path / "grey1.png"]
        for path in images:
            iio.imwrite(path, np.full((SIZE, SIZE, 3), 128, np.uint8))
        doc = json.loads(world.cameras.read_text())
        doc["frames"][0]["name"], doc["frames"][1]["name"] = "grey0.png", "grey1.png"
    else:  # the same camera twice: no baseline at all
        doc = json.loads(world.cameras.read_text())
        doc["frames"][1]["c2w"] = doc["frames"][0]["c2w"]
    cameras = tmp_path / "cams.json"
    cameras.write_text(json.dumps(doc))
    out = tmp_path / "out"
    argv = _reconstruct(world, images=images, cameras=cameras, out=out)
    argv += ["--formats", "ply", "renders", "mesh", "--frames", "2", "--mesh-resolution", "16"]
    assert main(argv) == 0
    _all_finite_outputs(out)


def test_zero_depth_surfels_export_without_nan(world, tmp_path):
    """Surfels at the camera centre (depth 0) and of zero size: renders and PLY stay finite, and the
    mesh, with no depth to fuse, is refused plainly rather than written with NaN."""
    from surfsplat import Gaussians
    from surfsplat.data.cameras import load_cameras
    from surfsplat.export.flow import ExportOptions, export_reconstruction
    from surfsplat.utils.checks import SurfSplatInputError

    cams = load_cameras(world.ply_cameras)
    n = 64
    centre = cams.cameras.c2w[0, :3, 3].float()
    g = Gaussians(
        means=centre.expand(n, 3).clone(),
        quats=torch.tensor([1.0, 0, 0, 0]).expand(n, 4).clone(),
        scales=torch.zeros(n, 2),
        opacities=torch.full((n,), 0.5),
        sh=torch.zeros(n, 3, 1),
    )
    options = ExportOptions(formats=("ply", "renders"), path_frames=2, progress=False)
    export_reconstruction(g, cams.cameras.to(torch.float32), cams.width, cams.height, tmp_path, options)
    _all_finite_outputs(tmp_path)
    mesh = ExportOptions(formats=("mesh",), path_frames=2, mesh_resolution=16, progress=False)
    with pytest.raises(SurfSplatInputError, match="no valid depth sample to fuse"):
        export_reconstruction(g, cams.cameras.to(torch.float32), cams.width, cams.height, tmp_path / "m", mesh)
    assert not (tmp_path / "m" / "mesh.ply").exists()
    for png in (tmp_path / "renders").glob("*.png"):
        assert iio.imread(png).shape[:2] == (cams.height, cams.width)


# ------------------------------------------------------------------------------------------------ viewer
def _get(port: int, path: str) -> int:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.putrequest("GET", path, skip_accept_encoding=True)  # the path goes out exactly as written
    conn.endheaders()
    status = conn.getresponse().status
    conn.close()
    return status


def test_viewer_serves_only_its_page(world, tmp_path, caplog):
    from surfsplat.viewer import SurfelViewer, load_viewer_scene

    secret = world.root / "secret.txt"
    secret.write_text("not for the browser")
    viewer = SurfelViewer(port=0)
    try:
        viewer.show(load_viewer_scene(world.ply, viewer.progress))
        port = viewer.server.get_port()
        assert viewer.url.startswith("http://127.0.0.1:")
        assert _get(port, "/") == 200
        for path in (
            "/../../../../../../etc/passwd",
            "/%2e%2e/%2e%2e/%2e%2e/%2e%2e/etc/passwd",
            "/..%2f..%2f..%2f..%2fetc%2fpasswd",
            "/..\\..\\..\\..\\etc\\passwd",
            str(secret),
            "/" + str(world.ply),
            "/" + os.path.relpath(secret, "/"),
        ):
            assert _get(port, path) == 404, path
    finally:
        viewer.stop()
    with caplog.at_level(logging.WARNING, logger="surfsplat.viewer.app"):
        viewer = SurfelViewer(host="127.0.0.1", port=0)
        viewer.stop()
        assert not caplog.records  # the default stays quiet
        viewer = SurfelViewer(host="0.0.0.0", port=0)
        viewer.stop()
    assert any("reachable from other machines" in r.getMessage() for r in caplog.records)


def test_absurd_distortion_is_one_line_exit_2(world, tmp_path, capsys, monkeypatch):
    """A lens whose distortion leaves no valid region (k1 50, k2 -80 folds the image): one line naming the
    model, before anything is read or written."""
    monkeypatch.chdir(tmp_path)
    model = _colmap_cameras(tmp_path, world, f"OPENCV {SIZE} {SIZE} 60 60 32 32 50 -80 0 0")
    code = main(_reconstruct(world, cameras=model, out=tmp_path / "o"))
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "OPENCV" in err, err
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------- processed captures, in a real process
# Captures as other tools leave them, broken one way each, built from the repository's distorted DTU fixture
# (photos, its COLMAP model in text and binary, its nerfstudio transforms.json and its fisheye one) and run as
# a user runs them: `python -m surfsplat ...` in its own process. Each is exit code 2, stderr exactly one line
# naming the file and the field or value (no traceback), and the output folder never made.
DISTORTED = Path(__file__).resolve().parents[1] / "data" / "distorted"
DTU = Path(__file__).resolve().parents[1] / "data" / "dtu_scan24" / "images_16"


def _photos(tmp: Path) -> Path:
    return Path(shutil.copytree(DISTORTED / "images", tmp / "images"))


def _text_model(tmp: Path, camera_line: str) -> Path:
    """The fixture's COLMAP text model with its one camera replaced by `camera_line` ("MODEL W H params")."""
    model = Path(shutil.copytree(DISTORTED / "sparse" / "text", tmp / "sparse" / "0"))
    (model / "cameras.txt").write_text(f"# one camera\n1 {camera_line}\n")
    return model


def _binary_model(tmp: Path, model_id: int | None = None, k1: float | None = None) -> Path:
    """The fixture's binary COLMAP model (one OPENCV camera) with its model id or its k1 overwritten:
    cameras.bin is a uint64 count, then per camera int32 id, int32 model id, uint64 width, uint64 height and
    the parameters as float64 (COLMAP's WriteCamerasBinary), k1 the fifth of OPENCV's."""
    model = Path(shutil.copytree(DISTORTED / "sparse" / "0", tmp / "sparse" / "0"))
    data = bytearray((model / "cameras.bin").read_bytes())
    if model_id is not None:
        struct.pack_into("<i", data, 8 + 4, model_id)
    if k1 is not None:
        struct.pack_into("<d", data, 8 + 24 + 4 * 8, k1)
    (model / "cameras.bin").write_bytes(bytes(data))
    return model


def _transforms(tmp: Path, fisheye: bool = False, **changes) -> Path:
    """The fixture's transforms.json (or its fisheye one) with top-level keys changed, written beside the photos."""
    source = DISTORTED / ("fisheye" if fisheye else "") / "transforms.json"
    doc = json.loads(source.read_text())
    doc.update(changes)
    path = tmp / "transforms.json"
    path.write_text(json.dumps(doc))  # NaN is written as the token JSON readers accept
    return path


def _no_photos_left(tmp: Path) -> Path:
    doc = json.loads((DISTORTED / "transforms.json").read_text())
    for frame in doc["frames"]:
        frame["file_path"] = "left_out/" + Path(frame["file_path"]).name
    path = tmp / "transforms.json"
    path.write_text(json.dumps(doc))
    return path


# (id, cameras from tmp, words the one line must contain)
CAPTURE_CASES = [
    (
        "colmap-text-nan-distortion",
        lambda t: _text_model(t, "OPENCV 100 75 190 190 51.5 38.7 nan 0.1 0.002 -0.001"),
        ["sparse/0/cameras.txt:2: camera 1: camera model OPENCV: parameter k1 is NaN"],
    ),
    (
        "colmap-binary-absurd-distortion",
        lambda t: _binary_model(t, k1=1e6),
        ["sparse/0/cameras.bin: camera 1: camera model OPENCV (fx 190, fy 190", "k1 1e+06", "no pinhole holds"],
    ),
    (
        "colmap-text-fisheye-no-valid-region",
        lambda t: _text_model(t, "OPENCV_FISHEYE 100 75 190 190 51.5 38.7 -5 0 0 0"),
        ["cameras.txt: camera 1: camera model OPENCV_FISHEYE", "k1 -5", "no valid undistorted region"],
    ),
    (
        "colmap-text-fisheye-beyond-90-degrees",
        lambda t: _text_model(t, "OPENCV_FISHEYE 100 75 20 20 51.5 38.7 0 0 0 0"),
        ["cameras.txt: camera 1: camera model OPENCV_FISHEYE (fx 20", "sees 182.5 degrees off the axis"],
    ),
    (
        "colmap-binary-model-id-11",
        lambda t: _binary_model(t, model_id=11),
        ["sparse/0/cameras.bin: camera 1 has camera model id 11, which is not supported"],
    ),
    (
        "colmap-text-unknown-model",
        lambda t: _text_model(t, "DIVISION 100 75 190 51.5 38.7 0.1"),
        ["cameras.txt:2: camera 1 has camera model DIVISION, which is not supported"],
    ),
    (
        "transforms-nan-distortion",
        lambda t: _transforms(t, k1=float("nan")),
        ["transforms.json: field 'k1' must be a finite number, got nan"],
    ),
    (
        "transforms-absurd-distortion",
        lambda t: _transforms(t, k2=-1e6),
        ["transforms.json: frame 0: camera model OPENCV (fx 190", "k2 -1e+06"],
    ),
    (
        "transforms-fisheye-no-valid-region",
        lambda t: _transforms(t, fisheye=True, k1=-5.0),
        ["transforms.json: frame 0: camera model OPENCV_FISHEYE", "k1 -5", "no valid undistorted region"],
    ),
    (
        "transforms-unknown-camera-model",
        lambda t: _transforms(t, camera_model="EQUIRECTANGULAR"),
        ["transforms.json: field 'camera_model' is 'EQUIRECTANGULAR', which is not supported"],
    ),
    (
        "transforms-every-photo-missing",
        _no_photos_left,
        ["transforms.json: every photo listed in it is missing (5 frames"],
    ),
]


def _surfsplat(args: list[str], cwd: Path, block: str | None = None) -> subprocess.CompletedProcess:
    """`python -m surfsplat ARGS` in its own process; `block` names a module the process cannot import (an
    optional extra that is not installed)."""
    if block is None:
        command = [sys.executable, "-m", "surfsplat", *args]
    else:
        run = f"import runpy, sys; sys.modules[{block!r}] = None; runpy.run_module('surfsplat', run_name='__main__')"
        command = [sys.executable, "-c", run, *args]
    return subprocess.run(command, cwd=cwd, capture_output=True, text=True, timeout=300)


def _assert_one_line(proc: subprocess.CompletedProcess, command: str, needles: list[str]) -> None:
    err = proc.stderr.strip()
    assert proc.returncode == 2, (proc.returncode, err)
    assert "Traceback" not in err, err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"surfsplat {command}: error: "), err
    for needle in needles:
        assert needle in lines[0], (needle, err)


@pytest.mark.parametrize("make, needles", [c[1:] for c in CAPTURE_CASES], ids=[c[0] for c in CAPTURE_CASES])
def test_processed_capture_case_in_a_process_is_one_line_exit_2_nothing_written(make, needles, tmp_path):
    photos = _photos(tmp_path)
    cameras = make(tmp_path)
    before = _tree(tmp_path)
    out = tmp_path / "out"
    args = ["reconstruct", "--images", str(photos), "--cameras", str(cameras), "--out", str(out)]
    proc = _surfsplat([*args, "--size", "32", "48", "--formats", "ply", "--no-progress", "--device", "cpu"], tmp_path)
    _assert_one_line(proc, "reconstruct", needles)
    assert not out.exists()
    assert _tree(tmp_path) == before  # nothing made or changed beside it either


@pytest.mark.parametrize("command", ["reconstruct", "poses"])
def test_heic_without_the_extra_in_a_process_is_one_line_exit_2_nothing_written(tmp_path, command):
    pillow_heif = pytest.importorskip("pillow_heif", reason="pillow-heif (the 'heic' extra) makes the HEIC fixture")
    from PIL import Image

    pillow_heif.register_heif_opener()
    photos = []
    for name in ("000000.png", "000001.png"):
        path = tmp_path / name.replace(".png", ".heic")
        Image.open(DTU / name).convert("RGB").save(path, "HEIF", quality=90)
        photos.append(str(path))
    before = _tree(tmp_path)
    out = tmp_path / ("out" if command == "reconstruct" else "cameras.json")
    if command == "reconstruct":
        args = ["reconstruct", "--images", *photos, "--out", str(out), "--formats", "ply", "--no-progress"]
    else:
        args = ["poses", *photos, "--out", str(out)]
    proc = _surfsplat(args, tmp_path, block="pillow_heif")
    _assert_one_line(proc, command, ["000000.heic", "pip install 'surfsplat[heic]'"])
    assert not out.exists()
    assert _tree(tmp_path) == before
