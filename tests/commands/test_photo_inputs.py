"""Phone photos at the command line: a HEIC without the `heic` extra is one line naming the extra,
exit 2 and nothing written; a photo with a damaged EXIF block still reconstructs, with one warning
line naming it; a portrait photo stored sideways (EXIF orientation 6) is read upright."""

from __future__ import annotations

import io
import json
import logging
import struct
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from surfsplat.cli import main
from surfsplat.data.cameras import save_cameras
from surfsplat.data.images import HEIF_EXTRA
from surfsplat.data.synthetic import make_scene, make_trajectory, render_synthetic

SIZE = 32


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    """Two 32x32 renders of a procedural room (uint8) and their camera file."""
    root = tmp_path_factory.mktemp("photos")
    scene = make_scene(5)
    cams = make_trajectory(scene, torch.Generator().manual_seed(0)).cameras(torch.tensor([0.0, 0.5]), SIZE, SIZE)
    images = render_synthetic(scene, cams, SIZE, SIZE).image
    arrays = [(im.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8) for im in images]
    save_cameras(root / "cameras.json", cams, SIZE, SIZE, ["a.jpg", "b.jpg"], near=0.5, far=15.0)
    return arrays, root / "cameras.json"


def _tree(folder: Path) -> set[str]:
    return {str(p) for p in folder.rglob("*")}


def _heic(path: Path, array: np.ndarray) -> Path:
    pillow_heif = pytest.importorskip("pillow_heif", reason="pillow-heif (the 'heic' extra) is not installed")
    pillow_heif.register_heif_opener()
    Image.fromarray(array).save(path, "HEIF", quality=90)
    return path


@pytest.mark.parametrize("command", ["reconstruct", "poses"])
def test_heic_without_the_extra_is_one_line_exit_2_nothing_written(views, tmp_path, capsys, monkeypatch, command):
    arrays, cameras = views
    photos = [_heic(tmp_path / "a.heic", arrays[0]), _heic(tmp_path / "b.heic", arrays[1])]
    monkeypatch.setitem(sys.modules, "pillow_heif", None)  # the extra uninstalled: import pillow_heif fails
    monkeypatch.chdir(tmp_path)
    before = _tree(tmp_path)
    if command == "reconstruct":
        argv = ["reconstruct", "--images", *map(str, photos), "--cameras", str(cameras), "--out", str(tmp_path / "o")]
        argv += ["--formats", "renders", "--no-progress"]
    else:
        argv = ["poses", *map(str, photos), "--out", str(tmp_path / "c.json")]
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert err == [f"surfsplat {command}: error: {photos[0]}: {HEIF_EXTRA}"]
    assert _tree(tmp_path) == before


def test_heic_photos_reconstruct_with_the_extra(views, tmp_path, capsys):
    arrays, cameras = views
    photos = [_heic(tmp_path / "a.heic", arrays[0]), _heic(tmp_path / "b.heic", arrays[1])]
    out = tmp_path / "o"
    argv = ["reconstruct", "--images", *map(str, photos), "--cameras", str(cameras), "--out", str(out)]
    assert main([*argv, "--formats", "renders", "--no-progress"]) == 0, capsys.readouterr().err
    summary = json.loads((out / "reconstruction.json").read_text())
    assert [Path(s).name for s in summary["images"]] == ["a.heic", "b.heic"]
    assert (out / "renders" / "view01_color.png").stat().st_size > 0


def _damaged_exif_jpeg(path: Path, array: np.ndarray) -> Path:
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, "JPEG", quality=95)
    data = buffer.getvalue()
    payload = b"Exif\x00\x00MM\x00\x2a\x00\x00\x00\x08\x00\x05\x01\x12\x00\x03"  # one entry promised, 4 bytes
    path.write_bytes(data[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + data[2:])
    return path


def test_photo_with_a_damaged_exif_block_reconstructs_with_one_warning(views, tmp_path, capsys, caplog):
    arrays, cameras = views
    photos = [_damaged_exif_jpeg(tmp_path / "a.jpg", arrays[0]), tmp_path / "b.jpg"]
    Image.fromarray(arrays[1]).save(photos[1], quality=95)
    out = tmp_path / "o"
    argv = ["reconstruct", "--images", *map(str, photos), "--cameras", str(cameras), "--out", str(out)]
    with caplog.at_level(logging.WARNING, logger="surfsplat"):
        assert main([*argv, "--formats", "renders", "--no-progress"]) == 0, capsys.readouterr().err
    warned = [r.getMessage() for r in caplog.records if "EXIF" in r.getMessage()]
    assert len(warned) == 1, warned
    assert warned[0].startswith(f"{photos[0]}: damaged EXIF block (") and "read without an orientation" in warned[0]
    assert (out / "renders" / "view00_color.png").is_file()


def test_portrait_stored_sideways_is_reconstructed_upright(views, tmp_path, capsys):
    """The same two views, one stored turned with EXIF orientation 6: the capture is the upright one,
    so the camera file of the upright photos fits and the renders are the plain run's, byte for byte."""
    arrays, cameras = views
    plain = [tmp_path / "a.png", tmp_path / "b.png"]
    for path, array in zip(plain, arrays):
        Image.fromarray(array).save(path)
    exif = Image.Exif()
    exif[0x0112] = 6
    turned = tmp_path / "t" / "b.png"
    turned.parent.mkdir()
    Image.fromarray(np.rot90(arrays[1], 1).copy()).save(turned, exif=exif.tobytes())  # stored = upright turned CCW
    runs = {}
    for name, photos in (("plain", plain), ("turned", [plain[0], turned])):
        out = tmp_path / name
        argv = ["reconstruct", "--images", *map(str, photos), "--cameras", str(cameras), "--out", str(out)]
        assert main([*argv, "--formats", "renders", "--no-progress"]) == 0, capsys.readouterr().err
        runs[name] = [
            (out / "renders" / f"view0{k}_{what}.png").read_bytes() for k in (0, 1) for what in ("color", "depth")
        ]
    assert runs["plain"] == runs["turned"]
