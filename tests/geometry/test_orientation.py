"""The camera of a photo as displayed (`surfsplat.geometry.orientation`), in closed form: a 3D point
projected by the stored image's camera, its pixel mapped through the EXIF transform, equals the
point projected by the displayed image's camera, for every orientation (turns exactly and rigidly;
mirrors exactly with the reflected frame they need, refused by default). The pixel map itself is
checked against what `read_image` (Pillow's exif_transpose) does to a single lit pixel."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from surfsplat.data.images import read_image
from surfsplat.geometry.cameras import Cameras, validate_c2w, validate_intrinsics
from surfsplat.geometry.orientation import (
    MIRRORED,
    camera_is_of_stored_image,
    displayed_camera,
    displayed_size,
    orientation_transform,
)
from surfsplat.geometry.rotations import quat_to_matrix
from surfsplat.utils.checks import SurfSplatInputError

W, H = 64, 48  # the stored image


def exif_map(orientation: int, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Displayed continuous coordinates of stored ones, written from the tag's table (row 0 / column 0
    of the stored image at 1 top/left ... 8 left/bottom of the displayed one)."""
    return {
        1: (x, y),
        2: (W - x, y),
        3: (W - x, H - y),
        4: (x, H - y),
        5: (y, x),
        6: (H - y, x),
        7: (H - y, W - x),
        8: (y, W - x),
    }[orientation]


