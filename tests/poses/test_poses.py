"""Cameras estimated from photos alone (`surfsplat.poses`, `surfsplat poses`, `reconstruct` without
--cameras): accuracy against exact synthetic cameras and the DTU / LLFF calibrations, the frame and
scale convention, EXIF focal lengths, and one clear error for every kind of bad input."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from surfsplat.cli import main
from surfsplat.data.synthetic.primitives import Primitive
from surfsplat.data.synthetic.render import render_synthetic
from surfsplat.data.synthetic.scene import WORLD_DOWN, Lighting, SyntheticConfig, SyntheticScene, make_scene
from surfsplat.data.synthetic.textures import random_texture
from surfsplat.geometry.cameras import Cameras, look_at
from surfsplat.geometry.lens import Lens
from surfsplat.poses import PoseConfig, estimate_cameras, exif_focal, relative_pose_errors
from surfsplat.utils.checks import SurfSplatInputError

W, H = 400, 300
FAST = PoseConfig(min_extraction_size=400)  # no upscaling: for the error paths, where accuracy is not the point


def _cameras(eyes: torch.Tensor, targets: torch.Tensor, fov_deg: float = 60.0) -> Cameras:
    f = 0.5 * W / math.tan(math.radians(fov_deg) / 2)
    K = torch.tensor([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Cameras(look_at(eyes.double(), targets.double(), WORLD_DOWN), K.repeat(len(eyes), 1, 1))


def _orbit(n: int, spread_deg: float, radius: float = 2.0) -> Cameras:
    """n cameras on a horizontal arc of `spread_deg` around the middle of room 0, looking at it."""
    target = torch.tensor([0.0, 0.0, 0.6], dtype=torch.float64)
    angles = torch.deg2rad(torch.linspace(-spread_deg / 2, spread_deg / 2, n, dtype=torch.float64))
    eyes = torch.stack([radius * torch.cos(angles), radius * torch.sin(angles), torch.full_like(angles, 1.4)], -1)
    return _cameras(eyes, target.expand(n, 3))


def _render(scene: SyntheticScene, cameras: Cameras) -> tuple[list[torch.Tensor], torch.Tensor]:
    out = render_synthetic(scene, Cameras(cameras.c2w.float(), cameras.K.float()), W, H)
    return list(out.image), out.depth


@pytest.fixture(scope="module")
def room():
    return make_scene(0)


@pytest.fixture(scope="module")
def orbit_views(room):
    cameras = _orbit(4, 40.0)
    images, depth = _render(room, cameras)
    return images, cameras, depth


def _save(images: list[torch.Tensor], folder: Path, prefix: str = "view") -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, image in enumerate(images):
        path = folder / f"{prefix}{i}.png"
        Image.fromarray((image.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)).save(path)
        paths.append(path)
    return paths


# ----------------------------------------------------------------------------------------- accuracy
@pytest.mark.slow
def test_synthetic_room_four_views_focal_unknown_within_tolerances(orbit_views):
    images, truth, depth = orbit_views
    cams, summary = estimate_cameras(images)
    assert summary.registered == ["view_000", "view_001", "view_002", "view_003"]
    assert summary.method.startswith("incremental") and summary.focal_source.startswith(
        "estimated by bundle adjustment"
    )
    rot, trans = relative_pose_errors(cams.cameras.c2w, truth.c2w)
    assert rot.max() < 1.0 and trans.max() < 2.0, (rot, trans)
    assert abs(summary.focal / float(truth.K[0, 0, 0]) - 1) < 0.05
    # convention: the first camera is the world frame, and the median depth of its triangulated
    # points is 4: a depth between the 10th and 90th percentiles of what it truly sees
    assert torch.allclose(cams.cameras.c2w[0], torch.eye(4, dtype=torch.float64), atol=1e-9)
    scale = float(cams.cameras.centers[3].norm() / (truth.centers[3] - truth.centers[0]).norm())
    first = depth[0][depth[0] > 0].double() * scale  # true depths in the estimate's unit
    assert float(first.quantile(0.1)) < 4 < float(first.quantile(0.9))
    visible = depth[depth > 0].double() * scale
    assert cams.near < float(visible.quantile(0.02)) and cams.far > float(visible.quantile(0.98))


@pytest.mark.slow
def test_a_mapping_run_that_registers_too_few_images_is_run_again(orbit_views, monkeypatch):
    import pycolmap

    # COLMAP's threads can make a run stop after its first images; here the first run finds nothing.
    real, calls = pycolmap.incremental_mapping, []

    def first_run_fails(*args, **kwargs):
        calls.append(args[3].random_seed)
        return {} if len(calls) == 1 else real(*args, **kwargs)

    monkeypatch.setattr(pycolmap, "incremental_mapping", first_run_fails)
    images, truth, _ = orbit_views
    cams, summary = estimate_cameras(images, config=PoseConfig(seed=7))
    assert calls == [7, 8]  # one more run, with the next seed, and no more once every image is in
    assert summary.method == "incremental (the largest of 2 mapping runs)"
    assert summary.registered == ["view_000", "view_001", "view_002", "view_003"]
    rot, _ = relative_pose_errors(cams.cameras.c2w, truth.c2w)
    assert rot.max() < 1.0
    with pytest.raises(SurfSplatInputError, match="mapping_attempts"):
        PoseConfig(mapping_attempts=0)


@pytest.mark.slow
def test_synthetic_room_two_views_with_focal(room):
    truth = _orbit(2, 12.0)
    images, _ = _render(room, truth)
    cams, summary = estimate_cameras(images, focal=float(truth.K[0, 0, 0]))
    assert summary.method == "two-view" and summary.focal_source == "given (--focal)"
    rot, trans = relative_pose_errors(cams.cameras.c2w, truth.c2w)
    assert rot[0] < 1.0 and trans[0] < 2.5, (rot, trans)
    assert summary.points > 500 and summary.reprojection_error < 0.5
    # the given focal, principal point at the centre, a SIMPLE_RADIAL lens whose k is (nearly) the room's zero
    f, cx, cy, k = summary.lens.params
    assert summary.lens.model == "SIMPLE_RADIAL" and (f, cx, cy) == (float(truth.K[0, 0, 0]), W / 2, H / 2)
    assert abs(k) < 0.01, k


DTU_PAIRS = [(23, 24), (12, 13), (30, 31)]


@pytest.mark.slow
def test_dtu_scan24_six_views_focal_unknown(data_dir):
    from surfsplat.data.load import load_scene

    scene = load_scene(data_dir / "dtu_scan24", images="images_4", dtype=torch.float64)
    views = list(range(21, 27))
    paths = [data_dir / "dtu_scan24" / "images_4" / f"{v:06d}.png" for v in views]
    cams, summary = estimate_cameras(paths)
    assert len(summary.registered) == 6
    rot, trans = relative_pose_errors(cams.cameras.c2w, scene.cameras.c2w[views])
    focal_error = abs(summary.focal / float(scene.cameras.K[21, 0, 0]) - 1)
    print(
        f"DTU 21-26: rotation max {rot.max():.3f} deg, translation max {trans.max():.3f} deg, focal {focal_error:.2%}"
    )
    assert rot.max() < 1.0 and trans.max() < 2.0 and focal_error < 0.05


@pytest.mark.slow
def test_dtu_scan24_neighbouring_pairs_with_focal(data_dir):
    from surfsplat.data.load import load_scene

    scene = load_scene(data_dir / "dtu_scan24", images="images_4", dtype=torch.float64)
    rotations = []
    for a, b in DTU_PAIRS:
        paths = [data_dir / "dtu_scan24" / "images_4" / f"{v:06d}.png" for v in (a, b)]
        cams, summary = estimate_cameras(paths, focal=float(scene.cameras.K[a, 0, 0]))
        assert summary.method == "two-view"
        rot, trans = relative_pose_errors(cams.cameras.c2w, scene.cameras.c2w[[a, b]])
        print(f"DTU ({a}, {b}): rotation {rot[0]:.3f} deg, translation {trans[0]:.3f} deg")
        assert rot[0] < 1.0 and trans[0] < 2.5
        rotations.append(rot[0])
    assert np.median(rotations) < 0.7


@pytest.mark.slow
def test_llff_fern_four_views_rotations_within_one_degree(data_dir):
    from surfsplat.data.load import load_scene

    scene = load_scene(data_dir / "llff_fern", images="images_8", dtype=torch.float64)
    views = [0, 1, 2, 3]
    cams, summary = estimate_cameras([data_dir / "llff_fern" / "images_8" / scene.names[v] for v in views])
    assert summary.focal_source.startswith("EXIF 35 mm equivalent 28 mm")  # the PNGs keep the phone's EXIF
    rot, trans = relative_pose_errors(cams.cameras.c2w, scene.cameras.c2w[views])
    print(f"fern 0-3: rotation max {rot.max():.3f} deg, translation max {trans.max():.3f} deg")
    assert rot.max() < 1.0


def test_relative_pose_errors_ignore_a_similarity_of_the_world():
    truth = _orbit(3, 30.0)
    S = torch.eye(4, dtype=torch.float64)
    S[:3, :3] = torch.linalg.matrix_exp(torch.tensor([[0, -0.3, 0.2], [0.3, 0, -0.1], [-0.2, 0.1, 0]]).double())
    S[:3, 3] = torch.tensor([1.0, -2.0, 0.5])
    moved = S @ truth.c2w
    moved[:, :3, 3] *= 3.0  # and a scale
    rot, trans = relative_pose_errors(moved, truth.c2w)
    assert rot.max() < 1e-9 and trans.max() < 1e-9
    tilted = truth.c2w.clone()
    tilted[1, :3, :3] = tilted[1, :3, :3] @ torch.linalg.matrix_exp(
        torch.tensor([[0, -1.0, 0], [1.0, 0, 0], [0, 0, 0]]).double() * math.radians(2.0)
    )
    rot, _ = relative_pose_errors(tilted, truth.c2w)
    assert rot[0] == pytest.approx(2.0, abs=1e-6) and rot[2] == pytest.approx(2.0, abs=1e-6)  # pairs with camera 1
    assert rot[1] < 1e-9


# ----------------------------------------------------------------------------------------- EXIF
def _jpeg_with_exif(path: Path, size: tuple[int, int], tags: dict[int, object]) -> Path:
    image = Image.new("RGB", size, (120, 90, 60))
    exif = Image.Exif()
    exif.get_ifd(0x8769).update(tags)
    image.save(path, exif=exif)
    return path


def test_exif_35mm_equivalent_focal(tmp_path):
    path = _jpeg_with_exif(tmp_path / "a.jpg", (400, 300), {0xA405: 28})
    focal, source = exif_focal(path, 400, 300)
    assert focal == pytest.approx(28 * 500 / math.hypot(36, 24))  # the 400x300 diagonal is 500 px
    assert "35 mm" in source


def test_exif_focal_plane_resolution_rescaled_to_the_image(tmp_path):
    # 4.25 mm lens, 1000 px/mm on a 4000x3000 sensor, stored downscaled to 400x300: 425 px
    tags = {0x920A: 4.25, 0xA20E: 1000.0, 0xA210: 4, 0xA002: 4000, 0xA003: 3000}
    path = _jpeg_with_exif(tmp_path / "b.jpg", (400, 300), tags)
    focal, _ = exif_focal(path, 400, 300)
    assert focal == pytest.approx(4.25 * 1000 * 0.1)
    assert exif_focal(_jpeg_with_exif(tmp_path / "c.jpg", (400, 300), {}), 400, 300) is None


def _photo_with_exif(path: Path, size: tuple[int, int], tags: dict[int, object], orientation: int, fmt: str) -> Path:
    exif = Image.Exif()
    exif[0x0112] = orientation
    exif.get_ifd(0x8769).update(tags)
    Image.new("RGB", size, (120, 90, 60)).save(path, fmt, exif=exif.tobytes())
    return path


@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_focal_plane_resolution_is_along_the_stored_width(tmp_path, orientation):
    """FocalPlaneXResolution is along the sensor's width, the STORED image's width (CIPA DC-008): a
    stored 200x300 crop of a 4000x3000 sensor keeps 200/4000 of its x pixels, whatever the display.
    The displayed width (300 for 5-8) or the long sides' ratio (300/4000) would give other values."""
    tags = {0x920A: 4.25, 0xA20E: 1000.0, 0xA210: 4, 0xA002: 4000, 0xA003: 3000}
    path = _photo_with_exif(tmp_path / "p.jpg", (200, 300), tags, orientation, "JPEG")
    shown = (300, 200) if orientation >= 5 else (200, 300)
    from surfsplat.data.images import read_image_size

    assert read_image_size(path) == shown
    focal, _ = exif_focal(path, *shown)
    assert focal == pytest.approx(4.25 * 1000 * 200 / 4000)


