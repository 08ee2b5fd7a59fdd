"""Pose-free captures whose photos differ in size: resized copies, and portrait photos among landscape
ones (pixels turned, no EXIF orientation: what a phone held upright stores). Each size gets a camera of
its own (COLMAP's automatic reconstruction), each view keeps its own intrinsics through the camera file,
undistortion and `reconstruct`. The truths: DTU scan 24's calibration (from ../shared/data, or the
100x75 fixture in tests/data), scaled with the photo (K' = diag(s, s, 1) K) or turned with it
(`surfsplat.geometry.orientation.displayed_camera`, orientation 6: 90 degrees clockwise)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from surfsplat.cli import main
from surfsplat.data.cameras import load_cameras, pinhole_of
from surfsplat.geometry.lens import Lens
from surfsplat.geometry.orientation import displayed_camera
from surfsplat.poses import PoseConfig, estimate_cameras, relative_pose_errors
from surfsplat.poses.errors import aligned_pose_errors

FIXTURE = Path(__file__).resolve().parents[1] / "data" / "dtu_scan24"


def _mixed_views(root: Path, images: str, views: list[int], kind: str, folder: Path, every: int, exif: bool = False):
    """The photos of `views` written to `folder`, every `every`-th one (from the second) resized to 0.75x
    ("resized") or turned 90 degrees clockwise ("portrait"); with their true K [V, 3, 3] and c2w [V, 4, 4], and
    the 35 mm equivalent focal length written in each one's EXIF (with `exif`; else None)."""
    from surfsplat.data.load import load_scene

    scene = load_scene(root, images=images, dtype=torch.float64)
    folder.mkdir(parents=True, exist_ok=True)
    paths, Ks, c2ws, f35s = [], [], [], []
    for k, v in enumerate(views):
        photo = Image.open(root / images / scene.names[v]).convert("RGB")
        W, H = photo.size
        K, c2w = scene.cameras.K[v].clone(), scene.cameras.c2w[v].clone()
        K[0, 1] = 0.0  # DTU's calibration has a skew of 5e-5 px, which no turned pinhole keeps
        f_photo = float(K[0, 0])
        if k % every == 1 and kind == "resized":
            w, h = round(0.75 * W), round(0.75 * H)
            photo = photo.resize((w, h), Image.Resampling.LANCZOS)
            K[:2] *= torch.tensor([w / W, h / H], dtype=K.dtype)[:, None]
            f_photo *= w / W
        elif k % every == 1 and kind == "portrait":
            photo = photo.transpose(Image.Transpose.ROTATE_270)  # as EXIF orientation 6 displays a stored photo
            K, c2w, _ = displayed_camera(K, c2w, W, H, 6)
        paths.append(folder / f"{k:02d}_{v:06d}.png")
        tags = Image.Exif()
        f35s.append(round(f_photo * math.hypot(36, 24) / math.hypot(*photo.size)) if exif else None)
        if exif:  # the 35 mm equivalent focal length (an integer, as phones write it) of the lens's fx
            tags.get_ifd(0x8769)[0xA405] = f35s[-1]
        photo.save(paths[-1], exif=tags.tobytes())
        Ks.append(K)
        c2ws.append(c2w)
    return paths, torch.stack(Ks), torch.stack(c2ws), f35s


def _sizes(paths: list[Path]) -> list[tuple[int, int]]:
    return [Image.open(p).size for p in paths]


