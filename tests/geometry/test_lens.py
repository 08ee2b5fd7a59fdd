"""COLMAP's camera models: `project` / `unproject` against pycolmap and OpenCV, round trips, pinholes."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pycolmap
import pytest
import torch

from surfsplat.geometry.lens import CAMERA_MODELS, Lens, project, undistorted_pinhole, unproject
from surfsplat.testing.lenses import CALIBRATIONS, HEIGHT, WIDTH
from surfsplat.utils.checks import SurfSplatInputError

W, H = WIDTH, HEIGHT
LENSES = CALIBRATIONS  # every model 0-10, realistic (see surfsplat.testing.lenses)
MODELS = [name for name, _ in CAMERA_MODELS.values()]
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_every_model_has_a_calibration() -> None:
    assert sorted(LENSES) == sorted(MODELS) and len(MODELS) == 11


def _pair(model: str, params: tuple[float, ...] | None = None) -> tuple[Lens, pycolmap.Camera]:
    params = LENSES[model] if params is None else params
    return Lens(model, W, H, params), pycolmap.Camera(model=model, width=W, height=H, params=list(params))


def _points(seed: int, n: int = 2000, spread: float = 0.65) -> np.ndarray:
    """Camera-frame points in front of the camera: random directions up to `spread` in x/z and y/z
    (the image and beyond), random depths, plus points within 1e-3 of the axis (the models' series
    and epsilon branches) and one exactly on it."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-spread, spread, (n, 2))
    xy[:50] *= 1e-3
    xy[50] = 0.0
    z = rng.uniform(0.2, 20.0, (n, 1))
    return np.concatenate([xy * z, z], axis=1)


def _pixels(seed: int, n: int = 2000) -> np.ndarray:
    """Pixels over the whole image (its border included) and the principal point's neighbourhood."""
    rng = np.random.default_rng(seed)
    px = np.stack([rng.uniform(0.0, W, n), rng.uniform(0.0, H, n)], axis=1)
    px[:50] = [W / 2, H / 2] + rng.uniform(-1e-2, 1e-2, (50, 2))
    return px


@pytest.mark.parametrize("model", MODELS)
def test_project_matches_pycolmap(model: str) -> None:
    lens, cam = _pair(model)
    pts = _points(1)
    ours = project(lens, torch.from_numpy(pts)).numpy()
    ref = cam.img_from_cam(pts)
    assert np.isfinite(ref).all()
    assert np.abs(ours - ref).max() <= 1e-6


@pytest.mark.parametrize("model", MODELS)
def test_unproject_matches_pycolmap(model: str) -> None:
    lens, cam = _pair(model)
    px = _pixels(2)
    ours = unproject(lens, torch.from_numpy(px)).numpy()
    ref = cam.cam_from_img(px)
    assert np.isfinite(ref).all()
    f = float(np.mean(lens.focal_and_centre[:2]))
    # normalized coordinates to 1e-6 px at the focal length, and the same in pixels through a pinhole
    assert np.abs(ours - ref).max() <= 1e-6 / f
    assert np.abs(ours - ref).max() * f <= 1e-6


@pytest.mark.parametrize(
    ("model", "params"),
    [
        ("FOV", (500.0, 510.0, 321.5, 238.7, 0.005)),  # omega^2 < 1e-4: COLMAP's series in omega
        ("FOV", (500.0, 510.0, 321.5, 238.7, 0.0)),  # omega = 0: the pinhole
        ("FOV", (500.0, 510.0, 321.5, 238.7, 1.6)),  # strong: series in the radius near the axis only
    ],
)
def test_fov_branches_match_pycolmap(model: str, params: tuple[float, ...]) -> None:
    lens, cam = _pair(model, params)
    pts = _points(3)
    assert np.abs(project(lens, torch.from_numpy(pts)).numpy() - cam.img_from_cam(pts)).max() <= 1e-6
    px = _pixels(4)
    ref = cam.cam_from_img(px)
    assert np.abs(unproject(lens, torch.from_numpy(px)).numpy() - ref).max() * 500 <= 1e-6


