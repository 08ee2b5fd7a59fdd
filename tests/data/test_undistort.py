"""Undistortion of pixels: maps against OpenCV's, photos distorted with known coefficients undistorted back."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from surfsplat.data.undistort import distort, distort_maps, undistort, undistort_maps
from surfsplat.geometry.lens import Lens, undistorted_pinhole
from surfsplat.testing.lenses import CALIBRATIONS, HEIGHT, WIDTH
from surfsplat.utils.checks import SurfSplatInputError

pytestmark = pytest.mark.usefixtures("one_torch_thread")

HERE = Path(__file__).resolve().parent
FIXTURE_IMAGES = HERE / "dtu_scan24" / "images_16"  # 100x75
SHARED_IMAGES = HERE.parents[2] / "shared" / "data" / "dtu_scan24" / "images_4"  # 400x300, beside the repository
OPENCV_COEFFS = (-0.1, 0.05, 0.001, -0.001)  # k1, k2, p1, p2
FISHEYE_COEFFS = (0.05, -0.01, 0.002, 0.0)  # k1, k2, k3, k4


def _photo(folder: Path, index: int = 0) -> torch.Tensor:
    path = sorted(folder.glob("*.png"))[index]
    return torch.from_numpy(np.array(Image.open(path).convert("RGB"))).permute(2, 0, 1).float() / 255


def _lenses(width: int, height: int, model: str) -> tuple[Lens, Lens]:
    """A pinhole of about 64 degrees across (f = 0.8 W) and the same camera with a lens."""
    f = 0.8 * width
    K = (f, f, width / 2 + 0.3, height / 2 - 0.2)
    coeffs = OPENCV_COEFFS if model == "OPENCV" else FISHEYE_COEFFS
    return Lens("PINHOLE", width, height, K), Lens(model, width, height, K + coeffs)


def _cv_K(lens: Lens) -> np.ndarray:
    """K in OpenCV's pixel convention (the top-left pixel's centre at (0, 0): cx, cy half a pixel less)."""
    fx, fy, cx, cy = lens.focal_and_centre
    return np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]], dtype=np.float64)


def _round_trip(image: torch.Tensor, model: str, there: str, back: str) -> tuple[float, float, float]:
    """(MAE of distort -> undistort over the valid region, MAE of the distorted photo against the
    original, fraction of the image valid); MAE in 1/255 units."""
    _, h, w = image.shape
    pinhole, lens = _lenses(w, h, model)
    distorted = distort(image, pinhole, lens, there)
    restored = undistort(distorted, lens, pinhole, back)
    ones = torch.ones(1, h, w)
    valid = undistort(distort(ones, pinhole, lens), lens, pinhole)[0] >= 1 - 1e-6
    mae = (restored - image).abs().mean(0)[valid].mean().item() * 255
    moved = (distorted - image).abs().mean().item() * 255
    return mae, moved, valid.float().mean().item()


@pytest.mark.parametrize("model", ["OPENCV", "OPENCV_FISHEYE"])
def test_undistort_maps_match_opencv(model: str) -> None:
    """Our maps (pinhole pixel -> lens pixel) equal cv2.initUndistortRectifyMap's, with the half-pixel
    shift of OpenCV's pixel convention, to 1e-3 px (float32 maps)."""
    _, lens = _lenses(400, 300, model)
    pinhole = undistorted_pinhole(lens)
    D = np.array(lens.extra_params, dtype=np.float64)
    size = (pinhole.width, pinhole.height)
    if model == "OPENCV":
        ref_x, ref_y = cv2.initUndistortRectifyMap(_cv_K(lens), D, None, _cv_K(pinhole), size, cv2.CV_32FC1)
    else:
        ref_x, ref_y = cv2.fisheye.initUndistortRectifyMap(
            _cv_K(lens), D, np.eye(3), _cv_K(pinhole), size, cv2.CV_32FC1
        )
    map_x, map_y = undistort_maps(lens, pinhole)
    assert not np.isnan(map_x).any()  # COLMAP's pinhole: no blank pixel
    assert max(np.abs(map_x - ref_x).max(), np.abs(map_y - ref_y).max()) <= 1e-3


