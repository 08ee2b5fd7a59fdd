"""`reconstruct` on captures processed by other tools: photos with a lens are undistorted as they are
read, so every stage after sees pinhole photos and cameras; the saved reconstruction records the
source lens beside the pinhole and the working crop, and its cameras.json is accepted back with the
photos it was written for (DTU's fixture views, and the same views distorted with a known lens)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from surfsplat.capture import FrameConfig
from surfsplat.data import load_scene_cameras
from surfsplat.data.cameras import CameraSet, load_cameras
from surfsplat.data.images import read_image
from surfsplat.data.transforms import rescale_and_crop
from surfsplat.export.flow import ExportOptions
from surfsplat.geometry.cameras import Cameras
from surfsplat.geometry.lens import Lens
from surfsplat.model import SurfSplat
from surfsplat.reconstruction.inputs import read_capture
from surfsplat.reconstruction.pipeline import _undistorted_views, reconstruct
from surfsplat.reconstruction.scene_fit import load_reconstruction
from surfsplat.utils.checks import SurfSplatInputError
from tests.helpers.lenses import (
    distort_photo,
    install_lens_references,
    reference_pinhole,
    reference_undistort,
    write_photos,
    write_pycolmap_model,
)

DTU = Path(__file__).resolve().parents[1] / "data" / "dtu_scan24"
VIEWS = ["000000.png", "000001.png"]  # adjacent views of the reduced scan 24 (100x75)
DISTORTION = (-0.1, 0.05, 0.001, -0.001)  # OPENCV k1, k2, p1, p2


@pytest.fixture(autouse=True)
def lens_math(monkeypatch):
    install_lens_references(monkeypatch)


@pytest.fixture(scope="module")
def dtu() -> CameraSet:
    return load_scene_cameras(DTU, images="images_16").select(VIEWS, "dtu")


def _distorted_capture(root: Path, dtu: CameraSet) -> tuple[list[Path], Lens]:
    """The two DTU views as an OPENCV lens would have taken them, and a pycolmap-written model of them."""
    K = dtu.cameras.K[0]
    lens = Lens(
        "OPENCV", dtu.width, dtu.height, (K[0, 0].item(), K[1, 1].item(), K[0, 2].item(), K[1, 2].item(), *DISTORTION)
    )
    photos = []
    for name in VIEWS:
        rgb, _ = read_image(DTU / "images_16" / name, background=None)
        photos.append(distort_photo(rgb, K, lens))
    write_photos(root / "images", VIEWS, torch.stack(photos))
    write_pycolmap_model(root / "sparse" / "0", dtu.cameras, VIEWS, lens, binary=True)
    return [root / "images" / n for n in VIEWS], lens


def test_views_with_a_lens_are_undistorted_as_they_are_read(tmp_path: Path, dtu: CameraSet) -> None:
    paths, lens = _distorted_capture(tmp_path, dtu)
    given = load_cameras(tmp_path)
    views, K, c2w = _undistorted_views(read_capture(paths, FrameConfig()), given.select(VIEWS, "test"), "test")
    assert torch.equal(c2w, given.select(VIEWS, "test").cameras.c2w)  # upright photos: the poses as given
    pinhole = reference_pinhole(lens)
    assert (views.width, views.height) == (pinhole.width, pinhole.height) != (lens.width, lens.height)
    torch.testing.assert_close(K, pinhole.intrinsics().expand(2, 3, 3))
    photo, _ = read_image(paths[1], background=None)
    assert (views.image(1) - reference_undistort(photo, lens, pinhole)).abs().mean() < 2 / 255
    # a uniform downscale of the photos: the lens follows them (COLMAP's Camera.rescale)
    half = [tmp_path / "half_a.png", tmp_path / "half_b.png"]
    for p, out in zip(paths, half):
        rgb, _ = read_image(p, background=None)
        write_photos(out.parent, [out.name], torch.nn.functional.interpolate(rgb[None], size=(38, 50), mode="area"))
    views, K, c2w = _undistorted_views(read_capture(half, FrameConfig()), given, "test")
    sx, sy = 50 / 100, 38 / 75  # COLMAP's per-axis factors
    expected = (lens.params[0] * sx, lens.params[1] * sy, lens.params[2] * sx, lens.params[3] * sy)
    assert (
        views.lenses[0][0].params[:4] == pytest.approx(expected, rel=1e-12)
        and views.lenses[0][0].params[4:] == DISTORTION
    )
    # photos of another shape than the lens's: one line naming the image and both sizes
    with pytest.raises(
        SurfSplatInputError, match=r"image '000000.png' is 100x75 but its OPENCV lens is calibrated for 120x75"
    ):
        _undistorted_views(
            read_capture(paths, FrameConfig()),
            CameraSet(given.cameras, 120, 75, VIEWS, lenses=[Lens("OPENCV", 120, 75, lens.params)] * 2),
            "test",
        )


@pytest.fixture(scope="module")
def model() -> SurfSplat:
    torch.manual_seed(0)
    return SurfSplat.from_preset("tiny").eval()


def _save(scene, out: Path) -> dict:
    scene.save(out, options=ExportOptions(formats=("ply",), bake=None, progress=False))
    return json.loads((out / "reconstruction.json").read_text())


@pytest.mark.slow
def test_reconstruct_camera_file_is_accepted_back_with_its_photos(tmp_path: Path, dtu: CameraSet, model) -> None:
    """cameras.json of the 48x32 working crop of the 100x75 photos, given back with the same photos."""
    photos = [DTU / "images_16" / n for n in VIEWS]
    first = reconstruct(photos, checkpoint=model, cameras=dtu, device="cpu", size=(32, 48), progress=False)
    summary = _save(first, tmp_path / "first")
    crop = summary["working_crop"]
    assert (crop["source_width"], crop["source_height"], crop["width"], crop["height"]) == (100, 75, 48, 32)
    again = reconstruct(
        photos,
        checkpoint=model,
        cameras=tmp_path / "first" / "cameras.json",
        device="cpu",
        size=(32, 48),
        progress=False,
    )
    torch.testing.assert_close(again.cameras.K, first.cameras.K, rtol=1e-6, atol=1e-5)
    torch.testing.assert_close(again.cameras.c2w, first.cameras.c2w)


@pytest.mark.slow
@pytest.mark.parametrize("given", ["colmap", "transforms"])
def test_reconstruct_a_capture_with_a_lens(tmp_path: Path, dtu: CameraSet, model, given: str) -> None:
    """Distorted DTU views with a COLMAP model or a nerfstudio transforms.json: the network sees the
    undistorted photos; reconstruction.json and cameras.json record the lens beside the pinhole."""
    paths, lens = _distorted_capture(tmp_path / "capture", dtu)
    pinhole = reference_pinhole(lens)
    cameras = tmp_path / "capture" / "sparse" / "0"
    if given == "transforms":
        fx, fy, cx, cy, k1, k2, p1, p2 = lens.params
        c2w_gl = dtu.cameras.c2w.double() @ torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
        frames = [{"file_path": f"images/{n}", "transform_matrix": c2w_gl[i].tolist()} for i, n in enumerate(VIEWS)]
        meta = {"camera_model": "OPENCV", "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": lens.width, "h": lens.height}
        meta |= {"k1": k1, "k2": k2, "p1": p1, "p2": p2, "frames": frames}
        cameras = tmp_path / "capture" / "transforms.json"
        cameras.write_text(json.dumps(meta))
    scene = reconstruct(paths, checkpoint=model, cameras=cameras, device="cpu", size=(32, 48), progress=False)
    summary = _save(scene, tmp_path / "out")
    assert summary["lenses"] == [{"source": lens.to_dict(), "pinhole": pinhole.to_dict(), "views": VIEWS}]
    assert summary["working_crop"]["source_width"] == pinhole.width
    written = json.loads((tmp_path / "out" / "cameras.json").read_text())
    assert written["frames"][0]["lens"] == lens.to_dict() and written["crop"] == summary["working_crop"]
    # the pinhole K of the crop: the undistorted photos' K taken through the working crop
    crop = scene.crop
    torch.testing.assert_close(
        crop.uncrop(scene.cameras.K.double()), pinhole.intrinsics().expand(2, 3, 3), rtol=1e-6, atol=1e-5
    )
    # given back with the distorted photos: the same cameras
    again = reconstruct(
        paths, checkpoint=model, cameras=tmp_path / "out" / "cameras.json", device="cpu", size=(32, 48), progress=False
    )
    torch.testing.assert_close(again.cameras.K, scene.cameras.K)
    assert isinstance(again.cameras, Cameras) and again.lenses == scene.lenses
    # what `surfsplat optimize` reads back: the context photos undistorted, then the working crop
    loaded, photos = load_reconstruction(tmp_path / "out")
    assert loaded.lenses == scene.lenses and loaded.crop == scene.crop
    for path, image in zip(paths, photos):
        rgb, _ = read_image(path, background=None)
        expected, _, _ = rescale_and_crop(reference_undistort(rgb, lens, pinhole)[None], torch.eye(3)[None], (32, 48))
        assert (image - expected[0].clamp(0, 1)).abs().mean() < 2 / 255


DISTORTED = Path(__file__).resolve().parents[1] / "data" / "distorted"


@pytest.mark.slow
@pytest.mark.parametrize("given", ["sparse/0", "transforms.json"])
def test_reconstruct_command_on_the_distorted_fixture(tmp_path: Path, given: str, capsys) -> None:
    """`surfsplat reconstruct --cameras` the fixture's COLMAP model or transforms.json: the lines the user
    reads name the lens, the pinhole and the working size; the folder records them."""
    from surfsplat.cli import main
    from surfsplat.model import save_checkpoint

    torch.manual_seed(0)
    weights, _ = save_checkpoint(SurfSplat.from_preset("tiny"), tmp_path / "tiny")
    out = tmp_path / "out"
    argv = ["reconstruct", "--checkpoint", str(weights), "--images", str(DISTORTED / "images")]
    argv += ["--cameras", str(DISTORTED / given), "--out", str(out), "--size", "32", "48", "--formats", "ply"]
    code = main(
        [*argv, "--raw-3dgs", "--optimize-steps", "0", "--refine-steps", "0", "--no-progress", "--device", "cpu"]
    )
    shown = capsys.readouterr()
    assert code == 0, shown.err
    truth = json.loads((DISTORTED / "truth.json").read_text())
    lens = Lens.from_dict(truth["lens"])
    pinhole = reference_pinhole(lens)
    fx, fy, cx, cy = pinhole.params
    line = (
        "lens OPENCV (fx 190, fy 190, cx 51.5, cy 38.7, k1 -0.3, k2 0.1, p1 0.002, p2 -0.001) at 100x75, 5 views: "
        f"photos undistorted to a {pinhole.width}x{pinhole.height} pinhole (fx {fx:.6g}, fy {fy:.6g}, cx {cx:.6g}, "
        f"cy {cy:.6g}), then rescaled and cropped to the 48x32 working size"
    )
    assert line in shown.out.splitlines(), shown.out
    summary = json.loads((out / "reconstruction.json").read_text())
    assert summary["lenses"][0]["source"] == lens.to_dict() and summary["lenses"][0]["pinhole"] == pinhole.to_dict()
    assert load_cameras(out / "cameras.json").lenses == [lens] * 5