@pytest.mark.parametrize("orientation", [1, 6])
def test_exif_35mm_focal_of_a_turned_photo_uses_the_diagonal(tmp_path, orientation):
    path = _photo_with_exif(tmp_path / "p.jpg", (400, 300), {0xA405: 28}, orientation, "JPEG")
    shown = (300, 400) if orientation == 6 else (400, 300)
    focal, _ = exif_focal(path, *shown)
    assert focal == pytest.approx(28 * 500 / math.hypot(36, 24))


@pytest.mark.parametrize("orientation", [1, 6, 8])
def test_exif_focal_read_from_heic(tmp_path, orientation):
    """pillow-heif keeps the EXIF block (it resets only the Orientation tag, after applying it): both
    routes read from a HEIC, the focal-plane one along the coded (stored) width."""
    pillow_heif = pytest.importorskip("pillow_heif", reason="pillow-heif (the 'heic' extra) is not installed")
    pillow_heif.register_heif_opener()
    tags = {0x920A: 4.25, 0xA20E: 1000.0, 0xA210: 4, 0xA002: 4000, 0xA003: 3000}
    path = _photo_with_exif(tmp_path / "p.heic", (64, 96), tags, orientation, "HEIF")
    shown = (96, 64) if orientation >= 5 else (64, 96)
    focal, source = exif_focal(path, *shown)
    assert focal == pytest.approx(4.25 * 1000 * 64 / 4000)
    assert "focal length 4.25 mm" in source
    path35 = _photo_with_exif(tmp_path / "q.heic", (64, 48), {0xA405: 26}, orientation, "HEIF")
    shown = (48, 64) if orientation >= 5 else (64, 48)
    assert exif_focal(path35, *shown)[0] == pytest.approx(26 * 80 / math.hypot(36, 24))