@pytest.mark.parametrize("model", ["OPENCV", "OPENCV_FISHEYE"])
def test_distort_maps_match_opencv(model: str) -> None:
    """Our inverse maps (lens pixel -> pinhole pixel) equal OpenCV's undistortPoints of every lens pixel."""
    pinhole, lens = _lenses(100, 75, model)
    ys, xs = np.mgrid[0:75, 0:100].astype(np.float64)
    pts = np.stack([xs, ys], -1).reshape(-1, 1, 2)
    D = np.array(lens.extra_params, dtype=np.float64)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    if model == "OPENCV":
        ref = cv2.undistortPoints(pts, _cv_K(lens), D, None, _cv_K(pinhole), criteria=crit)
    else:
        ref = cv2.fisheye.undistortPoints(pts, _cv_K(lens), D, None, _cv_K(pinhole), criteria=crit)
    ref = ref.reshape(75, 100, 2)
    map_x, map_y = distort_maps(pinhole, lens)
    inside = ~np.isnan(map_x)
    assert inside.mean() > 0.75  # the fisheye's corners see beyond the pinhole
    assert max(np.abs(map_x - ref[..., 0])[inside].max(), np.abs(map_y - ref[..., 1])[inside].max()) <= 1e-3
    # NaN exactly where the lens pixel's ray leaves the pinhole's image area [-0.5, W - 0.5] here
    outside = (ref[..., 0] < -0.5) | (ref[..., 0] > 99.5) | (ref[..., 1] < -0.5) | (ref[..., 1] > 74.5)
    assert np.array_equal(~inside, outside)


FOLDERS = [pytest.param(FIXTURE_IMAGES, id="100x75")]
if SHARED_IMAGES.is_dir():
    FOLDERS.append(pytest.param(SHARED_IMAGES, id="400x300"))
else:
    FOLDERS.append(
        pytest.param(SHARED_IMAGES, id="400x300", marks=pytest.mark.skip(reason="../shared/data/dtu_scan24 absent"))
    )


@pytest.mark.parametrize("folder", FOLDERS)
@pytest.mark.parametrize("model", ["OPENCV", "OPENCV_FISHEYE"])
def test_distorted_photo_undistorts_back(folder: Path, model: str) -> None:
    """DTU photos distorted here with known coefficients, then undistorted: two resamplings.
    Bicubic both ways: MAE <= 2/255 (measured 0.9-1.6). Bilinear both ways, the default: MAE <= 3/255
    (measured 1.9-2.6; a half-pixel shift and back, two bilinear resamplings with no distortion,
    costs 2.4-6.2/255 on the same photos, so this is bilinear's own blur, not a misplaced pixel)."""
    image = _photo(folder)
    mae, moved, valid = _round_trip(image, model, "bicubic", "bicubic")
    assert mae <= 2.0 and moved >= 10.0 and valid >= 0.95
    mae, _, _ = _round_trip(image, model, "bilinear", "bilinear")
    assert mae <= 3.0


def test_wrong_lens_does_not_undistort_back() -> None:
    """The round trip fails with the wrong coefficients (the sign of k1 flipped): the test can fail."""
    image = _photo(FIXTURE_IMAGES)
    pinhole, lens = _lenses(100, 75, "OPENCV")
    wrong = Lens("OPENCV", 100, 75, lens.params[:4] + (0.1,) + lens.params[5:])
    restored = undistort(distort(image, pinhole, lens, "bicubic"), wrong, pinhole, "bicubic")
    assert (restored - image).abs()[:, 5:-5, 5:-5].mean().item() * 255 > 4.0  # measured 5.8


@pytest.mark.parametrize("model", ["OPENCV", "OPENCV_FISHEYE"])
def test_opencv_distorted_photo_undistorts_back(model: str) -> None:
    """A photo distorted by OpenCV itself (each lens pixel lifted by cv2.undistortPoints, the pinhole
    photo sampled there by cv2.remap) is undistorted back by ours."""
    image = _photo(FIXTURE_IMAGES, 3)
    pinhole, lens = _lenses(100, 75, model)
    ys, xs = np.mgrid[0:75, 0:100].astype(np.float64)
    pts = np.stack([xs, ys], -1).reshape(-1, 1, 2)
    D = np.array(lens.extra_params, dtype=np.float64)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    undist = cv2.undistortPoints if model == "OPENCV" else cv2.fisheye.undistortPoints
    src = undist(pts, _cv_K(lens), D, None, _cv_K(pinhole), criteria=crit).reshape(75, 100, 2).astype(np.float32)
    hwc = image.permute(1, 2, 0).numpy()
    by_cv = cv2.remap(hwc, src[..., 0], src[..., 1], cv2.INTER_CUBIC, borderMode=cv2.BORDER_CONSTANT)
    by_cv = torch.from_numpy(np.clip(by_cv, 0, 1)).permute(2, 0, 1)
    restored = undistort(by_cv, lens, pinhole, "bicubic")
    valid = undistort(distort(torch.ones(1, 75, 100), pinhole, lens), lens, pinhole)[0] >= 1 - 1e-6
    # one pixel in from the valid region's edge: OpenCV's BORDER_CONSTANT blends black in there
    valid = torch.from_numpy(cv2.erode(valid.numpy().astype(np.uint8), np.ones((3, 3), np.uint8))).bool()
    assert (restored - image).abs().mean(0)[valid].mean().item() * 255 <= 2.0