def project(K: torch.Tensor, c2w: torch.Tensor, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel coordinates of world points [N, 3] with a camera (any 3x3 frame: a reflection projects too)."""
    R, t = c2w[:3, :3], c2w[:3, 3]
    cam = (points - t) @ R  # R^T (X - t), row-wise
    uvw = cam @ K.T
    return uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]


def _camera(seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[71.0, 0.0, 30.5], [0.0, 83.0, 21.25], [0.0, 0.0, 1.0]], dtype=torch.float64)
    q = torch.randn(4, generator=g, dtype=torch.float64)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = quat_to_matrix(q / q.norm())
    c2w[:3, 3] = torch.randn(3, generator=g, dtype=torch.float64)
    # points in front of the camera: camera-frame points sent to the world
    cam = torch.randn(200, 3, generator=g, dtype=torch.float64) * torch.tensor([1.0, 1.0, 0.5]) + torch.tensor(
        [0.0, 0.0, 4.0], dtype=torch.float64
    )
    points = cam @ c2w[:3, :3].T + c2w[:3, 3]
    return K, c2w, points


@pytest.mark.parametrize("orientation", [1, 3, 6, 8])
def test_turned_photo_projects_like_its_displayed_camera_exactly(orientation):
    K, c2w, points = _camera(orientation)
    K2, c2w2, size = displayed_camera(K, c2w, W, H, orientation)
    u, v = project(K, c2w, points)
    expected = exif_map(orientation, u, v)
    got = project(K2, c2w2, points)
    torch.testing.assert_close(got[0], expected[0], rtol=0, atol=1e-9)
    torch.testing.assert_close(got[1], expected[1], rtol=0, atol=1e-9)
    assert size == ((H, W) if orientation in (6, 8) else (W, H))
    validate_c2w("c2w", c2w2[None])  # a rigid camera: rotated about its optical axis
    validate_intrinsics("K", K2[None])
    Cameras(c2w2[None], K2[None])  # what every later stage takes
    axis = c2w[:3, 2]  # the optical axis and the centre do not move
    torch.testing.assert_close(c2w2[:3, 2], axis, rtol=0, atol=1e-12)
    torch.testing.assert_close(c2w2[:3, 3], c2w[:3, 3], rtol=0, atol=0)
    if orientation in (6, 8):  # fx and fy swap with the axes
        assert (K2[0, 0], K2[1, 1]) == (K[1, 1], K[0, 0])


@pytest.mark.parametrize("orientation", MIRRORED)
def test_mirrored_photo_is_refused_by_default(orientation):
    K, c2w, _ = _camera(0)
    with pytest.raises(SurfSplatInputError, match=f"orientation {orientation} shows the photo mirrored"):
        displayed_camera(K, c2w, W, H, orientation, source="IMG_1.jpg")


@pytest.mark.parametrize("orientation", MIRRORED)
def test_mirrored_photo_projects_exactly_with_a_reflected_frame(orientation):
    K, c2w, points = _camera(10 + orientation)
    K2, c2w2, _ = displayed_camera(K, c2w, W, H, orientation, reflection=True)
    u, v = project(K, c2w, points)
    expected = exif_map(orientation, u, v)
    got = project(K2, c2w2, points)
    torch.testing.assert_close(got[0], expected[0], rtol=0, atol=1e-9)
    torch.testing.assert_close(got[1], expected[1], rtol=0, atol=1e-9)
    assert float(torch.linalg.det(c2w2[:3, :3])) == pytest.approx(-1.0)  # a reflection, not a rigid camera
    validate_intrinsics("K", K2[None])  # K' is still a pinhole with positive focal lengths
    with pytest.raises(SurfSplatInputError, match="not a rigid camera transform"):
        validate_c2w("c2w", c2w2[None])


def test_skewed_K_cannot_be_transposed():
    K, c2w, _ = _camera(0)
    K[0, 1] = 0.5
    with pytest.raises(SurfSplatInputError, match="skewed K"):
        displayed_camera(K, c2w, W, H, 6)
    K2, c2w2, _ = displayed_camera(K, c2w, W, H, 3)  # a half turn keeps the layout: exact with skew
    _, _, points = _camera(0)
    u, v = project(K, c2w, points)
    got = project(K2, c2w2, points)
    torch.testing.assert_close(got[0], W - u, rtol=0, atol=1e-9)
    torch.testing.assert_close(got[1], H - v, rtol=0, atol=1e-9)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_pixel_map_is_what_read_image_does(tmp_path, orientation):
    """One lit pixel of the stored image: its centre (j + 0.5, i + 0.5) mapped by orientation_transform
    is the centre of the lit pixel of the photo read_image returns."""
    i, j = 5, 11
    stored = np.zeros((H, W, 3), dtype=np.uint8)
    stored[i, j] = 255
    exif = Image.Exif()
    exif[0x0112] = orientation
    path = tmp_path / "one.png"
    Image.fromarray(stored).save(path, exif=exif.tobytes())
    rgb, _ = read_image(path)
    assert (rgb.shape[2], rgb.shape[1]) == displayed_size(orientation, W, H)
    rows, cols = torch.nonzero(rgb[0] > 0.5, as_tuple=True)
    mapped = orientation_transform(orientation, W, H) @ torch.tensor([j + 0.5, i + 0.5, 1.0], dtype=torch.float64)
    assert (float(cols[0]) + 0.5, float(rows[0]) + 0.5) == (float(mapped[0]), float(mapped[1]))
    assert len(rows) == 1


def test_camera_file_size_tells_stored_from_displayed_for_turns_of_90_degrees():
    # a 4032x3024 stored photo displayed 3024x4032 (orientation 6); cameras calibrated at half size
    assert camera_is_of_stored_image((2016, 1512), (3024, 4032), 6) is True
    assert camera_is_of_stored_image((1512, 2016), (3024, 4032), 6) is False
    assert camera_is_of_stored_image((4032, 3024), (4032, 3024), 3) is None  # same size either way
    assert camera_is_of_stored_image((500, 500), (500, 500), 6) is None  # square: size cannot tell
    assert camera_is_of_stored_image((640, 360), (3024, 4032), 6) is None  # neither: the caller reports it


def test_orientation_must_be_one_to_eight():
    K, c2w, _ = _camera(0)
    for bad in (0, 9, True):
        with pytest.raises(SurfSplatInputError, match="EXIF orientation 1-8"):
            displayed_camera(K, c2w, W, H, bad)


@pytest.mark.parametrize("orientation", range(1, 9))
def test_displayed_image_is_what_pillows_exif_transpose_does(orientation):
    """The tensor turn of stored pixels (photos, masks, depth after undistortion) equals Pillow's
    `exif_transpose` of the same pixels tagged with the orientation, and `stored_image` undoes it."""
    from PIL import ImageOps

    from surfsplat.geometry.orientation import displayed_image, stored_image

    rng = np.random.default_rng(orientation)
    stored = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    tagged = Image.fromarray(stored)
    exif = tagged.getexif()
    exif[0x0112] = orientation
    tagged.info["exif"] = exif.tobytes()
    reference = np.asarray(ImageOps.exif_transpose(tagged))
    ours = displayed_image(torch.from_numpy(stored).permute(2, 0, 1), orientation).permute(1, 2, 0).numpy()
    assert ours.shape == reference.shape and np.array_equal(ours, reference)
    back = stored_image(torch.from_numpy(reference.copy()).permute(2, 0, 1), orientation)
    assert torch.equal(back, torch.from_numpy(stored).permute(2, 0, 1))


def test_lens_of_turned_photos_keeps_its_stored_projection_and_round_trips():
    """A Lens seeing turned photos: recorded and read back with its orientation; the projection functions
    refuse it (they are of the stored pixels: `stored()`), and its pinhole is the stored pinhole turned."""
    from surfsplat.data.cameras import pinhole_of, turned_pinhole
    from surfsplat.geometry.lens import Lens, project, undistorted_pinhole

    lens = Lens("OPENCV", 100, 75, (90.0, 92.0, 51.5, 38.7, -0.2, 0.05, 0.001, -0.002))
    turned = lens.turned(6)
    assert Lens.from_dict(turned.to_dict()) == turned and "orientation" not in lens.to_dict()
    assert turned.rescaled(50, 37).orientation == 6 and turned.stored() == lens
    with pytest.raises(ValueError, match="EXIF orientation 6"):
        project(turned, torch.tensor([[0.0, 0.0, 1.0]]))
    with pytest.raises(SurfSplatInputError, match="orientation must be an EXIF turn"):
        lens.turned(5)  # a mirrored photo has no camera
    flat = undistorted_pinhole(lens)
    shown = pinhole_of(turned)
    assert (shown.width, shown.height) == (flat.height, flat.width)
    K, _, _ = displayed_camera(flat.intrinsics(), torch.eye(4, dtype=torch.float64), flat.width, flat.height, 6)
    torch.testing.assert_close(shown.intrinsics(), K, rtol=0, atol=0)
    assert turned_pinhole(shown, 8) == pinhole_of(lens)  # 8 undoes 6