# ----------------------------------------------------------------------------------------- bad input
def test_fewer_than_two_images(orbit_views, tmp_path, capsys):
    with pytest.raises(SurfSplatInputError, match="at least 2 images of one scene, got 1"):
        estimate_cameras(orbit_views[0][:1])
    path = _save(orbit_views[0][:1], tmp_path)[0]
    assert main(["poses", str(path), "--out", str(tmp_path / "c.json")]) == 2
    assert "surfsplat poses: error: images: poses need at least 2 images of one scene, got 1" in capsys.readouterr().err
    assert not (tmp_path / "c.json").exists()


def test_unreadable_and_non_image_files(orbit_views, tmp_path, capsys):
    good = _save(orbit_views[0][:1], tmp_path)[0]
    fake = tmp_path / "broken.png"
    fake.write_bytes(b"not a png at all")
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    for bad in (fake, text):
        assert main(["poses", str(good), str(bad), "--out", str(tmp_path / "c.json")]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"surfsplat poses: error: {bad}: cannot decode image") and err.count("\n") == 1
    assert main(["poses", str(good), str(tmp_path / "missing.png"), "--out", str(tmp_path / "c.json")]) == 2
    assert "missing.png: image file not found" in capsys.readouterr().err
    assert not (tmp_path / "c.json").exists()


