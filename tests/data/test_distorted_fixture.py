"""The distorted capture fixture (`tests/data/distorted`): rebuilt identically, and what it says it is."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image

from surfsplat.data.undistort import distort, undistort
from surfsplat.geometry.lens import Lens

from .make_distorted import build

pytestmark = pytest.mark.usefixtures("one_torch_thread")

HERE = Path(__file__).resolve().parent
FIXTURE = HERE / "distorted"
TRUTH = json.loads((FIXTURE / "truth.json").read_text())
LENS = Lens.from_dict(TRUTH["lens"])


def _read(path: Path) -> torch.Tensor:
    return torch.from_numpy(np.array(Image.open(path).convert("RGB"))).permute(2, 0, 1).float() / 255


def test_rebuilds_identically(tmp_path: Path) -> None:
    build(tmp_path / "distorted")
    ours = sorted(p.relative_to(FIXTURE) for p in FIXTURE.rglob("*") if p.is_file())
    rebuilt = sorted(p.relative_to(tmp_path / "distorted") for p in (tmp_path / "distorted").rglob("*") if p.is_file())
    assert ours == rebuilt
    for rel in ours:
        assert (FIXTURE / rel).read_bytes() == (tmp_path / "distorted" / rel).read_bytes(), rel


@pytest.mark.parametrize("model_dir", ["sparse/0", "sparse/text"])
def test_colmap_model_holds_the_lens_and_poses(model_dir: str) -> None:
    rec = pycolmap.Reconstruction(str(FIXTURE / model_dir))
    assert len(rec.cameras) == 1 and len(rec.images) == len(TRUTH["views"])
    cam = rec.cameras[1]
    assert cam.model.name == LENS.model and (cam.width, cam.height) == (LENS.width, LENS.height)
    assert np.array_equal(cam.params, np.array(LENS.params))
    by_name = {img.name: img for img in rec.images.values()}
    for view in TRUTH["views"]:
        img = by_name[Path(view["image"]).name]
        w2c = np.eye(4)
        w2c[:3, :4] = img.cam_from_world().matrix()
        assert np.abs(np.linalg.inv(w2c) - np.array(view["c2w"])).max() <= 1e-9
        # every observation is where the lens projects its 3D point
        for p2d in img.points2D:
            xyz = rec.points3D[p2d.point3D_id].xyz
            assert np.abs(cam.img_from_cam(w2c[:3, :3] @ xyz + w2c[:3, 3]) - p2d.xy).max() <= 1e-9
    assert rec.num_points3D() > 20


@pytest.mark.parametrize("folder", [".", "fisheye"])
def test_photos_undistort_back_to_their_sources(folder: str) -> None:
    """Each photo, undistorted to its view's pinhole (IDR's K), is the DTU photo it came from:
    MAE <= 2.5/255 (measured 1.1-2.1: bicubic both ways, and the photos' 8-bit rounding); read as
    if it were the pinhole photo (no undistortion) it is not (measured 5.4-13.5/255)."""
    truth = json.loads((FIXTURE / folder / "truth.json").read_text())
    lens = Lens.from_dict(truth["lens"])
    for view in truth["views"]:
        pinhole = Lens.from_dict(view["pinhole"])
        photo = _read(FIXTURE / folder / view["image"])
        source = _read(HERE / view["source"])
        valid = undistort(distort(torch.ones(1, 75, 100), pinhole, lens), lens, pinhole)[0] >= 1 - 1e-6
        assert valid.float().mean() > 0.9  # the lens sees a little less than the pinhole: 95-96%
        back = undistort(photo, lens, pinhole, "bicubic")
        assert (back - source).abs().mean(0)[valid].mean().item() * 255 <= 2.5
        assert (photo - source).abs().mean(0)[valid].mean().item() * 255 > 4.0


def test_transforms_dialects() -> None:
    ns = json.loads((FIXTURE / "transforms.json").read_text())
    fx, fy, cx, cy = LENS.focal_and_centre
    k1, k2, p1, p2 = LENS.extra_params
    assert ns["camera_model"] == "OPENCV" and (ns["w"], ns["h"]) == (100, 75)
    assert (ns["fl_x"], ns["fl_y"], ns["cx"], ns["cy"], ns["k1"], ns["k2"], ns["p1"], ns["p2"]) == (
        fx,
        fy,
        cx,
        cy,
        k1,
        k2,
        p1,
        p2,
    )
    ngp = json.loads((FIXTURE / "instant_ngp" / "transforms.json").read_text())
    assert "camera_model" not in ngp and "fl_y" not in ngp and ngp["fl_x"] == fx
    assert isinstance(ngp["w"], float) and isinstance(ngp["h"], float)
    for ours, theirs, view in zip(ns["frames"], ngp["frames"], TRUTH["views"]):
        assert ours["file_path"] == view["image"] and theirs["file_path"] == "../" + view["image"]
        assert (FIXTURE / "instant_ngp" / theirs["file_path"]).is_file()
        gl = np.array(ours["transform_matrix"])
        cv = np.array(view["c2w"])
        assert np.abs(gl[:, 0] - cv[:, 0]).max() <= 1e-11 and np.abs(gl[:, 1:3] + cv[:, 1:3]).max() <= 1e-11
        assert np.array_equal(gl, np.array(theirs["transform_matrix"]))


def test_fisheye_transforms_dialect() -> None:
    ns = json.loads((FIXTURE / "fisheye" / "transforms.json").read_text())
    lens = Lens.from_dict(json.loads((FIXTURE / "fisheye" / "truth.json").read_text())["lens"])
    assert ns["camera_model"] == "OPENCV_FISHEYE" and lens.model == "OPENCV_FISHEYE"
    assert [ns[k] for k in ("fl_x", "fl_y", "cx", "cy")] == list(lens.focal_and_centre)
    assert [ns[k] for k in ("k1", "k2", "k3", "k4")] == list(lens.extra_params) and "p1" not in ns
    main = json.loads((FIXTURE / "transforms.json").read_text())
    assert ns["frames"] == main["frames"]  # the same views and poses
    assert all((FIXTURE / "fisheye" / f["file_path"]).is_file() for f in ns["frames"])
