"""One capture, four camera files: the distorted fixture's COLMAP model (binary and text), nerfstudio's and
instant-ngp's transforms.json give `reconstruct` the same pinhole, working crop and photos, bit for bit,
so a reconstruction does not depend on which tool processed the capture (benchmarks/undistort.py's
reconstruct part runs DTU through both a COLMAP model and nerfstudio's file on this premise)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from surfsplat.capture import FrameConfig
from surfsplat.data.cameras import load_cameras
from surfsplat.data.images import read_image
from surfsplat.data.transforms import rescale_and_crop, working_crop
from surfsplat.reconstruction.inputs import read_capture
from surfsplat.reconstruction.pipeline import DEFAULT_SIZE_MULTIPLE, _undistorted_views, _working_shape

DISTORTED = Path(__file__).resolve().parents[1] / "data" / "distorted"
DIALECTS = ["sparse/0", "sparse/text", "transforms.json", "instant_ngp/transforms.json"]
HOLDOUT_EVERY = 2  # views 0, 2, 4 held out, as `--holdout-every 2` picks them


def _inputs(given: str) -> dict:
    """What reconstruct's stages after loading see of the fixture read through `given`: the pinhole K and
    size, the working crop, and the context and held-out photos at the working size with their K."""
    photos = sorted((DISTORTED / "images").glob("*.png"))
    cams = load_cameras(DISTORTED / given)
    views, K, c2w = _undistorted_views(read_capture(photos, FrameConfig()), cams, given)
    shape = _working_shape(views, None, 512, DEFAULT_SIZE_MULTIPLE)
    images, K_work = [], []
    for i in range(len(views)):
        image, k, _ = rescale_and_crop(views.image(i)[None], K[i : i + 1].to(torch.float32), shape)
        images.append(image[0])
        K_work.append(k[0])
    held = [i for i in range(len(views)) if i % HOLDOUT_EVERY == 0]
    return {
        "names": list(views.names),
        "pinhole": [pinhole for _, pinhole in views.lenses],
        "K": K,
        "crop": working_crop(views.width, views.height, shape),
        "images": torch.stack(images),
        "K_work": torch.stack(K_work),
        "held_out": torch.stack([images[i] for i in held]),
        "c2w": c2w,
    }


@pytest.fixture(scope="module")
def colmap() -> dict:
    return _inputs("sparse/0")


@pytest.mark.parametrize("given", DIALECTS[1:])
def test_every_camera_file_gives_the_same_pinhole_crop_and_photos(colmap: dict, given: str) -> None:
    other = _inputs(given)
    assert other["names"] == colmap["names"]
    assert other["pinhole"] == colmap["pinhole"]  # Lens equality: model, size and parameters exactly
    assert other["crop"] == colmap["crop"]
    assert torch.equal(other["K"], colmap["K"]) and torch.equal(other["K_work"], colmap["K_work"])
    assert torch.equal(other["images"], colmap["images"])
    assert torch.equal(other["held_out"], colmap["held_out"])
    # the poses go through other rotations (COLMAP's quaternions, OpenGL axes in JSON): the same to 1e-9
    torch.testing.assert_close(other["c2w"], colmap["c2w"], atol=1e-9, rtol=0)


def test_the_photos_compared_are_undistorted(colmap: dict) -> None:
    """The photos above are the lens's photos undistorted (another size, other pixels), not the files
    read as they are: the comparison is of the undistortion each camera file asks for."""
    crop = colmap["crop"]
    raw, _ = read_image(DISTORTED / "images" / colmap["names"][0], background=None)
    assert (crop.source_width, crop.source_height) != tuple(raw.shape[:0:-1])
    plain, _, _ = rescale_and_crop(raw[None], torch.eye(3)[None], (crop.height, crop.width))
    assert (plain[0] - colmap["images"][0]).abs().mean() > 3 / 255
