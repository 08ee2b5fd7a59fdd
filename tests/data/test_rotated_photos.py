"""Phone photos with a COLMAP model: stored sideways or upside down (EXIF orientation 6, 3 or 8) and
calibrated on their stored pixels, as COLMAP calibrates them (its Bitmap::Read opens images with
OpenImageIO's `oiio:reorient` off; pycolmap's feature extraction gives a 60x100 photo with orientation 6
a 100x60 camera), read as displayed with each camera turned with its photo.

Ground truth: the reduced DTU scan 24 views are the displayed photos and their calibration the displayed
cameras. Each photo is stored turned with Pillow (the turn its `exif_transpose` undoes) and tagged; its
COLMAP camera and pose are the stored pixels', derived here by hand from the turn (the stored camera's
axes are the displayed one's turned about the optical axis), checked against pycolmap's own projection,
and written by pycolmap. Read back, every world point must land on the displayed pixel the original
calibration gives (1e-6 px) and each photo must be the original exactly; `reconstruct` on the capture
(`--optimize-steps 0`) must give each view the original K and pose through its working crop."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image

from surfsplat.data.cameras import load_cameras
from surfsplat.data.formats.dtu import load_dtu
from surfsplat.data.load import load_scene
from surfsplat.data.transforms import rescale_and_crop
from surfsplat.utils.checks import SurfSplatInputError

DTU = Path(__file__).resolve().parent / "dtu_scan24"
ORIENTATION_TAG = 0x0112
# the Pillow transpose that stores a displayed photo with this tag (exif_transpose applies its inverse)
STORE = {1: None, 3: Image.Transpose.ROTATE_180, 6: Image.Transpose.ROTATE_90, 8: Image.Transpose.ROTATE_270}


@pytest.fixture(scope="module")
def dtu():
    """The reduced scan 24 with K's skew set to 0: K decomposed from DTU's projection matrices has a skew
    of about 2e-5 px, which COLMAP's PINHOLE model cannot hold."""
    scene = load_dtu(DTU, images="images_16", dtype=torch.float64)
    scene.cameras.K[:, 0, 1] = 0.0
    return scene