@pytest.mark.parametrize("model", MODELS)
def test_round_trip_over_the_image(model: str) -> None:
    """project(unproject(p)) = p over the image: the pixel centres of every third row and column,
    and every pixel of the border."""
    lens, _ = _pair(model)
    rows = torch.unique(torch.cat([torch.arange(0, H, 3), torch.tensor([H - 1])]))
    cols = torch.unique(torch.cat([torch.arange(0, W, 3), torch.tensor([W - 1])]))
    ys, xs = torch.meshgrid(rows + 0.5, torch.arange(W) + 0.5, indexing="ij")
    ys2, xs2 = torch.meshgrid(torch.arange(H) + 0.5, cols + 0.5, indexing="ij")
    px = torch.cat([torch.stack([xs, ys], -1).reshape(-1, 2), torch.stack([xs2, ys2], -1).reshape(-1, 2)])
    px = px.to(torch.float64)
    n = unproject(lens, px)
    back = project(lens, torch.cat([n, torch.ones_like(n[..., :1])], dim=-1))
    assert torch.isfinite(back).all()
    assert (back - px).abs().max().item() <= 1e-6


@pytest.mark.parametrize("model", ["SIMPLE_PINHOLE", "PINHOLE", "OPENCV", "FULL_OPENCV", "RADIAL", "FOV"])
def test_zero_distortion_is_K(model: str) -> None:
    """With no distortion every perspective model is K [x/z, y/z, 1]; its inverse is K^-1."""
    distorted = Lens(model, W, H, LENSES[model])
    first = len(distorted.params) - len(distorted.extra_params)
    lens = Lens(model, W, H, distorted.params[:first] + (0.0,) * len(distorted.extra_params))
    assert lens.is_pinhole
    K = lens.intrinsics()
    fx, fy, cx, cy = lens.focal_and_centre
    assert torch.equal(K, torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=torch.float64))
    pts = torch.from_numpy(_points(5))
    hom = pts @ K.T
    assert (project(lens, pts) - hom[:, :2] / hom[:, 2:]).abs().max().item() <= 1e-9
    px = torch.from_numpy(_pixels(6))
    ray = torch.cat([px, torch.ones_like(px[:, :1])], dim=1) @ torch.linalg.inv(K).T
    assert (unproject(lens, px) - ray[:, :2]).abs().max().item() <= 1e-12


def _K(lens: Lens) -> np.ndarray:
    fx, fy, cx, cy = lens.focal_and_centre
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)


@pytest.mark.parametrize("model", ["OPENCV", "FULL_OPENCV"])
def test_project_matches_opencv(model: str) -> None:
    """OPENCV is OpenCV's (k1, k2, p1, p2); FULL_OPENCV its rational model (k1, k2, p1, p2, k3, k4,
    k5, k6: eight coefficients select CALIB_RATIONAL_MODEL's formula in projectPoints)."""
    lens, _ = _pair(model)
    pts = _points(7)
    dist = np.array(lens.extra_params, dtype=np.float64)
    ref, _ = cv2.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3), _K(lens), dist)
    assert np.abs(project(lens, torch.from_numpy(pts)).numpy() - ref[:, 0, :]).max() <= 1e-6


def test_opencv_fisheye_matches_opencv() -> None:
    lens, _ = _pair("OPENCV_FISHEYE")
    pts = _points(8, spread=1.2)  # up to about 60 degrees off the axis
    D = np.array(lens.extra_params, dtype=np.float64)
    ref, _ = cv2.fisheye.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3), _K(lens), D)
    assert np.abs(project(lens, torch.from_numpy(pts)).numpy() - ref[:, 0, :]).max() <= 1e-6


def test_behind_the_camera_is_nan_as_pycolmap() -> None:
    lens, cam = _pair("OPENCV")
    pts = np.array([[0.1, 0.2, -1.0], [0.3, 0.0, 0.0], [0.1, 0.2, 1.0]])
    ref = cam.img_from_cam(pts)
    ours = project(lens, torch.from_numpy(pts)).numpy()
    assert np.isnan(ref[:2]).all() and np.isnan(ours[:2]).all()
    assert np.abs(ours[2] - ref[2]).max() <= 1e-9


