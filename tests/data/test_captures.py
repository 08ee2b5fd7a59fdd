"""Captures processed by other tools, read by what they are: COLMAP models of every camera model
(written by pycolmap itself), every transforms.json dialect (nerfstudio, instant-ngp, Blender), frames
whose photo was left out, camera files recognised by their content, and the package's own camera
file accepted back with the photos it was written for (its working crop and lenses recorded)."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from surfsplat import Cameras
from surfsplat.data import load_scene, load_scene_cameras
from surfsplat.data.cameras import load_cameras, save_cameras
from surfsplat.data.formats.blender import read_transforms
from surfsplat.data.images import read_image
from surfsplat.data.transforms import WorkingCrop, rescale_and_crop, working_crop
from surfsplat.geometry.lens import CAMERA_MODELS, Lens
from surfsplat.utils.checks import SurfSplatInputError
from tests.helpers.data import random_cameras, write_images
from tests.helpers.lenses import (
    MODEL_PARAMS,
    colmap_camera,
    install_lens_references,
    reference_pinhole,
    reference_undistort,
    write_photos,
    write_pycolmap_model,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

W, H = 100, 75
GL = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))  # OpenCV <-> OpenGL camera axes
PINHOLES = ("SIMPLE_PINHOLE", "PINHOLE")


@pytest.fixture(autouse=True)
def lens_math(monkeypatch):
    """COLMAP's own undistorted_pinhole / undistort_image where the package lacks its own functions."""
    install_lens_references(monkeypatch)


def _lens(model: str) -> Lens:
    return Lens(model, W, H, tuple(MODEL_PARAMS[model]))


def _assert_pinhole_K(K: torch.Tensor, pinhole: Lens) -> None:
    fx, fy, cx, cy = pinhole.params
    expected = torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(K.double(), expected.expand_as(K), rtol=1e-6, atol=1e-9)


# ------------------------------------------------------------------------------------- COLMAP
@pytest.mark.parametrize("binary", [True, False], ids=["binary", "text"])
@pytest.mark.parametrize("model", [name for name, _ in CAMERA_MODELS.values()])
def test_colmap_every_model_is_read_into_its_lens(tmp_path: Path, model: str, binary: bool) -> None:
    """A pycolmap-written model of each camera model 0-10: the lens as COLMAP stores it; K and size of the
    pinhole COLMAP's image_undistorter chooses; photos undistorted as pycolmap's undistort_image does."""
    cams = random_cameras(3, 1, W, H)
    names = ["c.png", "a.png", "b.png"]  # registered out of order: the reader sorts by name
    lens = _lens(model)
    write_pycolmap_model(tmp_path / "sparse" / "0", cams, names, lens, binary)
    write_photos(tmp_path / "images", names, torch.rand(3, 3, H, W, generator=torch.Generator().manual_seed(2)))
    order = [1, 2, 0]

    cam_set = load_scene_cameras(tmp_path)
    assert cam_set.names == ["a.png", "b.png", "c.png"]
    torch.testing.assert_close(cam_set.cameras.c2w, cams.c2w[order], atol=1e-9, rtol=0)
    if model in PINHOLES:
        assert cam_set.lenses is None and (cam_set.width, cam_set.height) == (W, H)
        torch.testing.assert_close(cam_set.cameras.K, lens.intrinsics().expand(3, 3, 3))
        return
    assert cam_set.lenses == [lens] * 3  # COLMAP's parameters, in its order, at its size
    pinhole = reference_pinhole(lens)
    assert (cam_set.width, cam_set.height) == (pinhole.width, pinhole.height)
    _assert_pinhole_K(cam_set.cameras.K, pinhole)

    scene = load_scene(tmp_path, dtype=torch.float64)
    assert scene.images.shape == (3, 3, pinhole.height, pinhole.width) and scene.extras["lenses"] == [lens] * 3
    _assert_pinhole_K(scene.cameras.K, pinhole)
    photo, _ = read_image(tmp_path / "images" / "a.png", background=None)
    reference = reference_undistort(photo, lens, pinhole)
    # two bilinear resamplings of 8-bit values where the package undistorts, the same one where it is COLMAP's
    assert (scene.images[0].float() - reference).abs().mean() < 2 / 255