def stored_camera(K: np.ndarray, c2w: np.ndarray, width: int, height: int, orientation: int):
    """(K, c2w, (width, height)) of the stored pixels of a photo displayed as width x height with camera
    (K, c2w). With a stored pixel (xs, ys) and the displayed one (xd, yd) (continuous coordinates, pixel
    centres at +0.5), the turns of the tag are: 3: xs = W - xd, ys = H - yd; 6 (stored turned 90 degrees
    clockwise for display): xs = yd, ys = W - xd; 8: xs = H - yd, ys = xd. The stored camera's axes R
    (stored from displayed) put those maps into K: e.g. for 6, Xs = Yd, Ys = -Xd, so
    xs = fy Xs / Z + cy and ys = fx Ys / Z + (W - cx)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if orientation == 1:
        return K, c2w, (width, height)
    if orientation == 3:
        Ks, R, size = [[fx, 0, width - cx], [0, fy, height - cy]], [[-1, 0, 0], [0, -1, 0], [0, 0, 1]], (width, height)
    elif orientation == 6:
        Ks, R, size = [[fy, 0, cy], [0, fx, width - cx]], [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], (height, width)
    else:
        Ks, R, size = [[fy, 0, height - cy], [0, fx, cx]], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], (height, width)
    turn = np.eye(4)
    turn[:3, :3] = np.array(R, dtype=np.float64).T  # displayed axes from stored ones
    return np.array([*Ks, [0, 0, 1]], dtype=np.float64), c2w @ turn, size


def _world_points(c2w: np.ndarray, K: np.ndarray, width: int, height: int, n: int = 200) -> np.ndarray:
    """[n, 3] world points the displayed camera sees inside its image, at depths 2-4."""
    rng = np.random.default_rng(0)
    px = rng.uniform([0, 0], [width, height], (n, 2))
    z = rng.uniform(2, 4, (n, 1))
    cam = np.concatenate([(px - K[:2, 2]) / np.diag(K)[:2] * z, z], axis=1)
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def _pixels(K: np.ndarray, c2w: np.ndarray, world: np.ndarray) -> np.ndarray:
    w2c = np.linalg.inv(c2w)
    homogeneous = (world @ w2c[:3, :3].T + w2c[:3, 3]) @ K.T
    return homogeneous[:, :2] / homogeneous[:, 2:]


def rotated_capture(root: Path, dtu, views: list[int], orientations: list[int]) -> Path:
    """root/images (each view's PNG stored turned and tagged) and root/sparse/0 (pycolmap's binary model of
    the stored pixels: a PINHOLE camera per stored size, each image's pose of the stored camera)."""
    (root / "images").mkdir(parents=True)
    rec = pycolmap.Reconstruction()
    camera_ids: dict[tuple, int] = {}
    height, width = dtu.images.shape[-2:]
    for image_id, (view, orientation) in enumerate(zip(views, orientations), start=1):
        K, c2w = dtu.cameras.K[view].numpy(), dtu.cameras.c2w[view].numpy()
        Ks, c2ws, (ws, hs) = stored_camera(K, c2w, width, height, orientation)
        # the hand-derived stored camera is what pycolmap projects: stored pixels, turned, are the displayed ones
        world = _world_points(c2w, K, width, height)
        w2c_s = np.linalg.inv(c2ws)
        params = [Ks[0, 0], Ks[1, 1], Ks[0, 2], Ks[1, 2]]
        camera = pycolmap.Camera(model="PINHOLE", width=ws, height=hs, params=params, camera_id=len(camera_ids) + 1)
        stored_px = camera.img_from_cam(world @ w2c_s[:3, :3].T + w2c_s[:3, 3])
        xs, ys = stored_px[:, 0], stored_px[:, 1]
        shown = {1: (xs, ys), 3: (width - xs, height - ys), 6: (width - ys, xs), 8: (ys, height - xs)}[orientation]
        np.testing.assert_allclose(np.stack(shown, 1), _pixels(K, c2w, world), atol=1e-9)
        key = (ws, hs, *params)
        if key not in camera_ids:
            camera_ids[key] = camera.camera_id
            rec.add_camera_with_trivial_rig(camera)
        name = f"IMG_{view:04d}.png"
        image = pycolmap.Image(name=name, camera_id=camera_ids[key], image_id=image_id)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c_s[:3, :4]))
        photo = Image.fromarray((dtu.images[view].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8))
        exif = Image.Exif()
        if orientation != 1:
            photo = photo.transpose(STORE[orientation])
            exif[ORIENTATION_TAG] = orientation
        assert photo.size == (ws, hs)
        photo.save(root / "images" / name, exif=exif.tobytes())
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write(str(root / "sparse" / "0"))
    return root


VIEWS = [0, 1, 2, 3]


@pytest.mark.parametrize("orientations", [[1, 6, 3, 8], [6, 6, 8, 3]], ids=["mixed", "phone"])
def test_cameras_of_stored_pixels_are_read_as_the_displayed_photos_cameras(tmp_path, dtu, orientations):
    root = rotated_capture(tmp_path / "capture", dtu, VIEWS, orientations)
    height, width = dtu.images.shape[-2:]
    cams = load_cameras(root)
    assert (cams.width, cams.height) == (width, height) and cams.lenses is None and not cams.stored_pixels
    for i, view in enumerate(VIEWS):
        K, c2w = dtu.cameras.K[view].numpy(), dtu.cameras.c2w[view].numpy()
        world = _world_points(c2w, K, width, height)
        got = _pixels(cams.cameras.K[i].numpy(), cams.cameras.c2w[i].numpy(), world)
        assert np.abs(got - _pixels(K, c2w, world)).max() < 1e-6
    scene = load_scene(root)  # the photos decoded: as displayed, the originals exactly
    expected = (dtu.images[VIEWS] * 255).round() / 255
    assert torch.equal(scene.images.double(), expected.to(scene.images.dtype).double())
    torch.testing.assert_close(scene.cameras.K.double(), cams.cameras.K, rtol=1e-6, atol=0)  # float32 there


