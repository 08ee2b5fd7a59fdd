"""Converters into chunks, each checked by reading the chunks back through the RealEstate10K path."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from surfsplat.commands import convert as convert_command
from surfsplat.data import example_to_scene, load_example, load_scene, read_index
from surfsplat.data.convert import convert
from surfsplat.utils.checks import SurfSplatInputError
from tests.helpers.data import random_cameras, write_colmap_model, write_images

_GL = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


def _dl3dv_scene(root: Path, name: str, n: int, nested: bool) -> torch.Tensor:
    """A DL3DV scene: nerfstudio transforms.json for 64x48 photos, images_8 at 8x6; returns c2w."""
    base = root / name / "nerfstudio" if nested else root / name
    cams = random_cameras(n, hash(name) % 100, 64, 48)
    files = [f"frame_{i + 1:05d}.png" for i in range(n)]
    write_images(base / "images_8", files, 8, 6, seed=len(name))
    K = cams.K[0]
    meta = {
        "w": 64,
        "h": 48,
        "fl_x": float(K[0, 0]),
        "fl_y": float(K[1, 1]),
        "cx": float(K[0, 2]),
        "cy": float(K[1, 2]),
        "k1": 0,
        "k2": 0,
        "p1": 0,
        "p2": 0,
        "camera_model": "OPENCV",
        # Frames listed out of name order: the converter keeps the JSON order.
        "frames": [
            {"file_path": f"images/{files[i]}", "transform_matrix": (cams.c2w[i] @ _GL).tolist()}
            for i in reversed(range(n))
        ],
    }
    (base / "transforms.json").write_text(json.dumps(meta))
    return cams.c2w.flip(0), cams.scaled(1 / 8).K.flip(0)


def test_dl3dv_converter(tmp_path: Path) -> None:
    src = tmp_path / "dl3dv"
    c2w_a, K_a = _dl3dv_scene(src, "aaaa", 4, nested=True)
    c2w_b, _ = _dl3dv_scene(src, "bbbb", 3, nested=False)
    report = convert("dl3dv", src, tmp_path / "out")
    assert report.written == ["aaaa", "bbbb"] and not report.skipped
    ex = load_example(tmp_path / "out", "aaaa")
    assert ex["timestamps"].tolist() == [4, 3, 2, 1]  # frame numbers, JSON order
    # Image files are copied byte for byte.
    assert (
        ex["images"][0].numpy().tobytes() == (src / "aaaa" / "nerfstudio" / "images_8" / "frame_00004.png").read_bytes()
    )
    scene = example_to_scene(ex)
    torch.testing.assert_close(scene.cameras.c2w.double(), c2w_a, atol=1e-5, rtol=0)
    torch.testing.assert_close(scene.cameras.K.double(), K_a, atol=1e-4, rtol=1e-6)
    scene_b = example_to_scene(load_example(tmp_path / "out", "bbbb"))
    torch.testing.assert_close(scene_b.cameras.c2w.double(), c2w_b, atol=1e-5, rtol=0)


def test_dl3dv_converter_undistorts_photos_with_a_lens(tmp_path: Path, monkeypatch) -> None:
    """A DL3DV scene whose transforms.json has an OPENCV lens: the chunk holds the photos undistorted to
    the pinhole COLMAP's undistorter chooses, and that pinhole's K."""
    from surfsplat.data.images import decode_image_bytes, read_image
    from surfsplat.geometry.lens import Lens
    from tests.helpers.lenses import colmap_camera, install_lens_references, reference_pinhole, reference_undistort

    install_lens_references(monkeypatch)
    _dl3dv_scene(tmp_path / "dl3dv", "cccc", 2, nested=False)
    meta = json.loads((tmp_path / "dl3dv" / "cccc" / "transforms.json").read_text())
    meta.update(k1=-0.1, k2=0.05)
    (tmp_path / "dl3dv" / "cccc" / "transforms.json").write_text(json.dumps(meta))
    convert("dl3dv", tmp_path / "dl3dv", tmp_path / "out")
    ex = load_example(tmp_path / "out", "cccc")
    lens = Lens("OPENCV", 64, 48, (meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"], -0.1, 0.05, 0.0, 0.0))
    camera = colmap_camera(lens)  # the photos are images_8: the lens rescaled as COLMAP does
    camera.rescale(8, 6)
    small = Lens("OPENCV", 8, 6, tuple(camera.params))
    pinhole = reference_pinhole(small)
    scene = example_to_scene(ex)
    assert scene.images.shape[2:] == (pinhole.height, pinhole.width)
    fx, fy, cx, cy = pinhole.params
    expected = torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(scene.cameras.K[0].double(), expected, atol=1e-4, rtol=1e-6)
    photo, _ = read_image(tmp_path / "dl3dv" / "cccc" / "images_8" / "frame_00002.png", background=None)
    stored = decode_image_bytes(ex["images"][0], "chunk")
    assert (stored - reference_undistort(photo, small, pinhole)).abs().mean() < 2 / 255


def _scannet_scene(root: Path, name: str, n: int, bad: set[int]) -> torch.Tensor:
    cams = random_cameras(n, 7, 16, 12)
    scene = root / name
    write_images(scene / "color", [f"{i}.jpg" for i in range(n)], 16, 12, seed=3)
    (scene / "depth").mkdir()
    for i in range(n):
        Image.fromarray(np.full((6, 8), 1000 + 10 * i, np.uint16)).save(scene / "depth" / f"{i}.png")
    (scene / "pose").mkdir()
    for i in range(n):
        pose = np.full((4, 4), -np.inf) if i in bad else cams.c2w[i].numpy()
        np.savetxt(scene / "pose" / f"{i}.txt", pose)
    (scene / "intrinsic").mkdir()
    K4 = np.eye(4)
    K4[:3, :3] = cams.K[0].numpy()
    np.savetxt(scene / "intrinsic" / "intrinsic_color.txt", K4)
    return cams.c2w


def test_scannet_converter_skips_invalid_poses_and_keeps_depth(tmp_path: Path) -> None:
    c2w = _scannet_scene(tmp_path / "scans", "scene0001_00", 5, bad={2})
    report = convert("scannet", tmp_path / "scans", tmp_path / "out")
    assert report.written == ["scene0001_00"]
    assert report.skipped == [f"{tmp_path / 'scans' / 'scene0001_00'}: 1 frames with an invalid (inf/NaN) pose"]
    ex = load_example(tmp_path / "out", "scene0001_00")
    assert ex["timestamps"].tolist() == [0, 1, 3, 4]
    scene = example_to_scene(ex)
    torch.testing.assert_close(scene.cameras.c2w.double(), c2w[[0, 1, 3, 4]], atol=1e-5, rtol=0)
    # Depth PNGs (millimetres) come back in metres, resized to the colour image.
    assert scene.depths.shape == (4, 1, 12, 16)
    torch.testing.assert_close(scene.depths[2, 0], torch.full((12, 16), 1.030))


@pytest.mark.parametrize("fmt", ["blender", "colmap"])
def test_scene_converters_match_load_scene(tmp_path: Path, fmt: str) -> None:
    src = tmp_path / "scene"
    cams = random_cameras(3, 4, 12, 10)
    names = ["a.png", "b.png", "c.png"]
    if fmt == "colmap":
        write_images(src / "images", names, 12, 10, seed=5)
        write_colmap_model(src / "sparse" / "0", cams, names, 12, 10, binary=True)
    else:
        write_images(src, names, 12, 10, seed=5)
        meta = {
            "camera_angle_x": 0.7,
            "frames": [{"file_path": n, "transform_matrix": (cams.c2w[i] @ _GL).tolist()} for i, n in enumerate(names)],
        }
        (src / "transforms.json").write_text(json.dumps(meta))
    convert(fmt, src, tmp_path / "out")
    direct = load_scene(src)
    back = example_to_scene(load_example(tmp_path / "out", "scene"))
    assert torch.equal(back.images, direct.images)  # PNG: lossless
    torch.testing.assert_close(back.cameras.c2w, direct.cameras.c2w, atol=1e-5, rtol=0)
    torch.testing.assert_close(back.cameras.K, direct.cameras.K, atol=1e-4, rtol=1e-6)


@pytest.mark.slow
def test_dtu_converter_on_scan24(samples, tmp_path: Path) -> None:
    src = tmp_path / "scan24"
    src.mkdir()
    for name in ("cameras_sphere.npz", samples.dtu_images):
        (src / name).symlink_to(samples.root / "dtu_scan24" / name)
    args = argparse.Namespace(
        format="dtu",
        src=str(src),
        out=str(tmp_path / "out"),
        images=None,
        image_format="jpeg",
        quality=95,
        chunk_mb=100.0,
        frame_step=1,
        skip_bad=False,
        append=False,
    )
    assert convert_command.run(args) == 0
    assert list(read_index(tmp_path / "out")) == ["scan24"]
    back = example_to_scene(load_example(tmp_path / "out", "scan24"))
    direct = load_scene(src)
    assert back.images.shape == (samples.dtu_views, 3, *samples.dtu_size)
    torch.testing.assert_close(back.cameras.c2w, direct.cameras.c2w, atol=1e-5, rtol=0)
    # The chunk stores K as fx/W, cx/W, ...: the tiny skew of DTU's calibration is dropped.
    torch.testing.assert_close(
        back.cameras.K[:, [0, 1, 0, 1], [0, 1, 2, 2]],
        direct.cameras.K[:, [0, 1, 0, 1], [0, 1, 2, 2]],
        atol=1e-3,
        rtol=1e-6,
    )


def test_command_lists_every_converter() -> None:
    from surfsplat.data.convert import CONVERTERS

    assert convert_command.FORMATS == CONVERTERS


def test_converter_errors(tmp_path: Path) -> None:
    with pytest.raises(SurfSplatInputError, match="format: expected one of"):
        convert("nerf", tmp_path, tmp_path / "out")
    with pytest.raises(FileNotFoundError, match="neither a DL3DV scene nor a folder of them"):
        convert("dl3dv", tmp_path, tmp_path / "out")