def test_colmap_zero_distortion_perspective_models_are_pinholes(tmp_path: Path) -> None:
    cams = random_cameras(2, 3, W, H)
    lens = Lens("SIMPLE_RADIAL", W, H, (90.0, 50.0, 37.5, 0.0))
    write_pycolmap_model(tmp_path / "sparse" / "0", cams, ["a.png", "b.png"], lens, binary=True)
    write_images(tmp_path / "images", ["a.png", "b.png"], W, H, seed=3)
    cam_set = load_scene_cameras(tmp_path)
    assert cam_set.lenses is None
    torch.testing.assert_close(cam_set.cameras.K, lens.intrinsics().expand(2, 3, 3))


def test_colmap_lens_follows_a_downscaled_photo_folder(tmp_path: Path) -> None:
    """Photos in images_2 at half the calibrated size: the lens rescaled as COLMAP's Camera.rescale does."""
    cams = random_cameras(2, 4, 100, 76)
    lens = Lens("OPENCV", 100, 76, tuple(MODEL_PARAMS["OPENCV"]))
    write_pycolmap_model(tmp_path / "sparse" / "0", cams, ["a.png", "b.png"], lens, binary=False)
    write_images(tmp_path / "images_2", ["a.png", "b.png"], 50, 38, seed=4)
    cam_set = load_scene_cameras(tmp_path, images="images_2")
    camera = colmap_camera(lens)
    camera.rescale(50, 38)
    half = Lens("OPENCV", 50, 38, tuple(camera.params))
    assert cam_set.lenses == [half] * 2 and lens.rescaled(50, 38) == half
    assert half.params[0] == 45.0 and half.params[4:] == lens.params[4:]  # focal halved, distortion kept
    _assert_pinhole_K(cam_set.cameras.K, reference_pinhole(half))


# ----------------------------------------------------------------------------- transforms.json
def _transforms(root: Path, top: dict, frames: list[dict] | None = None, n: int = 3, present: int | None = None):
    """A transforms.json in root with n frames (OpenGL c2w of random_cameras) and `present` photos."""
    cams = random_cameras(n, 5, W, H)
    names = [f"frame_{i + 1:05d}.png" for i in range(n)]
    write_images(root / "images", names[: n if present is None else present], W, H, seed=5)
    c2w_gl = cams.c2w @ GL
    entries = [{"file_path": f"images/{name}", "transform_matrix": c2w_gl[i].tolist()} for i, name in enumerate(names)]
    for entry, extra in zip(entries, frames or []):
        entry.update(extra)
    (root / "transforms.json").write_text(json.dumps({**top, "frames": entries}))
    return root / "transforms.json", cams


FX, FY, CX, CY = 90.0, 88.0, 50.5, 37.0
NS = {"fl_x": FX, "fl_y": FY, "cx": CX, "cy": CY, "w": W, "h": H}
DIALECTS = {
    # nerfstudio's OPENCV: k1, k2, p1, p2 -> COLMAP OPENCV
    "nerfstudio_opencv": (
        {**NS, "camera_model": "OPENCV", "k1": -0.1, "k2": 0.05, "p1": 0.001, "p2": -0.001},
        Lens("OPENCV", W, H, (FX, FY, CX, CY, -0.1, 0.05, 0.001, -0.001)),
    ),
    # nerfstudio's OPENCV with its k3 (r^6 term): COLMAP FULL_OPENCV, k3 in its slot, no denominator
    "nerfstudio_opencv_k3": (
        {**NS, "camera_model": "OPENCV", "k1": -0.1, "k2": 0.05, "k3": 0.01, "k4": 0.0, "p1": 0.001, "p2": -0.001},
        Lens("FULL_OPENCV", W, H, (FX, FY, CX, CY, -0.1, 0.05, 0.001, -0.001, 0.01, 0.0, 0.0, 0.0)),
    ),
    "nerfstudio_fisheye": (
        {**NS, "camera_model": "OPENCV_FISHEYE", "k1": 0.05, "k2": -0.01, "k3": 0.002, "k4": 0.0005},
        Lens("OPENCV_FISHEYE", W, H, (FX, FY, CX, CY, 0.05, -0.01, 0.002, 0.0005)),
    ),
    # instant-ngp's colmap2nerf: no camera_model, k1/k2/p1/p2 (k3 = k4 = 0) at the top level, float w/h,
    # one focal length
    "instant_ngp": (
        {"fl_x": FX, "cx": CX, "cy": CY, "w": float(W), "h": float(H), "k1": -0.1, "k2": 0.05, "k3": 0, "k4": 0}
        | {"p1": 0.001, "p2": -0.001, "is_fisheye": False, "aabb_scale": 16},
        Lens("OPENCV", W, H, (FX, FX, CX, CY, -0.1, 0.05, 0.001, -0.001)),
    ),
    "instant_ngp_fisheye": (
        {"fl_x": FX, "fl_y": FY, "cx": CX, "cy": CY, "w": float(W), "h": float(H), "is_fisheye": True}
        | {"k1": 0.05, "k2": -0.01, "k3": 0.002, "k4": 0.0005, "p1": 0.0, "p2": 0.0},
        Lens("OPENCV_FISHEYE", W, H, (FX, FY, CX, CY, 0.05, -0.01, 0.002, 0.0005)),
    ),
}