@pytest.mark.slow
@pytest.mark.parametrize("kind, every", [("resized", 2), ("portrait", 3)])
def test_dtu_scan24_of_two_sizes_pose_free_within_a_degree_and_each_k_its_own(data_dir, tmp_path, kind, every):
    """DTU scan 24 views 12-26 (400x300) with every other view resized to 300x225, or every third turned to a
    300x400 portrait: a camera per size, rotations within 1 degree of the calibration, each view's fitted
    focal length within 3 % of its own true one and its principal point at its own centre."""
    root = data_dir / "dtu_scan24"
    paths, K_true, c2w_true, _ = _mixed_views(root, "images_4", list(range(12, 27)), kind, tmp_path, every)
    cams, summary = estimate_cameras(paths)
    names = [p.name for p in paths]
    assert cams.names == names, summary.lines()
    sizes = _sizes(paths)
    assert [(c.width, c.height) for c in summary.cameras] == list(dict.fromkeys(sizes))
    assert summary.sizes == dict(zip(names, sizes))
    rot, _ = aligned_pose_errors(cams.cameras.c2w, c2w_true)
    focal_errors = []
    for i, (name, (w, h)) in enumerate(zip(names, sizes)):
        lens = cams.lenses[i]
        assert lens == summary.lens_of(name) and (lens.width, lens.height) == (w, h) and lens.model == "SIMPLE_RADIAL"
        assert lens.params[1:3] == (w / 2, h / 2)  # the principal point stays at its own photo's centre
        focal_errors.append(lens.params[0] / float(K_true[i, 0, 0]) - 1)
        torch.testing.assert_close(cams.cameras.K[i], pinhole_of(lens).intrinsics(), rtol=0, atol=0)
        # the K returned (its pinhole's) against the true K of this photo: focal lengths within 3 %, the
        # principal point within 3 % of the photo's width and height (DTU's sits 1.5 % off the centre)
        K, T = cams.cameras.K[i], K_true[i]
        assert abs(float(K[0, 0] / T[0, 0]) - 1) < 0.03 and abs(float(K[1, 1] / T[1, 1]) - 1) < 0.03
        assert abs(float(K[0, 2] - T[0, 2])) < 0.03 * w and abs(float(K[1, 2] - T[1, 2])) < 0.03 * h
    print(f"DTU 12-26 {kind}: max rotation error {rot.max():.3f} deg, focal errors {np.round(focal_errors, 4)}")
    assert rot.max() < 1.0
    assert max(abs(e) for e in focal_errors) < 0.03
    # the camera file keeps each view's lens, and reads back with each view's size
    from surfsplat.data.cameras import save_cameras

    written = save_cameras(
        tmp_path / "cameras.json", cams.cameras, cams.width, cams.height, cams.names, lenses=cams.lenses
    )
    again = load_cameras(written)
    assert again.lenses == cams.lenses
    torch.testing.assert_close(again.cameras.c2w, cams.cameras.c2w, rtol=0, atol=1e-12)


def test_fixture_pair_landscape_and_portrait_two_cameras_each_its_exif_focal(tmp_path, capsys):
    """The 100x75 fixture's views 12 and 13, the second turned to a 75x100 portrait, each with its 35 mm
    equivalent focal length in EXIF; `surfsplat poses` with the pinhole model (at 100x75 a SIMPLE_RADIAL's k
    is not determined by two views: it came out from -2.5 to 6 on the fixture's pairs): two cameras, each its size's
    EXIF focal and centre, the relative rotation within 1 degree of the calibration turned with the photo,
    and a camera file whose frames each record their own size's lens."""
    paths, _, c2w_true, f35 = _mixed_views(FIXTURE, "images_16", [12, 13], "portrait", tmp_path, 2, exif=True)
    out = tmp_path / "cameras.json"
    assert main(["poses", *map(str, paths), "--out", str(out), "--camera-model", "SIMPLE_PINHOLE"]) == 0
    printed = capsys.readouterr().out
    assert "registered 2 of 2 images (two-view)" in printed
    assert "2 cameras, one per image size" in printed
    assert "camera 100x75 (1 image: 00_000012.png): SIMPLE_PINHOLE f " in printed
    assert "camera 75x100 (1 image: 01_000013.png): SIMPLE_PINHOLE f " in printed
    cams = load_cameras(out)
    # the 35 mm route uses the diagonal, 125 px in both shapes
    expected = [
        Lens("SIMPLE_PINHOLE", 100, 75, (f35[0] * 125.0 / math.hypot(36, 24), 50.0, 37.5)),
        Lens("SIMPLE_PINHOLE", 75, 100, (f35[1] * 125.0 / math.hypot(36, 24), 37.5, 50.0)),
    ]
    for got, want in zip(cams.lenses, expected):
        assert (got.model, got.width, got.height) == (want.model, want.width, want.height)
        assert got.params == pytest.approx(want.params, rel=1e-12)  # two views: f stays at its EXIF source
    for i, lens in enumerate(cams.lenses):  # each K the lens's own, in its own photo's pixels
        torch.testing.assert_close(cams.cameras.K[i], lens.intrinsics(), rtol=1e-12, atol=1e-9)
    rot, _ = relative_pose_errors(cams.cameras.c2w, c2w_true)
    print(f"fixture 12-13, 13 turned: rotation error {rot[0]:.3f} deg")
    assert rot[0] < 1.0
    # the same photos give the same cameras bit for bit, with a camera per size too
    config = PoseConfig(camera_model="SIMPLE_PINHOLE")
    first, _ = estimate_cameras(paths, config=config)
    second, _ = estimate_cameras(paths, config=config)
    assert torch.equal(first.cameras.c2w, second.cameras.c2w) and torch.equal(first.cameras.K, second.cameras.K)
    assert first.lenses == second.lenses == cams.lenses


