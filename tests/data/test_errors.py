"""A corpus of deliberately broken inputs: each gets one specific error naming the file and field,
or (dataset iteration) is skipped and counted with its reason."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from surfsplat.data import (
    BoundedViewSampler,
    BoundedViewSamplerConfig,
    ChunkDataset,
    ChunkDatasetConfig,
    EvaluationIndex,
    load_example,
    load_scene,
    read_chunk,
    write_chunks,
)
from surfsplat.utils.checks import SurfSplatInputError
from tests.helpers.data import make_example, random_cameras, write_colmap_model


# ------------------------------------------------------------------------------ scene builders
def _llff(root: Path, n: int = 3, size: tuple[int, int] = (16, 12)) -> Path:
    """A valid LLFF capture: poses_bounds.npy for 64x48 photos and images_4 at 16x12."""
    w, h = size
    cams = random_cameras(n, 0, 64, 48)
    poses = cams.to_llff(64, 48)
    poses[:, 2, 4] = 50.0
    bounds = np.tile([[1.0, 10.0]], (n, 1))
    np.save(root / "poses_bounds.npy", np.concatenate([poses.reshape(n, 15).numpy(), bounds], 1))
    (root / "images_4").mkdir()
    rng = np.random.default_rng(0)
    for i in range(n):
        Image.fromarray(rng.integers(0, 256, (h, w, 3), dtype=np.uint8)).save(root / "images_4" / f"im{i}.png")
    return root


def _edit_poses(root: Path, fn: Callable[[np.ndarray], None]) -> None:
    arr = np.load(root / "poses_bounds.npy")
    fn(arr)
    np.save(root / "poses_bounds.npy", arr)


def _blender(root: Path, meta_fn: Callable[[dict], None]) -> Path:
    cams = random_cameras(2, 1, 8, 8)
    (root / "train").mkdir()
    for i in range(2):
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(root / "train" / f"r_{i}.png")
    c2w_gl = cams.c2w @ torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
    meta = {
        "camera_angle_x": 0.8,
        "frames": [{"file_path": f"train/r_{i}", "transform_matrix": c2w_gl[i].tolist()} for i in range(2)],
    }
    meta_fn(meta)
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


# Each case: (id, build(tmp) -> path to load, fragment that must appear in the message).
def _case_truncated_png(tmp: Path) -> Path:
    root = _llff(tmp)
    data = (root / "images_4" / "im1.png").read_bytes()
    (root / "images_4" / "im1.png").write_bytes(data[: len(data) // 2])  # header intact, pixel data cut
    return root


def _case_not_an_image(tmp: Path) -> Path:
    root = _llff(tmp)
    (root / "images_4" / "im2.png").write_text("this is not a PNG")
    return root


def _case_nan_camera(tmp: Path) -> Path:
    root = _llff(tmp)
    _edit_poses(root, lambda a: a.__setitem__((1, 3), np.nan))
    return root


def _case_inf_camera(tmp: Path) -> Path:
    root = _llff(tmp)
    _edit_poses(root, lambda a: a.__setitem__((2, 7), np.inf))
    return root


def _case_non_rotation(tmp: Path) -> Path:
    root = _llff(tmp)

    def scale(a: np.ndarray) -> None:
        a[1, [0, 1, 2, 5, 6, 7, 10, 11, 12]] *= 1.5  # R -> 1.5 R

    _edit_poses(root, scale)
    return root


def _case_zero_focal(tmp: Path) -> Path:
    root = _llff(tmp)
    _edit_poses(root, lambda a: a.__setitem__((0, 14), 0.0))
    return root


def _case_size_mismatch(tmp: Path) -> Path:
    root = _llff(tmp)
    Image.fromarray(np.zeros((12, 15, 3), np.uint8)).save(root / "images_4" / "im0.png")
    return root


def _case_size_mismatch_uniform(tmp: Path) -> Path:
    # All images 15x12: not a uniform downscale of 64x48.
    root = _llff(tmp, size=(15, 12))
    return root


def _case_count_mismatch(tmp: Path) -> Path:
    root = _llff(tmp)
    (root / "images_4" / "im2.png").unlink()
    return root


def _case_dtu_missing_key(tmp: Path) -> Path:
    P = np.eye(4)
    P[:3, :3] = [[100, 0, 8], [0, 100, 6], [0, 0, 1]]
    P[2, 3] = 3
    np.savez(tmp / "cameras_sphere.npz", world_mat_0=P, world_mat_2=P, scale_mat_0=np.eye(4), scale_mat_2=np.eye(4))
    (tmp / "image").mkdir()
    return tmp


def _case_dtu_singular(tmp: Path) -> Path:
    (tmp / "image").mkdir()
    Image.fromarray(np.zeros((12, 16, 3), np.uint8)).save(tmp / "image" / "000.png")
    P = np.zeros((4, 4))
    P[3, 3] = 1
    np.savez(tmp / "cameras_sphere.npz", world_mat_0=P, scale_mat_0=np.eye(4))
    return tmp


def _case_blender_no_frames(tmp: Path) -> Path:
    return _blender(tmp, lambda m: m.pop("frames"))


def _case_blender_no_matrix(tmp: Path) -> Path:
    return _blender(tmp, lambda m: m["frames"][1].pop("transform_matrix"))


def _case_blender_no_intrinsics(tmp: Path) -> Path:
    return _blender(tmp, lambda m: m.pop("camera_angle_x"))


def _case_blender_r8_term(tmp: Path) -> Path:
    # nerfstudio's k4 of a perspective lens is an r^8 term, which no COLMAP model has
    return _blender(tmp, lambda m: m.update({"camera_model": "OPENCV", "k1": 0.1, "k4": 0.01}))


def _case_blender_frame_r8_term(tmp: Path) -> Path:
    # the same r^8 term held by one frame: the error names that frame, not the file's top level
    return _blender(tmp, lambda m: m["frames"][1].update({"camera_model": "OPENCV", "k1": 0.1, "k4": 0.01}))


def _case_blender_fisheye_tangential(tmp: Path) -> Path:
    return _blender(tmp, lambda m: m.update({"camera_model": "OPENCV_FISHEYE", "k1": 0.1, "p1": 0.01}))


def _case_blender_unknown_model(tmp: Path) -> Path:
    return _blender(tmp, lambda m: m.update({"camera_model": "EQUIRECTANGULAR"}))


def _case_blender_every_photo_missing(tmp: Path) -> Path:
    root = _blender(tmp, lambda m: None)
    shutil.rmtree(root / "train")
    return root


def _case_blender_fractional_size(tmp: Path) -> Path:
    return _blender(tmp, lambda m: m.update({"w": 8.5}))


def _case_blender_bad_json(tmp: Path) -> Path:
    _blender(tmp, lambda m: None)
    (tmp / "transforms.json").write_text("{ not json")
    return tmp


def _colmap(tmp: Path, **kw) -> Path:
    cams = random_cameras(2, 2, 8, 6)
    (tmp / "images").mkdir()
    for name in ("a.png", "b.png"):
        Image.fromarray(np.zeros((6, 8, 3), np.uint8)).save(tmp / "images" / name)
    write_colmap_model(tmp / "sparse" / "0", cams, ["a.png", "b.png"], 8, 6, **kw)
    return tmp


def _case_colmap_unknown_model(tmp: Path) -> Path:
    root = _colmap(tmp, binary=False)
    path = root / "sparse" / "0" / "cameras.txt"
    path.write_text(path.read_text().replace(" PINHOLE ", " RAD_TAN_THIN_PRISM_FISHEYE "))
    return root


def _case_colmap_unknown_model_id(tmp: Path) -> Path:
    root = _colmap(tmp, binary=True)
    path = root / "sparse" / "0" / "cameras.bin"
    data = bytearray(path.read_bytes())
    data[12:16] = (12).to_bytes(4, "little")  # the model id after the count (8 bytes) and camera id (4)
    path.write_bytes(bytes(data))
    return root


def _case_colmap_nan_distortion(tmp: Path) -> Path:
    return _colmap(tmp, binary=False, model="OPENCV", extra=[float("nan"), 0.0, 0.0, 0.0])


def _case_colmap_truncated(tmp: Path) -> Path:
    root = _colmap(tmp, binary=True)
    data = (root / "sparse" / "0" / "images.bin").read_bytes()
    (root / "sparse" / "0" / "images.bin").write_bytes(data[:40])
    return root


def _case_colmap_missing_image(tmp: Path) -> Path:
    root = _colmap(tmp, binary=True)
    (root / "images" / "b.png").unlink()
    return root


def _re10k(tmp: Path, edit: Callable[[list[str]], None]) -> Path:
    cams = random_cameras(2, 3, 8, 8)
    rows = cams.to_re10k(8, 8)
    lines = ["https://www.youtube.com/watch?v=x"] + [
        " ".join([str(ts)] + [repr(v) for v in r.tolist()]) for ts, r in zip((10, 20), rows)
    ]
    edit(lines)
    (tmp / "vid.txt").write_text("\n".join(lines))
    (tmp / "vid").mkdir()
    for ts in (10, 20):
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(tmp / "vid" / f"{ts}.png")
    return tmp / "vid.txt"


def _case_re10k_short_line(tmp: Path) -> Path:
    return _re10k(tmp, lambda lines: lines.__setitem__(2, " ".join(lines[2].split()[:-1])))


def _case_re10k_nan(tmp: Path) -> Path:
    return _re10k(tmp, lambda lines: lines.__setitem__(1, lines[1].replace(lines[1].split()[9], "nan", 1)))


def _case_re10k_missing_frame(tmp: Path) -> Path:
    path = _re10k(tmp, lambda lines: None)
    (tmp / "vid" / "20.png").unlink()
    return path


CASES = [
    ("truncated_png", _case_truncated_png, "im1.png: cannot decode image"),
    ("not_an_image", _case_not_an_image, "im2.png: cannot read image header (UnidentifiedImageError"),
    ("nan_camera", _case_nan_camera, "poses_bounds.npy: row 1 contains NaN or inf"),
    ("inf_camera", _case_inf_camera, "poses_bounds.npy: row 2 contains NaN or inf"),
    ("non_rotation", _case_non_rotation, "not a rigid camera transform"),
    ("zero_focal", _case_zero_focal, "poses_bounds.npy: row 0: focal length must be positive"),
    ("size_mismatch", _case_size_mismatch, "im0.png: image is 15x12 but the intrinsics are for 64x48"),
    ("size_mismatch_uniform", _case_size_mismatch_uniform, "image is 15x12 but the intrinsics are for 64x48"),
    ("count_mismatch", _case_count_mismatch, "3 camera rows but 2 images"),
    ("dtu_missing_key", _case_dtu_missing_key, "cameras_sphere.npz: missing key world_mat_1"),
    ("dtu_singular", _case_dtu_singular, "world_mat_0: projection matrix: its left 3x3 block is singular"),
    ("blender_no_frames", _case_blender_no_frames, "transforms.json: missing key 'frames'"),
    ("blender_no_matrix", _case_blender_no_matrix, "transforms.json: frame 1: missing key 'transform_matrix'"),
    ("blender_no_intrinsics", _case_blender_no_intrinsics, "frame 0: no intrinsics"),
    ("blender_r8_term", _case_blender_r8_term, "transforms.json: field 'k4' is 0.01"),  # a top-level key
    ("blender_frame_r8_term", _case_blender_frame_r8_term, "transforms.json: frame 1: field 'k4' is 0.01"),
    ("blender_fisheye_tangential", _case_blender_fisheye_tangential, "transforms.json: field 'p1' is 0.01"),
    ("blender_unknown_model", _case_blender_unknown_model, "field 'camera_model' is 'EQUIRECTANGULAR'"),
    ("blender_every_photo_missing", _case_blender_every_photo_missing, "every photo listed in it is missing"),
    ("blender_fractional_size", _case_blender_fractional_size, "field 'w' must be a positive whole number"),
    ("blender_bad_json", _case_blender_bad_json, "transforms.json: not valid JSON"),
    ("colmap_unknown_model", _case_colmap_unknown_model, "cameras.txt:2: camera 1 has camera model RAD_TAN"),
    ("colmap_unknown_model_id", _case_colmap_unknown_model_id, "cameras.bin: camera 1 has camera model id 12"),
    ("colmap_nan_distortion", _case_colmap_nan_distortion, "camera 1: camera model OPENCV: parameter k1 is NaN"),
    ("colmap_truncated", _case_colmap_truncated, "images.bin: truncated file"),
    ("colmap_missing_image", _case_colmap_missing_image, "1 of 2 listed frames has no photo (b.png)"),
    ("re10k_short_line", _case_re10k_short_line, "vid.txt:3: expected a timestamp and 18 numbers, got 18 fields"),
    ("re10k_nan", _case_re10k_nan, "vid.txt: camera row 0 contains NaN or inf"),
    ("re10k_missing_frame", _case_re10k_missing_frame, "vid.txt: 1 of 2 listed frames has no photo (20.png)"),
]


@pytest.mark.parametrize("name,build,fragment", CASES, ids=[c[0] for c in CASES])
def test_broken_scene_gets_its_specific_error(tmp_path: Path, name: str, build, fragment: str) -> None:
    path = build(tmp_path)
    with pytest.raises((SurfSplatInputError, FileNotFoundError)) as info:
        load_scene(path)
    message = str(info.value)
    assert fragment in message
    assert "\n" not in message  # one line


def test_unknown_layout_lists_what_was_looked_for(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="no known scene layout.*poses_bounds.npy.*cameras_sphere.npz"):
        load_scene(tmp_path)


# --------------------------------------------------------------------------------- chunk files
def test_chunk_errors(tmp_path: Path) -> None:
    torch.save([], tmp_path / "empty.torch")
    with pytest.raises(SurfSplatInputError, match="empty.torch: chunk contains no examples"):
        read_chunk(tmp_path / "empty.torch")
    (tmp_path / "garbage.torch").write_bytes(b"\x00\x01 not a torch file")
    with pytest.raises(SurfSplatInputError, match="garbage.torch: cannot load chunk"):
        read_chunk(tmp_path / "garbage.torch")
    ex = make_example("k", 3, seed=0)
    del ex["images"]
    torch.save([ex], tmp_path / "noimages.torch")
    with pytest.raises(SurfSplatInputError, match=r"noimages.torch example 0 \('k'\): missing field 'images'"):
        read_chunk(tmp_path / "noimages.torch")
    ex = make_example("k", 3, seed=0)
    ex["cameras"] = ex["cameras"][:, :17]
    torch.save([ex], tmp_path / "shape.torch")
    with pytest.raises(SurfSplatInputError, match=r"field 'cameras' must be a float tensor \[V, 18\], got \(3, 17\)"):
        read_chunk(tmp_path / "shape.torch")
    good = tmp_path / "good"
    write_chunks([make_example("present", 2, seed=1)], good)
    with pytest.raises(SurfSplatInputError, match="key 'absent' not found"):
        load_example(good, "absent")
    with pytest.raises(SurfSplatInputError, match="already holds 1 chunks"):
        write_chunks([make_example("again", 2, seed=1)], good)


def test_evaluation_index_errors(tmp_path: Path) -> None:
    with pytest.raises(SurfSplatInputError, match="entry 'x' is missing key 'target'"):
        EvaluationIndex.from_dict({"x": {"context": [0, 1]}})
    with pytest.raises(SurfSplatInputError, match="entry 'x' field 'context' must be a non-empty list"):
        EvaluationIndex.from_dict({"x": {"context": [0, -1], "target": [2]}})
    with pytest.raises(SurfSplatInputError, match="entry 'y' has unknown keys"):
        EvaluationIndex.from_dict({"y": {"context": [0], "target": [2], "extra": 1}})
    (tmp_path / "bad.json").write_text("[1, 2]")
    with pytest.raises(SurfSplatInputError, match="bad.json: expected a JSON object"):
        EvaluationIndex.load(tmp_path / "bad.json")


# --------------------------------------------------------------- dataset iteration: skip + count
def test_dataset_skips_and_counts_bad_examples(tmp_path: Path, caplog) -> None:
    good = make_example("good", 8, seed=0)
    nan = make_example("nan_camera", 8, seed=1)
    nan["cameras"][3, 8] = float("nan")
    rot = make_example("non_rotation", 8, seed=2)
    rot["cameras"][2, 6:9] *= 2
    corrupt = make_example("corrupt_image", 8, seed=3)
    # Every frame's bytes are cut short, so whichever views the sampler picks fail to decode.
    corrupt["images"] = [t[: t.numel() // 2].clone() for t in corrupt["images"]]
    corrupt["images"][0] = good["images"][0]  # a readable header, so the cameras are read first
    short = make_example("too_short", 2, seed=4)
    write_chunks([good, nan, rot, corrupt, short], tmp_path, target_bytes=1)
    (tmp_path / "999999.torch").write_bytes(b"broken")  # an unreadable chunk file
    sampler = BoundedViewSampler(
        BoundedViewSamplerConfig(
            min_distance_between_context_views=3, max_distance_between_context_views=5, warm_up_steps=0
        )
    )
    ds = ChunkDataset(ChunkDatasetConfig(roots=[tmp_path], image_shape=None, shuffle=False), sampler)
    with caplog.at_level("WARNING", logger="surfsplat.data"):
        samples = list(ds)
    assert [s["scene"] for s in samples] == ["good"]
    s = ds.summary
    assert s.yielded == 1 and s.num_skipped == 5
    assert dict(s.skipped) == {
        "bad cameras or image header": 2,
        "undecodable image": 1,
        "too few frames": 1,
        "unreadable chunk": 1,
    }
    text = "\n".join(s.messages)
    assert "('nan_camera'): camera row 3 contains NaN or inf" in text
    assert "('non_rotation'): world-to-camera of row[2]: not a rigid camera transform" in text
    assert "('corrupt_image') image" in text and "cannot decode image" in text
    assert "('too_short'): 2 frames are too few" in text
    assert "999999.torch: cannot load chunk" in text
    assert "1 samples, 5 skipped" in caplog.text


# ---------------------------------------------------------------------------------------- CLI
def test_convert_cli_reports_one_line_and_leaves_nothing_behind(tmp_path: Path, monkeypatch, capsys) -> None:
    from surfsplat import cli

    monkeypatch.setattr(cli, "COMMANDS", {"convert": ("surfsplat.commands.convert", "raw layouts to chunks")})
    src = tmp_path / "captures"
    good, bad = src / "ok_scene", src / "z_bad_scene"
    good.mkdir(parents=True)
    bad.mkdir()
    _llff(good)
    _case_nan_camera(bad)
    out = tmp_path / "out"
    code = cli.main(["convert", "llff", str(src), str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and "z_bad_scene/poses_bounds.npy: row 1 contains NaN or inf" in err
    assert "Traceback" not in err
    assert not out.exists()  # the good scene's chunk, and the folder made for it, were removed
    # With --skip-bad the good scene is written and the bad one listed.
    code = cli.main(["convert", "llff", str(src), str(out), "--skip-bad"])
    captured = capsys.readouterr()
    assert code == 0 and "wrote 1 scenes, skipped 1" in captured.out and "z_bad_scene" in captured.out
    assert json.loads((out / "index.json").read_text()) == {"ok_scene": "000000.torch"}
    shutil.rmtree(out)