@pytest.mark.parametrize("dialect", list(DIALECTS))
def test_transforms_dialects_map_to_colmap_models(tmp_path: Path, dialect: str) -> None:
    top, expected = DIALECTS[dialect]
    path, cams = _transforms(tmp_path, top)
    cam_set = load_cameras(path)  # the file itself, recognised as a transforms.json
    assert cam_set.lenses == [expected] * 3
    pinhole = reference_pinhole(expected)
    assert (cam_set.width, cam_set.height) == (pinhole.width, pinhole.height)
    _assert_pinhole_K(cam_set.cameras.K, pinhole)
    torch.testing.assert_close(cam_set.cameras.c2w, cams.c2w, atol=1e-12, rtol=0)


def test_nerfstudio_k3_is_the_r6_term_of_full_opencv() -> None:
    """nerfstudio's perspective distortion (camera_utils.radial_and_tangential_distort: radial factor
    1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8, tangential p1, p2) equals COLMAP's FULL_OPENCV with k3 in its
    slot and k4..k6 zero, evaluated by pycolmap."""
    k1, k2, k3, p1, p2 = -0.1, 0.05, 0.01, 0.001, -0.001
    lens = DIALECTS["nerfstudio_opencv_k3"][1]
    xy = np.random.default_rng(0).uniform(-0.5, 0.5, (50, 2))
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
    expected = np.stack([FX * xd + CX, FY * yd + CY], -1)
    pixels = colmap_camera(lens).img_from_cam(np.concatenate([xy, np.ones((50, 1))], -1))
    np.testing.assert_allclose(pixels, expected, rtol=0, atol=1e-9)


def test_nerfstudio_fisheye_is_opencv_fisheye() -> None:
    """k1..k4 of OPENCV_FISHEYE mean what OpenCV's fisheye model means (cv2.fisheye.projectPoints)."""
    import cv2

    lens = DIALECTS["nerfstudio_fisheye"][1]
    points = np.random.default_rng(1).uniform(-0.6, 0.6, (40, 3))
    points[:, 2] = 1.0
    K = np.array([[FX, 0, CX], [0, FY, CY], [0, 0, 1.0]])
    D = np.array(lens.params[4:])
    ours = colmap_camera(lens).img_from_cam(points)
    theirs, _ = cv2.fisheye.projectPoints(points[:, None], np.zeros(3), np.zeros(3), K, D)
    np.testing.assert_allclose(ours, theirs[:, 0], rtol=0, atol=1e-9)


def test_transforms_per_frame_intrinsics_override_the_top_level(tmp_path: Path) -> None:
    top = {**NS, "camera_model": "OPENCV", "k1": -0.1}
    own = {"fl_x": 80.0, "fl_y": 80.0, "k1": -0.05, "k2": 0.01}
    path, _ = _transforms(tmp_path, top, frames=[{}, own, {"k1": 0.0}])
    cam_set = read_transforms(path)
    assert cam_set.lenses[0] == Lens("OPENCV", W, H, (FX, FY, CX, CY, -0.1, 0.0, 0.0, 0.0))
    assert cam_set.lenses[1] == Lens("OPENCV", W, H, (80.0, 80.0, CX, CY, -0.05, 0.01, 0.0, 0.0))
    # the third frame's own k1 = 0 makes it a pinhole among lenses: its own PINHOLE lens, no undistortion
    assert cam_set.lenses[2] == Lens("PINHOLE", W, H, (FX, FY, CX, CY))
    # the views' pinholes differ in size, and a scene has one: one line naming the first that differs
    with pytest.raises(SurfSplatInputError, match=r"frame_00002.png: image undistorts to \d+x\d+ but frame_00001.png"):
        load_cameras(path)