def test_reconstruct_pose_free_landscape_and_portrait_each_view_its_own_k(tmp_path, capsys):
    """`reconstruct` without cameras on the fixture pair of two shapes, end to end (`--optimize-steps 0`):
    each view's K is its own photo's camera rescaled and centre-cropped to the working size (the closed
    form of rescale_and_crop), the portrait's crop is named, and the folder records a lens a view."""
    from surfsplat.model.checkpoint import save_checkpoint
    from surfsplat.model.surfsplat import SurfSplat

    torch.manual_seed(0)
    weights = tmp_path / "tiny" / "model.safetensors"
    save_checkpoint(SurfSplat.from_preset("tiny").eval(), weights)
    paths, _, _, _ = _mixed_views(FIXTURE, "images_16", [12, 13], "portrait", tmp_path / "photos", 2, exif=True)
    out = tmp_path / "out"
    argv = ["reconstruct", "--checkpoint", str(weights), "--images", *map(str, paths), "--out", str(out)]
    argv += ["--camera-model", "SIMPLE_PINHOLE", "--size", "32", "48", "--formats", "ply", "--raw-3dgs"]
    code = main([*argv, "--optimize-steps", "0", "--refine-steps", "0", "--no-progress", "--device", "cpu"])
    shown = capsys.readouterr()
    assert code == 0, shown.err
    # the portrait, scaled by max(32 / 100, 48 / 75) to 48x64, keeps 32 of its 64 rows
    assert "01_000013.png (75x100) keeps 50%, its top and bottom cut" in shown.err
    estimated = load_cameras(out / "estimated_cameras.json")
    assert [(lens.width, lens.height) for lens in estimated.lenses] == [(100, 75), (75, 100)]
    written = json.loads((out / "cameras.json").read_text())
    assert (written["width"], written["height"]) == (48, 32)
    shape = (32, 48)
    for i, (w, h) in enumerate([(100, 75), (75, 100)]):
        expected = estimated.cameras.K[i].clone()
        s = max(shape[0] / h, shape[1] / w)
        rw, rh = max(shape[1], round(w * s)), max(shape[0], round(h * s))
        expected[0] *= rw / w
        expected[1] *= rh / h
        expected[0, 2] -= (rw - shape[1]) // 2
        expected[1, 2] -= (rh - shape[0]) // 2
        torch.testing.assert_close(torch.tensor(written["frames"][i]["K"], dtype=torch.float64), expected)
        assert Lens.from_dict(written["frames"][i]["lens"]) == estimated.lenses[i]
    poses = json.loads((out / "poses.json").read_text())
    assert poses["image_sizes"] == {"00_000012.png": [100, 75], "01_000013.png": [75, 100]}
    assert [(c["width"], c["height"], c["images"]) for c in poses["cameras"]] == [
        (100, 75, ["00_000012.png"]),
        (75, 100, ["01_000013.png"]),
    ]


@pytest.mark.slow
def test_reconstruct_pose_free_dtu_with_portraits_undistorts_each_view_to_its_own_pinhole(data_dir, tmp_path):
    """`reconstruct` without cameras on DTU scan 24 views 12-26 (every other one, 400x300) with every third
    turned to a 300x400 portrait, the default lens model (SIMPLE_RADIAL, a camera per size): each view is read
    undistorted to its own size's pinhole and its K is that pinhole's rescaled and cropped to the working
    size; the camera file it writes, given back with the same photos, gives the same cameras."""
    import surfsplat
    from surfsplat.capture import OptimizeConfig

    root = data_dir / "dtu_scan24"
    paths, _, c2w_true, _ = _mixed_views(root, "images_4", list(range(12, 27, 2)), "portrait", tmp_path / "p", 3)
    options = surfsplat.CaptureOptions(views_per_pass=4, optimize=OptimizeConfig(steps=0))
    shape = (64, 96)
    run = dict(checkpoint="tiny-synthetic", size=shape, capture=options, device="cpu", progress=False)
    scene = surfsplat.reconstruct(paths, **run)
    estimated = scene.pose_cameras
    assert estimated.names == [p.name for p in paths] and len(scene.poses.cameras) == 2
    rot, _ = aligned_pose_errors(estimated.cameras.c2w, c2w_true)
    assert rot.max() < 1.0, rot
    for i, (lens, (w, h)) in enumerate(zip(estimated.lenses, _sizes(paths))):
        pinhole = pinhole_of(lens)
        assert (lens.model, lens.width, lens.height) == ("SIMPLE_RADIAL", w, h)
        assert (pinhole.width < w) and (pinhole.height < h)  # the largest valid region of its own photo
        expected = pinhole.intrinsics()
        s = max(shape[0] / pinhole.height, shape[1] / pinhole.width)
        rw, rh = max(shape[1], round(pinhole.width * s)), max(shape[0], round(pinhole.height * s))
        expected[0] *= rw / pinhole.width
        expected[1] *= rh / pinhole.height
        expected[0, 2] -= (rw - shape[1]) // 2
        expected[1, 2] -= (rh - shape[0]) // 2
        torch.testing.assert_close(scene.cameras.K[i].double(), expected, rtol=1e-6, atol=1e-4)
    assert scene.lenses == dict(zip(estimated.names, estimated.lenses))
    out = tmp_path / "out"
    scene.save(out, formats=("ply",))
    again = surfsplat.reconstruct(paths, cameras=out / "estimated_cameras.json", **run)
    torch.testing.assert_close(again.cameras.K, scene.cameras.K, rtol=0, atol=0)
    torch.testing.assert_close(again.cameras.c2w, scene.cameras.c2w, rtol=0, atol=1e-6)