def test_focal_with_photos_of_several_sizes_is_refused(orbit_views, tmp_path, capsys):
    """One focal length in pixels fits photos of one size: with several, --focal is one line, exit 2, no file."""
    paths = _save(orbit_views[0][:2], tmp_path)
    Image.open(paths[1]).resize((320, 240)).save(paths[1])
    with pytest.raises(SurfSplatInputError, match=r"^--focal: one focal length in pixels fits photos of one size, "):
        estimate_cameras(paths, focal=300.0)
    assert main(["poses", *map(str, paths), "--out", str(tmp_path / "c.json"), "--focal", "300"]) == 2
    err = capsys.readouterr().err
    assert err == (
        "surfsplat poses: error: --focal: one focal length in pixels fits photos of one size, these have 2 "
        "(400x300, 320x240); leave it out (EXIF, else bundle adjustment, finds one per size)\n"
    )
    assert not (tmp_path / "c.json").exists()


def test_too_few_matches_names_the_pair_and_count(orbit_views, tmp_path, capsys):
    other = make_scene(4)
    elsewhere, _ = _render(other, _cameras(torch.tensor([[1.0, 1.0, 1.5]]), torch.tensor([[2.0, 3.0, 1.0]])))
    with pytest.raises(SurfSplatInputError, match=r"view_000 - view_001: only \d+ verified matches \(\d+ putative\)"):
        estimate_cameras([orbit_views[0][0], elsewhere[0]], config=FAST)
    # at the command line: exit code 2, one line, no camera file
    paths = _save([orbit_views[0][0]], tmp_path / "a") + _save(elsewhere, tmp_path / "b")
    assert main(["poses", *map(str, paths), "--out", str(tmp_path / "c.json")]) == 2  # same file name twice
    assert "file names must be unique (cameras are keyed by name), repeated: ['view0.png']" in capsys.readouterr().err
    paths[1] = paths[1].rename(paths[1].with_name("other.png"))
    assert main(["poses", *map(str, paths), "--out", str(tmp_path / "c.json"), "--max-size", "400"]) == 2
    err = capsys.readouterr().err
    assert "view0.png - other.png: only" in err and "more overlap" in err and err.count("\n") == 1
    assert not (tmp_path / "c.json").exists()


