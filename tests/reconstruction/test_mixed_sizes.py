"""A capture of landscape and portrait photos with known cameras goes through `reconstruct`: each view
keeps its own K, cropped to the working size exactly as rescale_and_crop's closed form says, a
portrait photo stored sideways with EXIF orientation 6 (and its camera file of the stored pixels)
arrives upright with its camera turned, and the views that lose part of their frame are named."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from PIL import Image

import surfsplat
from surfsplat import Cameras
from surfsplat.capture import OptimizeConfig
from surfsplat.data.cameras import save_cameras
from surfsplat.data.images import read_image
from surfsplat.data.synthetic import make_scene, make_trajectory, render_synthetic
from surfsplat.export.images import write_png
from surfsplat.geometry.orientation import displayed_camera
from surfsplat.reconstruction.inputs import reference_size
from surfsplat.reconstruction.sizes import kept_share, view_cameras
from surfsplat.utils.checks import SurfSplatInputError

LW, LH = 48, 32  # landscape views; the portrait one is 32 x 48
NEAR, FAR = 0.5, 15.0
OPTIONS = surfsplat.CaptureOptions(views_per_pass=4, optimize=OptimizeConfig(steps=0))


@pytest.fixture(scope="module")
def capture():
    """Three landscape views and one portrait view of a procedural room, with their exact cameras."""
    scene = make_scene(5)
    trajectory = make_trajectory(scene, torch.Generator().manual_seed(0))
    t = torch.linspace(0, 1, 4)
    land = trajectory.cameras(t[:3], LW, LH)
    port = trajectory.cameras(t[3:], LH, LW)  # same field of view across the portrait's width
    images = [*render_synthetic(scene, land, LW, LH).image, render_synthetic(scene, port, LH, LW).image[0]]
    return scene, land, port, images


def _expected_network_K(K: torch.Tensor, size: tuple[int, int], shape: tuple[int, int]) -> torch.Tensor:
    """rescale_and_crop's closed form: scale s = max(H/h, W/w), then a centre crop shifts the principal point."""
    (w, h), (H, W) = size, shape
    s = max(H / h, W / w)
    rw, rh = max(W, round(w * s)), max(H, round(h * s))
    out = K.clone().double()
    out[0] *= rw / w
    out[1] *= rh / h
    out[0, 2] -= (rw - W) // 2
    out[1, 2] -= (rh - H) // 2
    return out


def test_reference_size_is_the_first_view_of_the_most_common_orientation():
    assert reference_size([(32, 48), (48, 32), (64, 40), (40, 64), (60, 40)]) == (48, 32)
    assert reference_size([(32, 48), (48, 32)]) == (32, 48)  # a tie: the first view's
    assert kept_share((32, 48), (32, 48)) == pytest.approx(32 * 48 / (48 * 72))


def test_portrait_and_landscape_views_keep_their_own_intrinsics(capture, tmp_path, caplog):
    _, land, port, images = capture
    paths = [write_png(tmp_path / f"v{i}.png", image) for i, image in enumerate(images)]
    given = Cameras(torch.cat([land.c2w, port.c2w]), torch.cat([land.K, port.K]))  # each K of its own photo
    with caplog.at_level(logging.WARNING, logger="surfsplat"):
        scene = surfsplat.reconstruct(
            paths, "tiny-synthetic", cameras=given, device="cpu", near=NEAR, far=FAR, capture=OPTIONS, progress=False
        )
    assert (scene.height, scene.width) == (LH, LW)  # the landscape majority sets the working size
    for i, (K, size) in enumerate([(k, (LW, LH)) for k in land.K] + [(port.K[0], (LH, LW))]):
        torch.testing.assert_close(scene.cameras.K[i].double(), _expected_network_K(K, size, (LH, LW)))
    torch.testing.assert_close(scene.cameras.c2w, given.c2w.float())
    assert scene.cameras.K[3, 0, 0] == pytest.approx(1.5 * port.K[0, 0, 0])  # the portrait is upscaled 1.5x
    warned = [r.getMessage() for r in caplog.records if "differ in shape" in r.getMessage()]
    assert len(warned) == 1 and "v3.png (32x48) keeps 44%, its top and bottom cut" in warned[0], warned
    assert "v0.png" not in warned[0]
    assert torch.isfinite(scene.gaussians.means).all() and len(scene.gaussians) == 4 * LH * LW