def test_transforms_blender_angles_and_informational_transform(tmp_path: Path) -> None:
    """Blender's camera_angle_x / _y (radians, centred principal point); nerfstudio's applied_transform is
    recorded by ns-process-data and not applied again."""
    top = {"camera_angle_x": 0.9, "camera_angle_y": 0.7, "applied_transform": np.eye(4)[:3].tolist()}
    top["applied_transform"][0][3] = 5.0
    path, cams = _transforms(tmp_path, top)
    cam_set = load_cameras(path)
    assert cam_set.lenses is None and (cam_set.width, cam_set.height) == (W, H)
    fx, fy = 0.5 * W / math.tan(0.45), 0.5 * H / math.tan(0.35)
    expected = torch.tensor([[fx, 0, W / 2], [0, fy, H / 2], [0, 0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(cam_set.cameras.K, expected.expand(3, 3, 3))
    torch.testing.assert_close(cam_set.cameras.c2w, cams.c2w, atol=1e-12, rtol=0)


def test_transforms_photos_undistorted_at_load(tmp_path: Path) -> None:
    top, lens = DIALECTS["nerfstudio_opencv"]
    path, _ = _transforms(tmp_path, top, n=2)
    scene = load_scene(tmp_path, dtype=torch.float64)
    pinhole = reference_pinhole(lens)
    assert scene.images.shape == (2, 3, pinhole.height, pinhole.width)
    photo, _ = read_image(tmp_path / "images" / "frame_00001.png", background=None)
    assert (scene.images[0].float() - reference_undistort(photo, lens, pinhole)).abs().mean() < 2 / 255


# ----------------------------------------------------------------------------- missing frames
def test_frames_without_photo_are_left_out_with_one_counted_warning(tmp_path: Path, caplog) -> None:
    path, cams = _transforms(tmp_path, {"camera_angle_x": 0.9}, n=7, present=3)
    with caplog.at_level(logging.WARNING):
        cam_set = load_cameras(tmp_path)  # the folder: its transforms.json
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings == [
        f"4 of 7 frames listed in {path} have no photo (frame_00004.png, frame_00005.png, frame_00006.png, ...); "
        "they are left out"
    ]
    assert cam_set.names == ["frame_00001.png", "frame_00002.png", "frame_00003.png"]
    torch.testing.assert_close(cam_set.cameras.c2w, cams.c2w[:3], atol=1e-12, rtol=0)


def test_fewer_than_two_photos_left_is_an_error(tmp_path: Path) -> None:
    _transforms(tmp_path, {"camera_angle_x": 0.9}, n=4, present=1)
    with pytest.raises(SurfSplatInputError, match=r"3 of 4 listed frames have no photo .*only frame_00001.png is left"):
        load_cameras(tmp_path / "transforms.json")
    (tmp_path / "images" / "frame_00001.png").unlink()
    with pytest.raises(SurfSplatInputError, match="transforms.json: every photo listed in it is missing"):
        load_cameras(tmp_path / "transforms.json")


def test_colmap_registered_images_without_photo_are_left_out(tmp_path: Path, caplog) -> None:
    cams = random_cameras(4, 6, W, H)
    names = ["a.png", "b.png", "c.png", "d.png"]
    write_pycolmap_model(tmp_path / "sparse" / "0", cams, names, _lens("PINHOLE"), binary=True)
    write_images(tmp_path / "images", ["a.png", "c.png", "d.png"], W, H, seed=6)
    with caplog.at_level(logging.WARNING):
        scene = load_scene(tmp_path)
    assert scene.names == ["a.png", "c.png", "d.png"]
    assert [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING] == [
        f"1 of 4 frames listed in {tmp_path / 'sparse' / '0'} (registered images) has no photo (b.png); "
        "they are left out"
    ]


def test_realestate10k_timestamps_without_frame_are_left_out(tmp_path: Path, caplog) -> None:
    cams = random_cameras(4, 10, 32, 18)
    stamps = [1001, 2002, 3003, 4004]
    rows = [" ".join([str(ts), *(repr(v) for v in row.tolist())]) for ts, row in zip(stamps, cams.to_re10k(32, 18))]
    (tmp_path / "key.txt").write_text("\n".join(["https://www.youtube.com/watch?v=x", *rows]) + "\n")
    write_images(tmp_path / "key", ["1001.jpg", "3003.jpg", "4004.jpg"], 32, 18, seed=10)
    with caplog.at_level(logging.WARNING):
        scene = load_scene(tmp_path / "key.txt", dtype=torch.float64)
    assert scene.names == ["1001", "3003", "4004"]
    assert scene.extras["timestamps"].tolist() == [1001, 3003, 4004]
    torch.testing.assert_close(scene.cameras.c2w, cams.c2w[[0, 2, 3]], atol=1e-9, rtol=0)
    assert [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING] == [
        f"1 of 4 frames listed in {tmp_path / 'key.txt'} has no photo (2002.jpg); they are left out"
    ]


def test_a_photo_that_exists_but_cannot_be_decoded_stays_an_error(tmp_path: Path) -> None:
    _transforms(tmp_path, {"camera_angle_x": 0.9}, n=3)
    (tmp_path / "images" / "frame_00002.png").write_bytes(b"not a png")
    with pytest.raises(SurfSplatInputError, match="frame_00002.png: cannot"):
        load_scene(tmp_path)


# ------------------------------------------------------------------------ content recognition
def test_camera_files_are_recognised_by_their_content(tmp_path: Path) -> None:
    cams = random_cameras(3, 7, W, H)
    names = ["a.png", "b.png", "c.png"]
    model = tmp_path / "capture" / "sparse" / "0"
    write_pycolmap_model(model, cams, names, _lens("OPENCV"), binary=True)
    write_pycolmap_model(tmp_path / "text", cams, names, _lens("OPENCV"), binary=False)
    expected = reference_pinhole(_lens("OPENCV"))
    # a COLMAP model: its folder, a capture holding sparse/0 without photos, or any of its files
    for given in (
        model,
        tmp_path / "capture",
        model / "cameras.bin",
        model / "images.bin",
        tmp_path / "text" / "images.txt",
    ):
        got = load_cameras(given)
        assert got.names == names and got.lenses == [_lens("OPENCV")] * 3, given
        _assert_pinhole_K(got.cameras.K, expected)
    # this package's camera file, with and without its format marker
    save_cameras(tmp_path / "own.json", cams, W, H, names)
    data = json.loads((tmp_path / "own.json").read_text())
    del data["format"]
    (tmp_path / "unmarked.json").write_text(json.dumps(data))
    for given in (tmp_path / "own.json", tmp_path / "unmarked.json"):
        got = load_cameras(given)
        torch.testing.assert_close(got.cameras.K, cams.K)
        assert got.lenses is None and got.crop is None
    # unknown content: what it holds and what is accepted, in one line
    (tmp_path / "other.json").write_text(json.dumps({"scenes": [1], "version": 2}))
    with pytest.raises(
        SurfSplatInputError,
        match=r"other.json: not a camera file .* keys scenes, version and no 'frames'; accepted: a transforms.json",
    ):
        load_cameras(tmp_path / "other.json")
    (tmp_path / "paths.json").write_text(json.dumps({"frames": [{"file_path": "a.png"}]}))
    with pytest.raises(SurfSplatInputError, match=r"'frames' whose entries hold file_path \(no transform_matrix"):
        load_cameras(tmp_path / "paths.json")
    (tmp_path / "poses.npy").write_bytes(b"")
    with pytest.raises(SurfSplatInputError, match=r"poses.npy: a .npy file; accepted:"):
        load_cameras(tmp_path / "poses.npy")


# ------------------------------------------------------------------- the camera file written back
def test_working_crop_is_what_rescale_and_crop_does() -> None:
    K = torch.tensor([[300.0, 0, 201.0], [0, 301.0, 149.0], [0, 0, 1]], dtype=torch.float64)[None]
    for (w, h), shape in [((400, 300), (288, 400)), ((100, 75), (64, 96)), ((640, 360), (256, 256))]:
        crop = working_crop(w, h, shape)
        _, K_crop, _ = rescale_and_crop(torch.zeros(1, 3, h, w), K, shape, method="area")
        expected = K.clone()
        expected[..., 0, :] *= crop.scaled_width / w
        expected[..., 1, :] *= crop.scaled_height / h
        expected[..., 0, 2] -= crop.left
        expected[..., 1, 2] -= crop.top
        torch.testing.assert_close(K_crop, expected, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(crop.uncrop(K_crop), K, rtol=1e-12, atol=1e-12)
    assert working_crop(400, 300, (288, 400)) == WorkingCrop(400, 300, 400, 300, 0, 6, 400, 288)


def test_camera_file_of_a_working_crop_is_accepted_with_its_photos(tmp_path: Path) -> None:
    """The 400x288 crop of DTU's 400x300 photos: K back to the photos (and to half their size)."""
    cams = random_cameras(2, 8, 400, 300)
    crop = working_crop(400, 300, (288, 400))
    _, K_crop, _ = rescale_and_crop(torch.zeros(2, 3, 300, 400), cams.K, (288, 400), method="area")
    save_cameras(tmp_path / "cameras.json", Cameras(cams.c2w, K_crop), 400, 288, ["a.png", "b.png"], crop=crop)
    back = load_cameras(tmp_path / "cameras.json")
    assert back.crop == crop and (back.width, back.height) == (400, 288)
    torch.testing.assert_close(back.resized(400, 300, "test").K, cams.K, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(back.resized(200, 150, "test").K, cams.scaled(0.5).K, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(back.resized(400, 288, "test").K, K_crop)
    with pytest.raises(SurfSplatInputError, match=r"images are 300x300 but the cameras are for 400x288 or the 400x300"):
        back.resized(300, 300, "test")


def test_camera_file_records_each_views_lens_and_pinhole(tmp_path: Path) -> None:
    lens = _lens("SIMPLE_RADIAL")
    pinhole = reference_pinhole(lens)
    cams = Cameras(random_cameras(2, 9, W, H).c2w, pinhole.intrinsics().expand(2, 3, 3))
    save_cameras(tmp_path / "c.json", cams, pinhole.width, pinhole.height, ["a.png", "b.png"], lenses=[lens, lens])
    frames = json.loads((tmp_path / "c.json").read_text())["frames"]
    assert frames[0]["lens"] == lens.to_dict() and frames[0]["pinhole"] == pinhole.to_dict()
    assert load_cameras(tmp_path / "c.json").lenses == [lens, lens]


# ------------------------------------------------------------------ the distorted DTU fixture
DISTORTED = Path(__file__).resolve().parent / "distorted"


@pytest.mark.parametrize(
    "given",
    ["sparse/0", "sparse/text", "sparse/0/images.bin", "transforms.json", "instant_ngp", "fisheye/transforms.json"],
)
def test_distorted_fixture_is_read_by_every_file_of_it(given: str) -> None:
    """The fixture's COLMAP model (binary and text), nerfstudio and instant-ngp transforms.json, and its
    fisheye set's nerfstudio OPENCV_FISHEYE transforms.json: one lens, the pinhole COLMAP's undistorter
    chooses, the poses its truth.json holds."""
    folder = DISTORTED / "fisheye" if given.startswith("fisheye") else DISTORTED
    truth = json.loads((folder / "truth.json").read_text())
    lens = Lens.from_dict(truth["lens"])
    cam_set = load_cameras(DISTORTED / given)
    assert cam_set.names == [Path(v["image"]).name for v in truth["views"]]
    assert cam_set.lenses == [lens] * len(truth["views"])
    _assert_pinhole_K(cam_set.cameras.K, reference_pinhole(lens))
    c2w = torch.tensor([v["c2w"] for v in truth["views"]], dtype=torch.float64)
    torch.testing.assert_close(cam_set.cameras.c2w.double(), c2w, atol=1e-9, rtol=0)


@pytest.mark.parametrize("given", ["sparse/0", "fisheye/transforms.json"])
def test_distorted_fixture_photos_come_back_to_their_source(given: str) -> None:
    """Each distorted photo undistorted at load equals its DTU source photo seen by the new pinhole (the
    source resampled by the homography K_pinhole K_source^-1: same rotation, other intrinsics)."""
    folder = DISTORTED / "fisheye" if given.startswith("fisheye") else DISTORTED
    truth = json.loads((folder / "truth.json").read_text())
    scene = load_scene(DISTORTED / given)
    pinhole = reference_pinhole(Lens.from_dict(truth["lens"]))
    h, w = scene.height, scene.width
    j, i = torch.meshgrid(torch.arange(w) + 0.5, torch.arange(h) + 0.5, indexing="xy")
    errors = []
    for view, image in zip(truth["views"], scene.images):
        source, _ = read_image(DISTORTED.parent / view["source"], background=None)
        K_src = Lens.from_dict(view["pinhole"]).intrinsics()
        rays = torch.stack([j, i, torch.ones_like(j)], -1).double() @ torch.linalg.inv(pinhole.intrinsics()).T
        uv = rays @ K_src.T
        H, W = source.shape[1:]
        grid = torch.stack([uv[..., 0] / W * 2 - 1, uv[..., 1] / H * 2 - 1], -1).float()[None]
        expected = torch.nn.functional.grid_sample(source[None], grid, align_corners=False)[0]
        errors.append((image - expected)[:, 2:-2, 2:-2].abs().mean().item())  # the border: half a pixel of blank
    assert max(errors) < 3 / 255, errors  # three resamplings of 8-bit photos (distort, undistort, this one)