def test_each_size_is_extracted_at_its_own_size_with_its_own_first_octave(tmp_path, monkeypatch):
    """Sizes on both sides of sift_upsample_below: every photo goes to SIFT once, at its own size's extraction
    size, with its size's first octave (-1, upsampled, below the threshold), and its keypoints come back in
    its own pixels (the extraction-size keypoints divided by its own scale)."""
    import pycolmap

    from surfsplat.poses.estimate import _extraction_size, _Workspace

    small = np.asarray(Image.open(FIXTURE / "images_16" / "000012.png").convert("RGB"))  # 100x75
    large = np.asarray(Image.fromarray(small).resize((160, 120), Image.Resampling.LANCZOS))
    config = PoseConfig(min_extraction_size=64, max_size=140, sift_upsample_below=120)
    sizes = [(100, 75), (160, 120)]
    ext = [_extraction_size(s, config) for s in sizes]
    assert ext == [(100, 75), (140, 105)]  # kept, and the long side brought down to max_size
    calls, real = [], pycolmap.extract_features

    def spy(*args, **kwargs):
        calls.append((list(kwargs["image_names"]), kwargs["extraction_options"].sift.first_octave))
        return real(*args, **kwargs)

    monkeypatch.setattr(pycolmap, "extract_features", spy)
    monkeypatch.setattr(pycolmap.logging, "minloglevel", 3)  # as estimate_cameras runs COLMAP: quiet
    work = _Workspace(tmp_path, ["a", "b", "c"], sizes, [0, 1, 0], [120.0, 192.0], "prior", "SIMPLE_RADIAL", config)
    work.extract([small, large, small], ext)
    assert calls == [(["s0/000000.png", "s0/000002.png"], -1), (["s1/000001.png"], 0)]
    db = pycolmap.Database.open(work.database)
    try:
        cameras = {c.camera_id: c for c in db.read_all_cameras()}
        images = {im.name: im for im in db.read_all_images()}
        assert [images[f].camera_id for f in work.files] == [1, 2, 1]  # a camera per size
        for camera_id, (w, h), f in ((1, sizes[0], 120.0), (2, sizes[1], 192.0)):
            assert (cameras[camera_id].width, cameras[camera_id].height) == (w, h)
            assert list(cameras[camera_id].params) == [f, w / 2, h / 2, 0.0]  # in the input pixels of its size
        kp_large = db.read_keypoints(images["s1/000001.png"].image_id)
    finally:
        db.close()
    # keypoints in the 160x120 photo's own pixels: the keypoints of its 140x105 extraction copy, extracted
    # alone (one size, nothing rescaled), times 160 / 140
    copy = np.asarray(Image.fromarray(large).resize((140, 105), Image.Resampling.LANCZOS))
    (tmp_path / "alone").mkdir()
    alone = _Workspace(tmp_path / "alone", ["b"], [(140, 105)], [0], [168.0], "prior", "SIMPLE_RADIAL", config)
    alone.extract([copy], [(140, 105)])
    db = pycolmap.Database.open(alone.database)
    try:
        reference = db.read_keypoints(alone.ids["b"])
    finally:
        db.close()
    assert len(reference) == len(kp_large) > 20
    np.testing.assert_allclose(kp_large[:, :2], reference[:, :2] * np.float32(160 / 140), rtol=1e-6)