@pytest.mark.parametrize("given", ["capture", "model"], ids=["capture-folder", "bare-model"])
def test_reconstruct_on_rotated_phone_photos_gives_each_view_its_displayed_camera(tmp_path, dtu, given, capsys):
    """End to end (`--optimize-steps 0`): a capture folder (the reader turns the cameras) or the bare model
    with --images (cameras of the stored pixels, turned where the photos meet them): each view's K in the
    written cameras.json is the original K through the working crop, its pose the original pose."""
    from surfsplat.cli import main

    orientations = [6, 8, 6, 8] if given == "model" else [1, 6, 3, 8]  # a bare model holds one stored size
    root = rotated_capture(tmp_path / "capture", dtu, VIEWS, orientations)
    # the bare model: copied away from the photos, so that no reader sees them
    cameras = root if given == "capture" else shutil.copytree(root / "sparse" / "0", tmp_path / "model")
    out = tmp_path / "out"
    argv = ["reconstruct", "--images", str(root / "images"), "--cameras", str(cameras), "--out", str(out)]
    argv += ["--size", "32", "48", "--formats", "ply", "--optimize-steps", "0", "--refine-steps", "0"]
    assert main([*argv, "--no-progress", "--device", "cpu", "--near", "1", "--far", "6"]) == 0, capsys.readouterr().err
    written = json.loads((out / "cameras.json").read_text())
    names = [f"IMG_{v:04d}.png" for v in VIEWS]
    frames = {f["name"]: f for f in written["frames"]}
    for view, name in zip(VIEWS, names):
        _, K_net, _ = rescale_and_crop(dtu.images[view : view + 1].float(), dtu.cameras.K[view : view + 1], (32, 48))
        torch.testing.assert_close(
            torch.tensor(frames[name]["K"], dtype=torch.float64), K_net[0].double(), rtol=0, atol=1e-5
        )
        torch.testing.assert_close(
            torch.tensor(frames[name]["c2w"], dtype=torch.float64), dtu.cameras.c2w[view], rtol=0, atol=1e-6
        )


def test_mirrored_photo_with_a_colmap_model_is_one_line(tmp_path, dtu):
    root = rotated_capture(tmp_path / "capture", dtu, [0, 1], [1, 1])
    photo = Image.open(root / "images" / "IMG_0001.png")
    exif = Image.Exif()
    exif[ORIENTATION_TAG] = 2  # shown mirrored left-right
    photo.transpose(Image.Transpose.FLIP_LEFT_RIGHT).save(root / "images" / "IMG_0001.png", exif=exif.tobytes())
    with pytest.raises(SurfSplatInputError, match="IMG_0001.png.*EXIF orientation 2 shows the photo mirrored") as err:
        load_cameras(root)
    assert "\n" not in str(err.value) and "sparse/0/cameras.bin: camera 2 (IMG_0001.png)" in str(err.value)


# ---------------------------------------------------------------------------- with a lens
DISTORTED = Path(__file__).resolve().parent / "distorted"


def stored_opencv(params: tuple, width: int, height: int, orientation: int) -> tuple[list[float], tuple[int, int]]:
    """The OPENCV parameters (fx, fy, cx, cy, k1, k2, p1, p2) of the stored pixels of photos displayed as
    width x height through `params`. The pinhole part turns as in `stored_camera`; the radial terms depend
    on r alone; the tangential term is r^2 q + 2 (q . x) x with q = (p2, p1) (OpenCV's
    dx = 2 p1 x y + p2 (r^2 + 2 x^2), dy = p1 (r^2 + 2 y^2) + 2 p2 x y), so q turns with the axes:
    q_stored = R q (R of `stored_camera`, its 2x2 block)."""
    fx, fy, cx, cy, k1, k2, p1, p2 = params
    K, _, size = stored_camera(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), np.eye(4), width, height, orientation)
    R = {1: [[1, 0], [0, 1]], 3: [[-1, 0], [0, -1]], 6: [[0, 1], [-1, 0]], 8: [[0, -1], [1, 0]]}[orientation]
    q2, q1 = np.array(R, dtype=np.float64) @ np.array([p2, p1])
    return [K[0, 0], K[1, 1], K[0, 2], K[1, 2], k1, k2, float(q1), float(q2)], size