def test_unregistered_image_is_named_and_the_rest_goes_on(orbit_views):
    other = make_scene(4)
    elsewhere, _ = _render(other, _cameras(torch.tensor([[1.0, 1.0, 1.5]]), torch.tensor([[2.0, 3.0, 1.0]])))
    images, truth, _ = orbit_views
    # the room is a pinhole: from three views at 400 px without upscaling, a SIMPLE_RADIAL fit's k trades
    # with the rotations (measured 1.06 deg max against the 1.0 below); what is tested here is the left-out photo
    config = PoseConfig(min_extraction_size=400, camera_model="SIMPLE_PINHOLE")
    cams, summary = estimate_cameras([images[0], images[1], elsewhere[0], images[2]], config=config)
    assert summary.registered == ["view_000", "view_001", "view_003"] and summary.unregistered == ["view_002"]
    assert cams.names == ["view_000", "view_001", "view_003"]
    assert any("not registered" in n and "view_002" in n and "3 registered" in n for n in summary.notes)
    rot, _ = relative_pose_errors(cams.cameras.c2w, truth.c2w[[0, 1, 2]])
    assert rot.max() < 1.0


def test_pure_rotation_is_refused(room):
    eye = torch.tensor([[2.0, 0.0, 1.4], [2.0, 0.0, 1.4]])
    turn = torch.deg2rad(torch.tensor([-4.0, 4.0]))
    targets = torch.stack([2.0 - 2.0 * torch.cos(turn), 2.0 * torch.sin(turn), torch.full((2,), 0.8)], -1)
    cameras = _cameras(eye, targets)
    images, _ = _render(room, cameras)
    with pytest.raises(
        SurfSplatInputError, match="view_000 - view_001: the camera turned without moving.*step sideways"
    ):
        estimate_cameras(images, focal=float(cameras.K[0, 0, 0]), config=FAST)
    # with a wrong focal length a rotation is no longer an exact K R K^-1, but still one homography
    with pytest.raises(
        SurfSplatInputError,
        match=r"one homography explains 9.% of the matches and only .\..% show parallax.*or the camera mostly turned",
    ):
        estimate_cameras(images, config=FAST)


def test_single_plane_is_refused():
    g = torch.Generator().manual_seed(3)
    wall = Primitive(
        "plane",
        torch.tensor([0.0, 3.0, 0.0]),
        torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]).T.contiguous(),  # normal -y, toward us
        torch.zeros(3),
        random_texture(g, pattern="noise"),
    )
    scene = SyntheticScene(
        [wall], Lighting(), torch.tensor([-5.0, -5, 0]), torch.tensor([5.0, 5, 3]), 3, SyntheticConfig()
    )
    eyes = torch.tensor([[-0.25, 0.0, 1.5], [0.25, 0.0, 1.5]])
    images, _ = _render(scene, _cameras(eyes, eyes + torch.tensor([0.3, 3.0, 0.0])))
    with pytest.raises(SurfSplatInputError, match=r"one homography explains 9.% .*\(nearly\) one plane.*other depths"):
        estimate_cameras(images, config=FAST)