def test_no_inverse_is_nan_as_pycolmap() -> None:
    """Beyond the fold of a strong barrel distortion (1 + k r^2 with k = -2 has its maximum radius
    0.27 at r = 0.41) COLMAP's iteration does not converge: NaN for both; pixels inside converge."""
    lens, cam = _pair("SIMPLE_RADIAL", (500.0, 320.0, 240.0, -2.0))
    px = np.array([[320.0 + 500 * 0.4, 240.0], [320.0 + 500 * 0.1, 240.0 + 500 * 0.05]])
    ref = cam.cam_from_img(px)
    ours = unproject(lens, torch.from_numpy(px)).numpy()
    assert np.isnan(ref[0]).all() and np.isnan(ours[0]).all()
    assert np.abs(ours[1] - ref[1]).max() <= 1e-12


def test_fisheye_beyond_90_degrees_follows_colmap() -> None:
    """A fisheye pixel whose ray is beyond 90 degrees: COLMAP returns the theta vector unscaled."""
    lens, cam = _pair("OPENCV_FISHEYE", (150.0, 150.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0))
    px = np.array([[320.0 + 150 * 1.8, 240.0], [5.0, 5.0]])  # theta 1.8 rad, and a corner at theta 2.6
    assert np.abs(unproject(lens, torch.from_numpy(px)).numpy() - cam.cam_from_img(px)).max() <= 1e-9


def test_batch_shapes_and_dtypes() -> None:
    lens, _ = _pair("OPENCV")
    pts = torch.from_numpy(_points(9, n=2 * 4 * 25)).reshape(2, 4, 25, 3)
    flat = project(lens, pts.reshape(-1, 3))
    assert torch.equal(project(lens, pts), flat.reshape(2, 4, 25, 2))
    assert project(lens, pts.float()).dtype == torch.float32
    assert (project(lens, pts.float()).double() - project(lens, pts)).abs().max() <= 1e-3
    px = flat.reshape(2, 100, 2)
    assert torch.equal(unproject(lens, px), unproject(lens, flat).reshape(2, 100, 2))


def test_bad_shapes_raise() -> None:
    lens, _ = _pair("OPENCV")
    with pytest.raises(SurfSplatInputError, match=r"points: expected a tensor of shape \[\.\.\., 3\]"):
        project(lens, torch.zeros(4, 2))
    with pytest.raises(SurfSplatInputError, match=r"pixels: expected a tensor of shape \[\.\.\., 2\]"):
        unproject(lens, torch.zeros(4, 3))


def test_pinhole_pixel_centre_convention() -> None:
    """The top-left pixel's centre (0.5, 0.5) is where a pinhole with cx = cy = 0 sees the ray
    (0.5/f, 0.5/f): COLMAP's convention, this project's (K' = diag(s, s, 1) K at s-times the size)."""
    lens = Lens("PINHOLE", 4, 3, (2.0, 2.0, 2.0, 1.5))
    centre = unproject(lens, torch.tensor([[2.0, 1.5], [0.5, 0.5]], dtype=torch.float64))
    assert torch.equal(centre[0], torch.zeros(2, dtype=torch.float64))
    assert torch.allclose(centre[1], torch.tensor([-0.75, -0.5], dtype=torch.float64), atol=0, rtol=0)
    assert math.isclose(float(project(lens, torch.tensor([0.0, 0.0, 1.0]))[0]), 2.0)


# --- undistorted_pinhole: COLMAP's UndistortCamera ---------------------------------------------

MORE_LENSES = [
    ("SIMPLE_RADIAL", 100, 75, (80.0, 50.0, 37.5, 0.08)),  # pincushion: the pinhole shrinks
    ("OPENCV", 100, 75, (80.0, 80.0, 50.0, 37.5, -0.1, 0.05, 0.001, -0.001)),  # the fixtures' lens
    ("OPENCV", 400, 300, (320.0, 318.0, 207.3, 141.9, -0.25, 0.08, 0.002, 0.001)),  # off-centre
    ("OPENCV_FISHEYE", 400, 300, (160.0, 160.0, 200.0, 150.0, 0.05, -0.01, 0.002, 0.0)),
    ("SIMPLE_RADIAL", 640, 480, (500.0, 320.0, 240.0, 5.0)),  # absurd but monotone: clamped to 0.2
    ("FOV", 333, 111, (150.0, 160.0, 170.0, 50.0, 0.5)),
    # the principal point on the left border's pixel centres: COLMAP divides by zero there (IEEE inf)
    ("OPENCV", 100, 75, (100.0, 100.0, 0.5, 37.5, 0.01, 0.0, 0.0, 0.0)),
    ("OPENCV", 100, 75, (100.0, 100.0, 50.0, 74.5, -0.01, 0.0, 0.0, 0.0)),
]