def test_portrait_photo_stored_sideways_with_a_camera_of_its_stored_pixels(capture, tmp_path):
    """The phone's way: pixels stored landscape, EXIF orientation 6, and (as COLMAP calibrates them) a
    camera file for the stored 48x32 pixels. The photo reads upright and its camera is turned with it."""
    scene_, land, port, images = capture
    # the stored image's camera: the displayed portrait turned back (orientation 8 undoes 6)
    K_s, c2w_s, size_s = displayed_camera(port.K[0].double(), port.c2w[0].double(), LH, LW, 8)
    assert size_s == (LW, LH)
    stored = render_synthetic(scene_, Cameras(c2w_s[None].float(), K_s[None].float()), LW, LH).image[0]
    paths = [write_png(tmp_path / f"v{i}.png", image) for i, image in enumerate(images[:3])]
    exif = Image.Exif()
    exif[0x0112] = 6
    pixels = (stored.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    Image.fromarray(pixels).save(tmp_path / "IMG_portrait.png", exif=exif.tobytes())
    paths.append(tmp_path / "IMG_portrait.png")
    # read as displayed: the stored render turned upright is the render of the displayed camera
    upright, _ = read_image(paths[3])
    assert tuple(upright.shape) == (3, LW, LH)
    assert (upright - images[3]).abs().max() <= 1.5 / 255  # 8-bit rounding of two renders of one ray set
    cams = Cameras(torch.cat([land.c2w, c2w_s[None].float()]), torch.cat([land.K, K_s[None].float()]))
    save_cameras(tmp_path / "cameras.json", cams, LW, LH, [p.name for p in paths], near=NEAR, far=FAR)
    scene = surfsplat.reconstruct(
        paths, "tiny-synthetic", cameras=tmp_path / "cameras.json", device="cpu", capture=OPTIONS, progress=False
    )
    torch.testing.assert_close(
        scene.cameras.K[3].double(), _expected_network_K(port.K[0], (LH, LW), (LH, LW)), rtol=0, atol=1e-4
    )
    torch.testing.assert_close(scene.cameras.c2w[3], port.c2w[0], rtol=0, atol=1e-5)


def test_a_size_no_camera_fits_names_the_view():
    from surfsplat.data.cameras import CameraSet

    cams = Cameras(torch.eye(4).repeat(2, 1, 1), torch.tensor([[40.0, 0, 24], [0, 40, 16], [0, 0, 1]]).repeat(2, 1, 1))
    given = CameraSet(cams, LW, LH, ["a.png", "b.png"])
    with pytest.raises(SurfSplatInputError, match=r"cameras.json: b.png is 40x40 but the cameras are for 48x32"):
        view_cameras(given, [(LW, LH), (40, 40)], [1, 1], ["a.png", "b.png"], "cameras.json")
    with pytest.raises(SurfSplatInputError, match=r"b.png is 32x48"):  # transposed without an EXIF turn
        view_cameras(given, [(LW, LH), (LH, LW)], [1, 1], ["a.png", "b.png"], "cameras.json")
    with pytest.raises(SurfSplatInputError, match=r"cameras.json: b.png: EXIF orientation 5 shows the photo mirrored"):
        view_cameras(given, [(LW, LH), (LH, LW)], [1, 5], ["a.png", "b.png"], "cameras.json")


def test_mirrored_photos_are_named_in_one_warning(tmp_path, caplog):
    from surfsplat.capture import FrameConfig
    from surfsplat.reconstruction.inputs import read_capture

    paths = []
    for name, orientation in (("a.png", 1), ("b.png", 2), ("c.png", 6), ("d.png", 7)):
        exif = Image.Exif()
        exif[0x0112] = orientation
        Image.new("RGB", (LW, LH), (90, 60, 30)).save(tmp_path / name, exif=exif.tobytes())
        paths.append(tmp_path / name)
    with caplog.at_level(logging.WARNING, logger="surfsplat"):
        views = read_capture(paths, FrameConfig())
    assert views.orientations == [1, 2, 6, 7]
    assert views.sizes == [(LW, LH), (LW, LH), (LH, LW), (LH, LW)]
    warned = [r.getMessage() for r in caplog.records if "mirrored" in r.getMessage()]
    assert len(warned) == 1 and warned[0].startswith("b.png (orientation 2), d.png (orientation 7): shown mirrored")


def test_crop_report_only_where_the_photos_differ_in_shape():
    from surfsplat.reconstruction.sizes import crop_report

    assert crop_report([(48, 32), (48, 32)], ["a", "b"], (32, 32)) is None  # one shape: cropped alike, as before
    assert crop_report([(48, 32), (96, 64)], ["a", "b"], (32, 48)) is None  # one shape, two sizes: nothing lost
    line = crop_report([(48, 32), (32, 48)], ["a", "b"], (32, 48))
    assert line.startswith("the photos differ in shape: every view is cropped to the working size 48x32; ")
    assert "b (32x48) keeps 44%, its top and bottom cut" in line and "a (" not in line