def test_config_checks_name_the_option():
    with pytest.raises(SurfSplatInputError, match="--focal: expected a positive focal length"):
        PoseConfig(focal=-3.0)
    with pytest.raises(SurfSplatInputError, match="--near/--far: expected near < far"):
        PoseConfig(near=5.0, far=2.0)


# ----------------------------------------------------------------------------------------- commands
@pytest.mark.slow
def test_poses_command_writes_a_camera_file_load_cameras_reads(orbit_views, tmp_path, capsys):
    from surfsplat.data.cameras import load_cameras
    from surfsplat.geometry.lens import undistorted_pinhole

    paths = _save(orbit_views[0][:2], tmp_path)
    focal = float(orbit_views[1].K[0, 0, 0])
    out = tmp_path / "cameras.json"
    assert main(["poses", *map(str, paths), "--out", str(out), "--focal", str(focal), "--far", "30"]) == 0
    printed = capsys.readouterr().out
    assert "registered 2 of 2 images (two-view)" in printed and "given (--focal)" in printed
    assert "view0.png - view1.png:" in printed and "inliers" in printed
    assert "camera SIMPLE_RADIAL: f " in printed  # the default model, with its parameters
    cams = load_cameras(out)
    assert cams.names == ["view0.png", "view1.png"] and cams.far == 30 and 0 < cams.near < 4
    frames = json.loads(out.read_text())["frames"]
    lens, pinhole = (Lens.from_dict(frames[0][key]) for key in ("lens", "pinhole"))
    assert (
        lens.model == "SIMPLE_RADIAL" and lens.params[0] == pytest.approx(focal) and (lens.width, lens.height) == (W, H)
    )
    # the file's K and size are those of the pinhole the photos are undistorted to
    assert pinhole == undistorted_pinhole(lens) and (cams.width, cams.height) == (pinhole.width, pinhole.height)
    assert cams.cameras.K[0, 0, 0] == pinhole.params[0] and cams.cameras.K[1, 1, 1] == pinhole.params[1]
    rot, trans = relative_pose_errors(cams.cameras.c2w, orbit_views[1].c2w[:2])
    assert rot[0] < 1.0 and trans[0] < 2.5


@pytest.mark.slow
def test_reconstruct_two_fern_photos_without_a_camera_file(data_dir, tmp_path, capsys):
    from surfsplat.model.checkpoint import save_checkpoint
    from surfsplat.model.surfsplat import SurfSplat

    torch.manual_seed(0)
    checkpoint = tmp_path / "tiny" / "model.safetensors"
    save_checkpoint(SurfSplat.from_preset("tiny").eval(), checkpoint)
    fern = data_dir / "llff_fern" / "images_8"
    photos = [fern / "IMG_4026.png", fern / "IMG_4027.png"]
    out = tmp_path / "out"
    args = ["reconstruct", "--checkpoint", str(checkpoint), "--images", *map(str, photos), "--out", str(out)]
    assert main([*args, "--size", "96", "128", "--formats", "ply", "renders", "--no-progress"]) == 0
    assert "registered 2 of 2 images (two-view)" in capsys.readouterr().out
    estimated = json.loads((out / "estimated_cameras.json").read_text())
    assert [f["name"] for f in estimated["frames"]] == ["IMG_4026.png", "IMG_4027.png"]
    poses = json.loads((out / "poses.json").read_text())
    assert poses["registered"] == ["IMG_4026.png", "IMG_4027.png"] and poses["method"] == "two-view"
    summary = json.loads((out / "reconstruction.json").read_text())
    assert summary["near"] == pytest.approx(poses["near"]) and summary["far"] == pytest.approx(poses["far"])
    report = (out / "report.html").read_text()
    for k in (0, 1):  # each photo beside its camera
        assert f'src="poses/photo{k:02d}.png"' in report and (out / "poses" / f"photo{k:02d}.png").is_file()
    assert "IMG_4027.png: centre (" in report and "renders/view01_color.png" in report
    assert (out / "poses" / "cameras.svg").read_text().count("<polygon") == 2