def _check_against_colmap(lens: Lens) -> None:
    cam = pycolmap.Camera(model=lens.model, width=lens.width, height=lens.height, params=list(lens.params))
    ref = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), cam)
    ours = undistorted_pinhole(lens)
    assert ours.model == "PINHOLE" and ref.model.name == "PINHOLE"
    assert (ours.width, ours.height) == (ref.width, ref.height)
    assert np.abs(np.array(ours.params) / np.array(ref.params) - 1).max() <= 1e-6


@pytest.mark.parametrize("model", [m for m in MODELS if m not in ("SIMPLE_PINHOLE", "PINHOLE")])
def test_undistorted_pinhole_matches_colmap(model: str) -> None:
    lens = Lens(model, W, H, LENSES[model])
    _check_against_colmap(lens)
    # the size changes for every one of these lenses (barrel: larger; FOV: wider, shorter)
    assert (undistorted_pinhole(lens).width, undistorted_pinhole(lens).height) != (W, H)


@pytest.mark.parametrize(("model", "width", "height", "params"), MORE_LENSES)
def test_undistorted_pinhole_matches_colmap_more(model: str, width: int, height: int, params: tuple) -> None:
    _check_against_colmap(Lens(model, width, height, params))


@pytest.mark.parametrize("model", ["SIMPLE_PINHOLE", "PINHOLE"])
def test_pinhole_returns_itself(model: str) -> None:
    lens = Lens(model, W, H, LENSES[model])
    _check_against_colmap(lens)  # COLMAP too returns a pinhole unchanged
    fx, fy, cx, cy = lens.focal_and_centre
    assert undistorted_pinhole(lens) == Lens("PINHOLE", W, H, (fx, fy, cx, cy))


def test_zero_distortion_returns_itself_where_colmap_crops_a_pixel() -> None:
    """The documented difference: a zero-distortion OPENCV camera needs no resampling, so it stays
    as it is; COLMAP's border search crops it to (W - 1) x (H - 1) (cx / (cx - 0.5) on the left side
    against 1 on the right)."""
    lens = Lens("OPENCV", W, H, (500.0, 500.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0))
    assert undistorted_pinhole(lens) == Lens("PINHOLE", W, H, (500.0, 500.0, 320.0, 240.0))
    cam = pycolmap.Camera(model="OPENCV", width=W, height=H, params=list(lens.params))
    ref = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), cam)
    assert (ref.width, ref.height) == (W - 1, H - 1)


@pytest.mark.parametrize(
    ("model", "width", "height", "params", "reason"),
    [
        # 1 - 2 r^2 folds at r = 0.41 (radius 0.27): the corners (radius 0.8) have no inverse
        ("SIMPLE_RADIAL", 640, 480, (500.0, 320.0, 240.0, -2.0), "the distortion has no inverse at border pixel"),
        ("OPENCV", 640, 480, (500.0, 500.0, 320.0, 240.0, 0.0, 0.0, 0.3, 0.0), "has no inverse at border pixel"),
        # theta (1 - 0.5 theta^2) reaches at most 0.54 rad; the corners are at 1.33
        ("OPENCV_FISHEYE", 640, 480, (300.0, 300.0, 320.0, 240.0, -0.5, 0, 0, 0), "has no inverse at border"),
        # an equidistant fisheye of 150 px focal length: the corners see 152 degrees off the axis
        ("OPENCV_FISHEYE", 640, 480, (150.0, 150.0, 320.0, 240.0, 0, 0, 0, 0), r"sees 152\.5 degrees off the axis"),
        # FOV with omega = 3: tan(r omega) wraps beyond r = 0.52; the corners are at 0.8
        ("FOV", 640, 480, (500.0, 500.0, 320.0, 240.0, 3.0), "projects 524 px away from it"),
        # the polynomial in theta turns back near theta = 1; the corners' inverse lies beyond the fold
        ("OPENCV_FISHEYE", 64, 48, (24.0, 24.0, 32.0, 24.0, 0.33, 1.27, 1.49, -2.06), "Jacobian determinant"),
    ],
)
def test_no_valid_region_raises(model: str, width: int, height: int, params: tuple, reason: str) -> None:
    lens = Lens(model, width, height, params)
    with pytest.raises(SurfSplatInputError, match=reason) as err:
        undistorted_pinhole(lens)
    line = str(err.value)
    named = ", ".join(f"{n} {v:g}" for n, v in zip(lens.param_names, params))
    assert "\n" not in line and line.startswith(f"camera model {model} ({named}) at {width}x{height}: ")


