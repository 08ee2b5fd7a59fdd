"""Camera paths (slerp, interpolation, turntable) against closed forms; camera files and their errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from surfsplat import Cameras
from surfsplat.data.cameras import load_cameras, save_cameras
from surfsplat.export.paths import axis_angle_matrix, focus_point, interpolate_cameras, mean_camera, slerp, turntable
from surfsplat.geometry.rotations import matrix_to_quat, quat_to_matrix
from surfsplat.utils.checks import SurfSplatInputError


def _rz(angle: float) -> torch.Tensor:
    return axis_angle_matrix(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), angle)


def _cams(rotations: list[torch.Tensor], centres: list[list[float]], f: float = 50.0) -> Cameras:
    n = len(rotations)
    c2w = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    c2w[:, :3, :3] = torch.stack(rotations)
    c2w[:, :3, 3] = torch.tensor(centres, dtype=torch.float64)
    K = torch.tensor([[f, 0, 32.0], [0, f, 24.0], [0, 0, 1]], dtype=torch.float64).repeat(n, 1, 1)
    return Cameras(c2w, K)


def test_slerp_rotates_at_constant_angular_speed():
    # Rotations about z by 0 and 1.2 rad: slerp at t is the rotation by 1.2 t (closed form).
    q0, q1 = matrix_to_quat(_rz(0.0)), matrix_to_quat(_rz(1.2))
    t = torch.linspace(0, 1, 7, dtype=torch.float64)
    R = quat_to_matrix(slerp(q0, q1, t))
    expected = torch.stack([_rz(1.2 * float(s)) for s in t])
    torch.testing.assert_close(R, expected, atol=1e-12, rtol=0)


def test_slerp_takes_the_short_way_for_opposite_quaternion_signs():
    q0 = matrix_to_quat(_rz(0.1))
    q1 = -matrix_to_quat(_rz(0.5))  # same rotation, other hemisphere
    mid = quat_to_matrix(slerp(q0, q1, torch.tensor([0.5], dtype=torch.float64)))[0]
    torch.testing.assert_close(mid, _rz(0.3), atol=1e-12, rtol=0)


def test_interpolate_cameras_hits_the_views_and_moves_at_constant_speed():
    cams = _cams([_rz(0.0), _rz(0.4), _rz(0.6)], [[0, 0, 0], [1.0, 0, 0], [1.0, 3.0, 0]])
    path = interpolate_cameras(cams, 9)
    torch.testing.assert_close(path.c2w[0], cams.c2w[0], atol=1e-12, rtol=0)
    torch.testing.assert_close(path.c2w[-1], cams.c2w[-1], atol=1e-12, rtol=0)
    # The centres lie on the polyline of total length 4; 9 frames -> 8 equal steps of 0.5.
    steps = (path.centers[1:] - path.centers[:-1]).norm(dim=-1)
    torch.testing.assert_close(steps, torch.full((8,), 0.5, dtype=torch.float64), atol=1e-12, rtol=0)
    # Frame 2 (arc length 1) is exactly the middle view.
    torch.testing.assert_close(path.c2w[2], cams.c2w[1], atol=1e-12, rtol=0)
    R = path.c2w[:, :3, :3]
    torch.testing.assert_close(
        R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(9, 3, 3), atol=1e-12, rtol=0
    )


def test_turntable_keeps_the_focus_on_the_optical_axis():
    cams = _cams([_rz(0.0), _rz(0.2)], [[0, 0, 0], [0.3, 0, 0]])
    focus = torch.tensor([0.15, 0.0, 4.0], dtype=torch.float64)
    path = turntable(cams, focus, num_frames=16, degrees=40.0)
    centre, K = mean_camera(cams)
    distance = (centre[:3, 3] - focus).norm()
    # Every frame is a rotation of the mean camera about an axis through the focus: same distance,
    # the focus projects where the mean camera projects it, and the sweep reaches +-20 degrees.
    torch.testing.assert_close((path.centers - focus).norm(dim=-1), distance.expand(16), atol=1e-12, rtol=0)
    cam_points = path.w2c[:, :3, :3] @ focus + path.w2c[:, :3, 3]
    uv = (path.K @ cam_points[..., None])[..., 0]
    mean_cam = torch.linalg.inv(centre)[:3, :3] @ focus + torch.linalg.inv(centre)[:3, 3]
    mean_uv = K @ mean_cam
    torch.testing.assert_close(uv[:, :2] / uv[:, 2:], (mean_uv[:2] / mean_uv[2]).expand(16, 2), atol=1e-9, rtol=0)
    forward = path.c2w[:, :3, 2]
    angles = torch.rad2deg(torch.arccos((forward @ centre[:3, 2]).clamp(-1, 1)))
    assert abs(float(angles.max()) - 20.0) < 1e-6


def test_focus_point_is_the_median_depth_along_the_mean_axis():
    cams = _cams([_rz(0.0), _rz(0.0)], [[0, 0, 0], [0.2, 0, 0]])
    depth = torch.tensor([1.0, 2.0, 3.0, 10.0]).reshape(1, 1, 2, 2).repeat(2, 1, 1, 1)
    valid = torch.ones_like(depth, dtype=torch.bool)
    valid[:, :, 1, 1] = False  # the 10 is not covered
    focus = focus_point(depth, valid, cams)
    torch.testing.assert_close(focus, torch.tensor([0.1, 0.0, 2.0], dtype=torch.float64))


def test_camera_file_round_trip_is_exact(tmp_path):
    cams = _cams([_rz(0.3), _rz(-0.2)], [[0.1, 0.2, 0.3], [1.0, -2.0, 0.5]])
    save_cameras(tmp_path / "cams.json", cams, 64, 48, ["a.png", "b.png"], near=0.5, far=9.0)
    back = load_cameras(tmp_path / "cams.json")
    assert (back.width, back.height, back.names, back.near, back.far) == (64, 48, ["a.png", "b.png"], 0.5, 9.0)
    assert torch.equal(back.cameras.c2w, cams.c2w) and torch.equal(back.cameras.K, cams.K)
    assert not list(tmp_path.glob(".*tmp*"))


def test_camera_file_selection_opengl_and_rescale(tmp_path):
    c2w_gl = torch.eye(4).tolist()
    doc = {
        "width": 100,
        "height": 50,
        "convention": "opengl",
        "frames": [
            {"name": "x.png", "K": [[80, 0, 50], [0, 80, 25], [0, 0, 1]], "c2w": c2w_gl},
            {"name": "y.png", "K": [[90, 0, 50], [0, 90, 25], [0, 0, 1]], "c2w": c2w_gl[:3]},
        ],
    }
    (tmp_path / "c.json").write_text(json.dumps(doc))
    cams = load_cameras(tmp_path / "c.json")
    # OpenGL looks down -z with y up: OpenCV's y and z axes are flipped.
    assert torch.equal(cams.cameras.c2w[0, :3, :3], torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)))
    picked = cams.select(["y", "x.png"], "c.json")
    assert picked.names == ["y.png", "x.png"]
    K = picked.resized(200, 100, "c.json").K
    assert K[0, 0, 0] == 180 and K[0, 0, 2] == 100 and K[0, 1, 2] == 50
    with pytest.raises(SurfSplatInputError, match="only a uniform rescale"):
        picked.resized(200, 60, "c.json")
    with pytest.raises(SurfSplatInputError, match="no camera for image 'z.png'"):
        cams.select(["z.png"], "c.json")


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d.pop("width"), "field 'width' must be a positive integer"),
        (lambda d: d["frames"][1].__setitem__("K", [[1, 0], [0, 1]]), r"frames\[1\].K: expected shape \(3, 3\)"),
        (lambda d: d["frames"][0].__setitem__("c2w", [[1, 0, 0, 0]] * 4), "not a rigid camera transform"),
        (
            lambda d: d["frames"][0].__setitem__("K", [[0, 0, 1], [0, 5, 1], [0, 0, 1]]),
            "focal lengths must be positive",
        ),
        (lambda d: d.__setitem__("near", 1.0), "give both 'near' and 'far'"),
        (lambda d: d.__setitem__("convention", "blender"), "field 'convention'"),
    ],
)
def test_camera_file_errors_name_the_field(tmp_path, change, message):
    doc = {
        "width": 10,
        "height": 10,
        "frames": [{"K": [[5, 0, 5], [0, 5, 5], [0, 0, 1]], "c2w": torch.eye(4).tolist()}] * 2,
    }
    doc = json.loads(json.dumps(doc))
    change(doc)
    (tmp_path / "c.json").write_text(json.dumps(doc))
    with pytest.raises(SurfSplatInputError, match=message):
        load_cameras(tmp_path / "c.json")


def test_camera_files_that_are_not_json_or_missing(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_cameras(tmp_path / "nope.json")
    (tmp_path / "c.json").write_text("{not json")
    with pytest.raises(SurfSplatInputError, match="not valid JSON"):
        load_cameras(tmp_path / "c.json")


def test_interpolation_needs_two_views():
    cams = _cams([_rz(0.0)], [[0, 0, 0]])
    with pytest.raises(SurfSplatInputError, match="at least 2 cameras"):
        interpolate_cameras(cams, 5)
    with pytest.raises(SurfSplatInputError, match="num_frames"):
        interpolate_cameras(_cams([_rz(0.0)] * 2, [[0, 0, 0], [1, 0, 0]]), 1)
    assert math.isclose(float(axis_angle_matrix(torch.tensor([0.0, 0.0, 2.0]), math.pi / 2)[0, 1]), -1.0, abs_tol=1e-7)


@pytest.mark.parametrize("folder, images", [("llff_fern", "images_16"), ("dtu_scan24", "images_16")])
def test_scene_folder_cameras_decode_no_pixel_and_match_the_scene(monkeypatch, folder, images):
    """load_cameras on a scene folder reads camera records and image headers only, and returns the
    cameras load_scene gives for the same folder."""
    import surfsplat.data.formats.common as common
    import surfsplat.data.formats.dtu as dtu
    from surfsplat.data.load import load_scene

    root = Path(__file__).resolve().parents[1] / "data" / folder
    scene = load_scene(root, images=images, dtype=torch.float64)

    def refuse(*args, **kwargs):
        raise AssertionError("a pixel was decoded")

    monkeypatch.setattr(common, "read_image", refuse)
    monkeypatch.setattr(dtu, "read_image", refuse)
    cams = load_cameras(root, images=images)
    assert torch.equal(cams.cameras.c2w, scene.cameras.c2w) and torch.equal(cams.cameras.K, scene.cameras.K)
    assert (cams.width, cams.height, cams.names) == (scene.width, scene.height, scene.names)
    assert cams.near == float(scene.near.min()) and cams.far == float(scene.far.max())