def rotated_lens_capture(root: Path, orientations: list[int], layout: str) -> tuple[Path, dict]:
    """The distorted fixture's photos stored turned and tagged, with the cameras of the stored pixels as a
    COLMAP model (pycolmap, binary) or as nerfstudio's transforms.json (per-frame intrinsics, w and h of
    the stored image); returns the capture and, per photo, its stored pycolmap Camera and w2c."""
    truth = json.loads((DISTORTED / "truth.json").read_text())
    lens = truth["lens"]
    width, height = lens["width"], lens["height"]
    (root / "images").mkdir(parents=True)
    rec, frames, stored = pycolmap.Reconstruction(), [], {}
    for image_id, (view, orientation) in enumerate(zip(truth["views"], orientations), start=1):
        c2w = np.array(view["c2w"])
        params, (ws, hs) = stored_opencv(tuple(lens["params"]), width, height, orientation)
        _, c2ws, _ = stored_camera(np.eye(3), c2w, width, height, orientation)
        camera = pycolmap.Camera(model="OPENCV", width=ws, height=hs, params=params, camera_id=image_id)
        # the stored camera, turned, is the fixture's lens: pycolmap's projections agree
        original = pycolmap.Camera(model="OPENCV", width=width, height=height, params=lens["params"])
        world = _world_points(c2w, np.array([[190.0, 0, 50], [0, 190, 37.5], [0, 0, 1]]), width, height)
        w2c, w2cs = np.linalg.inv(c2w), np.linalg.inv(c2ws)
        xs, ys = camera.img_from_cam(world @ w2cs[:3, :3].T + w2cs[:3, 3]).T
        shown = {1: (xs, ys), 3: (width - xs, height - ys), 6: (width - ys, xs), 8: (ys, height - xs)}[orientation]
        np.testing.assert_allclose(
            np.stack(shown, 1), original.img_from_cam(world @ w2c[:3, :3].T + w2c[:3, 3]), atol=1e-9
        )
        name = Path(view["image"]).name
        stored[name] = (camera, w2cs)
        photo = Image.open(DISTORTED / view["image"]).convert("RGB")
        exif = Image.Exif()
        if orientation != 1:
            photo = photo.transpose(STORE[orientation])
            exif[ORIENTATION_TAG] = orientation
        photo.save(root / "images" / name, exif=exif.tobytes())
        rec.add_camera_with_trivial_rig(camera)
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=name, camera_id=image_id, image_id=image_id), pycolmap.Rigid3d(w2cs[:3, :4])
        )
        gl = c2ws.copy()
        gl[:3, 1:3] *= -1  # nerfstudio's OpenGL axes
        keys = ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2")
        frames.append({"file_path": f"images/{name}", "transform_matrix": gl.tolist(), "w": ws, "h": hs})
        frames[-1].update({"camera_model": "OPENCV", **dict(zip(keys, params))})
    if layout == "colmap":
        (root / "sparse" / "0").mkdir(parents=True)
        rec.write(str(root / "sparse" / "0"))
    else:
        (root / "transforms.json").write_text(json.dumps({"frames": frames}))
    return root, stored


@pytest.mark.parametrize("orientation", [3, 6, 8])
@pytest.mark.parametrize("layout", ["colmap", "transforms"])
def test_rotated_photos_with_a_lens_are_colmaps_undistortion_turned_for_display(tmp_path, layout, orientation):
    """Each photo is undistorted in its stored frame, as COLMAP's image_undistorter does it (pycolmap's
    `undistort_image` of the stored photo, the reference), then turned for display; its pinhole camera
    projects every world point where pycolmap's undistorted camera of the stored photo does, turned (1e-6 px).
    (COLMAP's pinhole of a lens is not symmetric under a turn: the fixture's lens undistorts to 101x75 when
    stored upright and to 101x74 displayed from sideways pixels, so photos of one capture share a turn here.)"""
    root, stored = rotated_lens_capture(tmp_path / "capture", [orientation] * 5, layout)
    scene = load_scene(root, dtype=torch.float64)
    for i, name in enumerate(scene.names):
        camera, w2cs = stored[name]
        photo = np.array(Image.open(root / "images" / name).convert("RGB"))  # the stored pixels (no transpose)
        bitmap, pinhole = pycolmap.undistort_image(
            pycolmap.UndistortCameraOptions(), pycolmap.Bitmap.from_array(photo), camera
        )
        reference = Image.fromarray(bitmap.to_array())
        if orientation != 1:  # displayed as the tag says: exif_transpose's turn of the stored pixels
            reference = reference.transpose(STORE[{3: 3, 6: 8, 8: 6}[orientation]])
        expected = np.asarray(reference).astype(np.float64)
        got = scene.images[i].permute(1, 2, 0).numpy() * 255
        assert got.shape == expected.shape
        assert np.abs(got - expected).max() <= 1.5  # one 8-bit level, and ours stays in float
        world = _world_points(np.linalg.inv(w2cs), np.eye(3) * 100, 10, 10, n=50)
        xs, ys = pinhole.img_from_cam(world @ w2cs[:3, :3].T + w2cs[:3, 3]).T
        ws, hs = pinhole.width, pinhole.height
        shown = {1: (xs, ys), 3: (ws - xs, hs - ys), 6: (hs - ys, xs), 8: (ys, ws - xs)}[orientation]
        got_px = _pixels(scene.cameras.K[i].numpy(), scene.cameras.c2w[i].numpy(), world)
        assert np.abs(got_px - np.stack(shown, 1)).max() < 1e-6