@pytest.mark.parametrize("model", MODELS)
def test_gradients_are_finite_on_the_axis(model: str) -> None:
    """project is differentiable everywhere in front of the camera, the axis (the models' epsilon
    and series branches) included: the unused branch of each switch stays finite."""
    lens, _ = _pair(model)
    pts = torch.tensor([[0.0, 0.0, 2.0], [1e-9, -1e-9, 1.0], [0.3, -0.2, 1.5]], dtype=torch.float64, requires_grad=True)
    project(lens, pts).sum().backward()
    assert torch.isfinite(pts.grad).all()
    # and it is the derivative: a central difference at the off-axis point
    h = 1e-6
    step = torch.tensor([h, 0.0, 0.0], dtype=torch.float64)
    num = (project(lens, pts[2].detach() + step) - project(lens, pts[2].detach() - step)).sum() / (2 * h)
    assert abs(float(num) - float(pts.grad[2, 0])) <= 1e-5 * max(1.0, abs(float(num)))


def test_focal_length_must_be_positive() -> None:
    with pytest.raises(SurfSplatInputError, match="camera model OPENCV: focal length fy is 0.0 "):
        Lens("OPENCV", W, H, (500.0, 0.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0))
    with pytest.raises(SurfSplatInputError, match="camera model SIMPLE_RADIAL: focal length f is -1.0 "):
        Lens("SIMPLE_RADIAL", W, H, (-1.0, 320.0, 240.0, 0.0))


@pytest.mark.parametrize("model", MODELS)
def test_device_is_the_inputs(model: str) -> None:
    """On an accelerator (the stand-in device of surfsplat.testing) the results stay there, equal to
    the CPU's; project waits on the host nowhere (unproject: twice per Newton iteration)."""
    from surfsplat.testing.standin_device import StandinDevice, standin

    lens, _ = _pair(model)
    pts = torch.from_numpy(_points(10, n=64))
    px = torch.from_numpy(_pixels(11, n=64))
    with StandinDevice() as dev:
        on_pts, on_px = standin(pts), standin(px)
        projected = project(lens, on_pts)
        waits_project = [s for s in dev.syncs if "lens.py" in s.where]
        lifted = unproject(lens, on_px)
        assert projected.device == on_pts.device and lifted.device == on_px.device
        assert not waits_project
        assert torch.equal(projected.cpu(), project(lens, pts)) and torch.equal(lifted.cpu(), unproject(lens, px))


@pytest.mark.parametrize("model", MODELS)
def test_rescaled_matches_colmap(model: str) -> None:
    """Lens.rescaled is pycolmap's Camera.rescale(new_width, new_height), and a photo resized with it
    projects where the resized pixels are (x' = x * W'/W)."""
    lens, cam = _pair(model)
    small = lens.rescaled(160, 121)
    cam.rescale(160, 121)
    assert (small.width, small.height) == (cam.width, cam.height)
    assert np.abs(np.array(small.params) - np.array(cam.params)).max() <= 1e-12
    if lens.param_names[0] != "f":  # one focal length cannot follow two different factors exactly
        pts = torch.from_numpy(_points(12, n=100))
        scale = torch.tensor([160 / W, 121 / H], dtype=torch.float64)
        assert (project(small, pts) - project(lens, pts) * scale).abs().max().item() <= 1e-9