def test_reconstruct_refuses_focal_with_a_camera_file(orbit_views, tmp_path, capsys):
    paths = _save(orbit_views[0][:2], tmp_path)
    args = ["reconstruct", "--checkpoint", str(tmp_path / "none"), "--images", *map(str, paths)]
    assert main([*args, "--cameras", str(tmp_path / "cameras.json"), "--focal", "300"]) == 2
    err = capsys.readouterr().err
    assert (
        err == "surfsplat reconstruct: error: --focal: only used when the cameras are estimated (without --cameras)\n"
    )


@pytest.mark.slow
def test_sequential_matching_pairs_only_neighbours_and_keeps_accuracy(room):
    """Ordered frames (a video): each image is matched with its next `sequential_overlap` ones only;
    six views 6 degrees apart, neighbours only, still give every camera within a degree."""
    truth = _orbit(6, 30.0)
    images, _ = _render(room, truth)
    config = PoseConfig(matching="sequential", sequential_overlap=1, focal=float(truth.K[0, 0, 0]))
    cams, summary = estimate_cameras(images, config=config)
    assert [(p.first, p.second) for p in summary.pairs] == [(f"view_{i:03d}", f"view_{i + 1:03d}") for i in range(5)]
    assert summary.registered == [f"view_{i:03d}" for i in range(6)]
    rot, trans = relative_pose_errors(cams.cameras.c2w, truth.c2w)
    assert rot.max() < 1.0 and trans.max() < 2.0, (rot, trans)
    with pytest.raises(SurfSplatInputError, match="matching"):
        PoseConfig(matching="spatial")


@pytest.mark.slow
def test_sequential_matching_with_quadratic_overlap_matches_powers_of_two_ahead(room):
    """COLMAP's quadratic overlap: each frame is matched with the frames 1, 2, 4, ... 2^(overlap-1)
    ahead instead of the next `overlap`, so a slow video still has pairs with a baseline to start from."""
    truth = _orbit(6, 30.0)
    images, _ = _render(room, truth)
    names = [f"view_{i:03d}" for i in range(6)]
    for quadratic, offsets in ((False, (1, 2, 3)), (True, (1, 2, 4))):
        config = PoseConfig(
            matching="sequential", sequential_overlap=3, quadratic_overlap=quadratic, focal=float(truth.K[0, 0, 0])
        )
        _, summary = estimate_cameras(images, config=config)
        matched = {(p.first, p.second): p.matches for p in summary.pairs}
        assert set(matched) == {(names[i], names[i + d]) for i in range(6) for d in offsets if i + d < 6}
        assert all(m > 0 for m in matched.values()), matched  # each listed pair was matched by COLMAP


def _label_boxes(svg: str) -> list[tuple[float, float, float, float]]:
    import re

    boxes = []
    for x, y, text in re.findall(r'<text x="([\d.-]+)" y="([\d.-]+)" font-size="11">([^<]*)</text>', svg):
        x, y = float(x), float(y)
        boxes.append((x, y - 10, x + 6.2 * len(text), y + 2))
    return boxes


def test_top_view_labels_never_overlap_and_every_dot_names_its_photo():
    from surfsplat.data.cameras import CameraSet
    from surfsplat.poses.report import top_view_svg

    # Three cameras 10 units apart, then seventeen within 5 cm of the middle one (a pause in a walk,
    # where the names would pile up on each other).
    x = torch.cat((torch.tensor([0.0, 10.0, 20.0]), 10.0 + torch.linspace(0.003, 0.05, 17)))
    c2w = torch.eye(4).repeat(20, 1, 1)
    c2w[:, 0, 3] = x
    K = torch.tensor([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]).repeat(20, 1, 1)
    names = [f"frame_{i:05d}.png" for i in range(20)]
    svg = top_view_svg(CameraSet(Cameras(c2w, K), 64, 48, names))
    assert all(f"<title>{n}</title>" in svg for n in names)
    labelled = [n for n in names if f">{n}</text>" in svg]
    boxes = _label_boxes(svg)
    assert len(boxes) == len(labelled)
    assert all(
        not (a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3])
        for i, a in enumerate(boxes)
        for b in boxes[:i]
    )
    # The spread cameras keep their names; most of the cluster's are hidden, and the picture says so.
    assert names[:3] == labelled[:3] and len(labelled) <= 6
    assert f"{20 - len(labelled)} of 20 names hidden" in svg