def test_camera_file_of_rotated_lens_photos_is_read_back_with_them(tmp_path, capsys):
    """reconstruct's cameras.json records each lens with the orientation of its photos: given back with the
    same photos it gives the same cameras, and `surfsplat optimize`'s reader undistorts them as before."""
    from surfsplat.cli import main
    from surfsplat.reconstruction.scene_fit import load_reconstruction

    root, _ = rotated_lens_capture(tmp_path / "capture", [6] * 5, "colmap")
    base = ["reconstruct", "--images", str(root / "images"), "--size", "32", "48", "--formats", "ply"]
    base += ["--optimize-steps", "0", "--refine-steps", "0", "--no-progress", "--device", "cpu"]
    assert main([*base, "--cameras", str(root), "--out", str(tmp_path / "a")]) == 0, capsys.readouterr().err
    first = json.loads((tmp_path / "a" / "cameras.json").read_text())
    assert {f["lens"]["orientation"] for f in first["frames"]} == {6}
    assert "(the stored pixels of photos turned by EXIF orientation 6)" in capsys.readouterr().out
    camera_file = tmp_path / "a" / "cameras.json"
    assert main([*base, "--cameras", str(camera_file), "--out", str(tmp_path / "b")]) == 0, capsys.readouterr().err
    again = json.loads((tmp_path / "b" / "cameras.json").read_text())
    for a, b in zip(first["frames"], again["frames"]):
        assert a["lens"] == b["lens"] and a["pinhole"] == b["pinhole"]
        torch.testing.assert_close(torch.tensor(b["K"]), torch.tensor(a["K"]), rtol=0, atol=1e-9)
        torch.testing.assert_close(torch.tensor(b["c2w"]), torch.tensor(a["c2w"]), rtol=0, atol=1e-9)
    _, photos = load_reconstruction(tmp_path / "a")
    scene = load_scene(root)  # the photos undistorted as displayed
    for i, name in enumerate(json.loads((tmp_path / "a" / "reconstruction.json").read_text())["images"]):
        expected, _, _ = rescale_and_crop(
            scene.images[scene.names.index(Path(name).name)][None], torch.eye(3)[None], (32, 48)
        )
        assert (photos[i] - expected[0].clamp(0, 1)).abs().max() < 1e-6


@pytest.mark.parametrize("orientation", [3, 6])
def test_bare_model_with_a_lens_turns_where_the_photos_meet_it(tmp_path, orientation):
    """The same lens capture given as its bare model folder (cameras of the stored pixels, no photo read)
    and its photos: the views reconstruct reads are the capture folder's, K, pose and pixels."""
    from surfsplat.capture import FrameConfig
    from surfsplat.reconstruction.inputs import read_capture
    from surfsplat.reconstruction.pipeline import _undistorted_views

    root, _ = rotated_lens_capture(tmp_path / "capture", [orientation] * 5, "colmap")
    bare = load_cameras(shutil.copytree(root / "sparse" / "0", tmp_path / "model"))  # no photos beside it
    assert bare.stored_pixels and {lens.orientation for lens in bare.lenses} == {1}
    folder = load_scene(root, dtype=torch.float64)
    photos = sorted((root / "images").iterdir())
    views, K, c2w = _undistorted_views(read_capture(photos, FrameConfig()), bare.select(folder.names, "t"), "t")
    torch.testing.assert_close(K, folder.cameras.K, rtol=0, atol=1e-12)
    torch.testing.assert_close(c2w, folder.cameras.c2w, rtol=0, atol=1e-12)
    assert {lens.orientation for lens, _ in views.lenses} == {orientation}
    for i in range(len(views)):
        assert torch.equal(views.image(i).double(), folder.images[i].to(torch.float32).double())