def test_undistorted_pinhole_has_no_blank_pixel() -> None:
    """COLMAP's default (blank_pixels 0): every pixel of the pinhole shows the photo."""
    for model in ("OPENCV", "OPENCV_FISHEYE"):
        _, lens = _lenses(100, 75, model)
        pinhole = undistorted_pinhole(lens)
        cover = undistort(torch.ones(1, 75, 100), lens, pinhole)
        assert cover.shape == (1, pinhole.height, pinhole.width) and bool((cover == 1).all())
        wider = Lens("PINHOLE", pinhole.width + 20, pinhole.height + 20, pinhole.params[:2] + (60.0, 47.0))
        assert bool((undistort(torch.ones(1, 75, 100), lens, wider) == 0).any())  # a wider view has blanks


def test_bilinear_matches_a_reference_sampler() -> None:
    """undistort is bilinear sampling at the maps: against torch's grid_sample (exact weights) within
    cv2.remap's 1/32-pixel weight quantization."""
    image = _photo(FIXTURE_IMAGES, 5)
    _, lens = _lenses(100, 75, "OPENCV")
    pinhole = undistorted_pinhole(lens)
    ours = undistort(image, lens, pinhole)
    map_x, map_y = undistort_maps(lens, pinhole)
    # grid_sample, align_corners=False: -1 and 1 are the image's outer edges; clamped = BORDER_REPLICATE
    gx = torch.from_numpy((map_x + 0.5) / 100 * 2 - 1)
    gy = torch.from_numpy((map_y + 0.5) / 75 * 2 - 1)
    grid = torch.stack([gx, gy], -1)[None]
    ref = torch.nn.functional.grid_sample(
        image[None], grid, mode="bilinear", padding_mode="border", align_corners=False
    )[0]
    diff = (ours - ref).abs()
    assert diff.max().item() <= 1 / 32 and diff.mean().item() <= 2e-3


def test_nearest_picks_source_pixels() -> None:
    """mode="nearest" (depth): every output value is the input pixel nearest to the map's point."""
    _, lens = _lenses(100, 75, "OPENCV_FISHEYE")
    pinhole = undistorted_pinhole(lens)
    depth = torch.rand(1, 75, 100, generator=torch.Generator().manual_seed(0)) * 10 + 1
    out = undistort(depth, lens, pinhole, "nearest")[0]
    map_x, map_y = undistort_maps(lens, pinhole)
    j = np.clip(np.floor(map_x + 0.5), 0, 99).astype(int)
    i = np.clip(np.floor(map_y + 0.5), 0, 74).astype(int)
    ties = (np.abs(map_x - np.round(map_x) - 0.5) < 1e-3) | (np.abs(map_y - np.round(map_y) - 0.5) < 1e-3)
    expect = depth[0].numpy()[i, j]
    assert np.array_equal(out.numpy()[~ties], expect[~ties]) and (~ties).mean() > 0.99


def test_batches_dtypes_devices() -> None:
    """[N, C, H, W] is each image undistorted; uint8 and bool stay their type; float32 photos in [0, 1]."""
    _, lens = _lenses(100, 75, "OPENCV")
    pinhole = undistorted_pinhole(lens)
    stack = torch.stack([_photo(FIXTURE_IMAGES, i) for i in range(3)])  # [3, 3, 75, 100]
    both = undistort(stack, lens, pinhole)
    for i in range(3):
        assert torch.equal(both[i], undistort(stack[i], lens, pinhole))
    assert both.dtype == torch.float32 and 0 <= both.min() and both.max() <= 1
    cubic = undistort(stack, lens, pinhole, "bicubic")
    assert 0 <= cubic.min() and cubic.max() <= 1
    u8 = undistort((stack[0] * 255).round().to(torch.uint8), lens, pinhole)
    assert u8.dtype == torch.uint8 and (u8.float() / 255 - both[0]).abs().max() <= 2 / 255
    mask = torch.zeros(1, 75, 100, dtype=torch.bool)
    mask[:, 20:50, 30:70] = True
    m = undistort(mask, lens, pinhole, "nearest")
    assert m.dtype == torch.bool and 0.8 < m.sum().item() / mask.sum().item() < 1.2


def test_maps_are_cached_per_lens_pair() -> None:
    _, lens = _lenses(100, 75, "OPENCV")
    pinhole = undistorted_pinhole(lens)
    first = undistort_maps(lens, pinhole)
    same = undistort_maps(Lens(lens.model, lens.width, lens.height, tuple(lens.params)), pinhole)
    assert first[0] is same[0] and not first[0].flags.writeable


def test_bad_inputs_raise() -> None:
    pinhole, lens = _lenses(100, 75, "OPENCV")
    with pytest.raises(SurfSplatInputError, match="undistort: image is 80x75 but its lens is 100x75"):
        undistort(torch.zeros(3, 75, 80), lens, pinhole)
    with pytest.raises(SurfSplatInputError, match="mode must be one of bilinear, bicubic, nearest"):
        undistort(torch.zeros(3, 75, 100), lens, pinhole, "area")
    with pytest.raises(SurfSplatInputError, match="expected a pinhole Lens .* got OPENCV"):
        undistort(torch.zeros(3, 75, 100), lens, lens)
    with pytest.raises(SurfSplatInputError, match=r"image must be \[C, H, W\] or \[N, C, H, W\]"):
        undistort(torch.zeros(75, 100), lens, pinhole)


@pytest.mark.parametrize("folder", ["distorted", "distorted/fisheye"])
def test_equals_colmaps_image_undistorter(folder: str) -> None:
    """8-bit photos undistorted by ours equal pycolmap's `undistort_image` (COLMAP's
    image_undistorter, default options): the same size, every value within one 8-bit level
    (measured: equal but for at most two values in a photo)."""
    import json

    import pycolmap

    truth = json.loads((HERE / folder / "truth.json").read_text())
    lens = Lens.from_dict(truth["lens"])
    cam = pycolmap.Camera(model=lens.model, width=lens.width, height=lens.height, params=list(lens.params))
    pinhole = undistorted_pinhole(lens)
    for view in truth["views"]:
        photo = np.array(Image.open(HERE / folder / view["image"]).convert("RGB"))
        bitmap, ref_cam = pycolmap.undistort_image(
            pycolmap.UndistortCameraOptions(), pycolmap.Bitmap.from_array(photo), cam
        )
        ref = bitmap.to_array().astype(np.int16)
        ours = undistort(torch.from_numpy(photo).permute(2, 0, 1).contiguous(), lens, pinhole)
        ours = ours.permute(1, 2, 0).numpy().astype(np.int16)
        assert (ref_cam.width, ref_cam.height) == (pinhole.width, pinhole.height) == ours.shape[1::-1]
        diff = np.abs(ours - ref)
        assert diff.max() <= 1 and (diff > 0).mean() <= 1e-3


@pytest.mark.parametrize("model", [m for m in CALIBRATIONS if m not in ("SIMPLE_PINHOLE", "PINHOLE")])
def test_equals_colmaps_image_undistorter_every_model(model: str) -> None:
    """The same for every lens model (the realistic calibrations, rescaled to 100x75), on a DTU photo
    distorted here."""
    import pycolmap

    lens = Lens(model, WIDTH, HEIGHT, CALIBRATIONS[model]).rescaled(100, 75)
    fx, fy, cx, cy = lens.focal_and_centre
    source = Lens("PINHOLE", 100, 75, (fx, fy, cx, cy))
    photo = (distort(_photo(FIXTURE_IMAGES, 7), source, lens, "bicubic") * 255).round().to(torch.uint8)
    hwc = photo.permute(1, 2, 0).contiguous().numpy()
    cam = pycolmap.Camera(model=model, width=100, height=75, params=list(lens.params))
    bitmap, _ = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(), pycolmap.Bitmap.from_array(hwc), cam)
    ref = bitmap.to_array().astype(np.int16)
    ours = undistort(photo, lens, undistorted_pinhole(lens)).permute(1, 2, 0).numpy().astype(np.int16)
    assert ours.shape == ref.shape
    diff = np.abs(ours - ref)
    assert diff.max() <= 1 and (diff > 0).mean() <= 1e-3
