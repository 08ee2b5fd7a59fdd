"""The browser app (`surfsplat app`): uploads made safe (names, kinds, the size limit), session folders
removed on time, progress following the library's stages, and, in headless Chromium through
Playwright, the whole flow: two fern photos -> the 3D view drawn, the downloads matching
reconstruction.json, then a broken photo answered with one line."""

from __future__ import annotations

import io
import json
import os
import socket
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from surfsplat.app.files import SessionFolders, prepare_uploads, safe_name
from surfsplat.app.run import STAGES, RunCancelled, StageTracker, closure_table, weights_choices
from surfsplat.utils.checks import SurfSplatInputError
from surfsplat.utils.log import listen_progress, progress

FERN = Path(__file__).resolve().parents[1] / "data" / "llff_fern" / "images_16"


# ------------------------------------------------------------------------------------------ uploads
@pytest.mark.parametrize(
    "name, safe",
    [
        ("IMG_4026.PNG", "IMG_4026.png"),
        ("../../etc/passwd", "passwd"),
        ("..\\..\\boot.ini", "boot.ini"),
        ("a photo (1).jpg", "a_photo_1.jpg"),
        ("/abs/path/.hidden.png", "hidden.png"),
        ("..", "fallback"),
        ("фото.jpg", "fallback.jpg"),
        ("x.tar;rm -rf", "x"),  # not a plain suffix: dropped
        ("cameras.json", "cameras.json"),
    ],
)
def test_safe_name_keeps_only_plain_characters(name, safe):
    out = safe_name(name, "fallback")
    assert out == safe
    assert set(out) <= set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789._-")


def _files(tmp_path: Path, names: dict[str, bytes]) -> list[Path]:
    """Uploads as a server stores them: each in a folder of its own, under its original name."""
    out = []
    for k, (name, data) in enumerate(names.items()):
        path = tmp_path / "upload" / str(k) / name
        path.parent.mkdir(parents=True)
        path.write_bytes(data)
        out.append(path)
    return out


def test_uploads_are_copied_into_the_session_under_safe_unique_names(tmp_path):
    photo = (FERN / "IMG_4026.png").read_bytes()
    files = _files(tmp_path, {"IMG 1.png": photo, "b.png": photo})
    session = tmp_path / "session"
    uploads = prepare_uploads(files, None, session, 10**9, names=["../../evil.png", "..\\evil.png"])
    assert [p.name for p in uploads.images] == ["evil.png", "evil_2.png"]
    assert all(p.parent == session / "inputs" and p.read_bytes() == photo for p in uploads.images)
    assert uploads.capture == uploads.images and uploads.video is None and uploads.cameras is None
    assert sorted(p.name for p in session.rglob("*") if p.is_file()) == ["evil.png", "evil_2.png"]


def test_a_video_and_a_camera_file(tmp_path):
    video, cams = _files(tmp_path, {"walk.MP4": b"not decoded here", "cams.json": b"{}"})
    uploads = prepare_uploads([video], cams, tmp_path / "s", 10**9)
    assert uploads.capture == tmp_path / "s" / "inputs" / "walk.mp4" and uploads.images == []
    assert uploads.cameras == tmp_path / "s" / "inputs" / "cams.json"


@pytest.mark.parametrize(
    "names, cameras, limit, message",
    [
        ({}, None, 10**9, "photos: drop two or more photos of one scene, one video, or a zip or folder"),
        ({"notes.txt": b"x", "a.png": b"x"}, None, 10**9, "notes.txt: neither a photo (.png"),
        ({"a.mp4": b"x", "b.png": b"x"}, None, 10**9, "expected two or more photos or one video, got 1 photos and 1"),
        ({"a.mp4": b"x", "b.mov": b"x"}, None, 10**9, "got 0 photos and 2 videos"),
        (
            {"a.png": b"x", "cameras.json": b"{}"},
            None,
            10**9,
            "cameras.json: a camera file goes in the camera file box",
        ),
        ({"a.png": b"x", "b.png": b"x"}, "poses.txt", 10**9, "cameras: expected a JSON camera file"),
        (
            {"a.png": b"x" * 600_000, "b.png": b"x" * 600_000},
            None,
            10**6,
            "upload: 1.2 MB in all is over this server's limit of 1.0 MB",
        ),
    ],
)
def test_bad_uploads_get_one_line_before_anything_is_copied(tmp_path, names, cameras, limit, message):
    files = _files(tmp_path, names)
    camera_file = None
    if cameras is not None:
        camera_file = tmp_path / cameras
        camera_file.write_text("x")
    with pytest.raises(SurfSplatInputError) as err:
        prepare_uploads(files, camera_file, tmp_path / "session", limit)
    assert message in str(err.value) and "\n" not in str(err.value)
    assert str(tmp_path) not in str(err.value)  # no server path on the page
    assert not (tmp_path / "session").exists()


def test_session_folders_are_removed_after_their_time_and_not_while_in_use(tmp_path):
    sessions = SessionFolders(tmp_path / "root", keep_seconds=60)
    old, busy = sessions.new(), sessions.new()
    sessions.release(old)
    (old / "inputs").mkdir()
    (old / "inputs" / "a.png").write_bytes(b"x")
    other = tmp_path / "root" / "not-a-session"
    other.mkdir()
    assert sessions.remove_expired(now=time.time() + 30) == []
    assert sessions.remove_expired(now=time.time() + 120) == [old]
    assert not old.exists() and busy.exists() and other.exists()  # in use, and not ours: kept
    sessions.release(busy)
    assert sessions.remove_expired(now=time.time() + 120) == [busy]
    with pytest.raises(SurfSplatInputError, match="keep_seconds"):
        SessionFolders(tmp_path, 0)


# ------------------------------------------------------------------------------------------ progress
def test_progress_listener_sees_every_loop_shown_or_not_and_can_stop_it():
    seen = []
    with listen_progress(lambda desc, done, total: seen.append((desc, done, total))):
        assert list(progress(range(3), desc="forward passes", enabled=False)) == [0, 1, 2]
        with progress(total=2, desc="refine") as bar:
            bar.update()
            bar.set_postfix(loss=1.0)
            bar.update()
    assert seen == [("forward passes", 0, 3), ("forward passes", 1, 3), ("forward passes", 2, 3)] + [
        ("forward passes", 3, 3),
        ("refine", 0, 2),
        ("refine", 1, 2),
        ("refine", 2, 2),
    ]
    assert list(progress(range(2), enabled=False)) == [0, 1]  # outside: nothing is reported

    def stop(desc, done, total):
        if done >= 2:
            raise RunCancelled("stopped")

    ran = []
    with pytest.raises(RunCancelled), listen_progress(stop):
        for i in progress(range(10), desc="render camera path", enabled=False):
            ran.append(i)
    assert ran == [0, 1]


def test_stage_tracker_follows_the_stages_in_order():
    reports = []
    tracker = StageTracker(lambda f, text: reports.append((round(f, 3), text)))
    tracker.enter("cameras")
    tracker("forward passes", 0, 2)
    tracker("forward passes", 2, 2)
    tracker("render turntable", 48, 48)  # the mesh follows without a loop of its own
    assert reports == [
        (0.0, "cameras"),
        (0.10, "network passes and fusion: 0/2"),
        (0.25, "network passes and fusion: 2/2"),
        (0.88, "export: turntable: 48/48"),
        (0.88, "export: mesh"),
    ]
    assert [end for _, _, end in STAGES] == sorted(end for _, _, end in STAGES) and STAGES[-1][2] == 1.0
    stopped = StageTracker(lambda f, text: None, cancelled=lambda: True)
    with pytest.raises(RunCancelled):
        stopped("refine", 1, 10)


def test_weights_offer_cached_release_weights_first_then_the_demo_model(monkeypatch):
    from surfsplat.model import pretrained

    cached = {"re10k-256x448-base"}
    monkeypatch.setattr(pretrained, "cached_file", lambda entry: Path("/x") if entry.name in cached else None)
    names = [name for _, name in weights_choices()]
    assert names[:2] == ["re10k-256x448-base", "tiny-synthetic"]
    labels = dict((name, label) for label, name in weights_choices())
    assert "downloads on first use; CC BY-NC-SA 4.0" in labels["re10k-256x256-small"]
    assert "procedural rooms at 64 px" in labels["tiny-synthetic"]


def test_closure_table_reads_reconstruction_json_keys():
    closure = {
        "closure": 0.96,
        "closed": True,
        "mean_alpha": {"x1": 0.965, "x2": 0.935, "x4": 0.927},
        "coverage": {k: {"alpha>=0.5": 0.99, "alpha>=0.9": 0.8} for k in ("x1", "x2", "x4")},
        "undersized_share": 0.0,
        "opacity_quantiles": {"p50": 0.53},
        "problems": [],
    }
    table = closure_table(closure)
    assert "**Closure** 0.960 (alpha x4 / x1), closed" in table
    assert "| x4 | 0.927 | 99.0% | 80.0% |" in table and table.index("| x1 |") < table.index("| x4 |")


def test_the_command_is_registered_and_refuses_bad_limits():
    from surfsplat.app.config import AppConfig
    from surfsplat.cli import build_parser

    args = build_parser().parse_args(["app", "--port", "0", "--max-upload-mb", "5", "--keep-minutes", "2"])
    assert (args.host, args.port, args.max_upload_mb, args.keep_minutes, args.share) == ("127.0.0.1", 0, 5, 2, False)
    assert AppConfig(host="0.0.0.0").local_only is False and AppConfig().local_only
    with pytest.raises(SurfSplatInputError, match="--max-upload-mb"):
        AppConfig(max_upload_mb=0)
    with pytest.raises(SurfSplatInputError, match="--keep-minutes"):
        AppConfig(keep_minutes=-1)


# ------------------------------------------------------------------------------------------ browser
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """The app on a free localhost port, in this process (gradio serves from its own thread)."""
    pytest.importorskip("gradio", reason='the app needs gradio (pip install "surfsplat[app]")')
    from surfsplat.app import AppConfig, build

    root = tmp_path_factory.mktemp("sessions")
    config = AppConfig(
        port=_free_port(),
        working_size=64,
        refine_fits=0,
        sessions_dir=str(root),
        max_upload_mb=20,
        export=dict(path_frames=8, turntable_frames=8, mesh_resolution=48, bake_steps=4),
    )
    demo = build(config)
    demo.launch(
        server_name=config.host,
        server_port=config.port,
        prevent_thread_lock=True,
        ssr_mode=False,
        quiet=True,
        allowed_paths=[str(root)],
    )
    yield demo, root
    demo.close()


@pytest.mark.slow
def test_browser_two_photos_to_a_drawn_scene_and_downloads_then_a_broken_photo(served, tmp_path):
    """What a person does: drop two fern photos, press Start, see the 3D view drawn (the canvas is not
    blank), download the PLY (its vertices are reconstruction.json's surfels) and the zip; then drop
    a photo that is not one and read the library's one line, with no traceback and no server path."""
    from tests.helpers.browser import chromium

    sync_api = pytest.importorskip("playwright.sync_api", reason="needs playwright (pip install playwright)")
    from plyfile import PlyData

    exe = chromium()
    demo, root = served
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=exe,
            args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
        )
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 900}, accept_downloads=True)
            page.goto(demo.local_url, timeout=60_000)
            page.locator("#start").wait_for(timeout=60_000)
            page.screenshot(path=str(tmp_path / "empty.png"))

            page.locator("#photos input[type=file]").set_input_files(
                [str(FERN / "IMG_4026.png"), str(FERN / "IMG_4027.png")]
            )
            page.locator("#photos td.filename[aria-label='IMG_4027.png']").wait_for(timeout=30_000)
            page.locator("#start").click()
            page.locator("#status").get_by_text("Done.").wait_for(timeout=240_000)

            canvas = page.locator("#view3d canvas").first
            canvas.wait_for(timeout=30_000)
            deadline = time.monotonic() + 60
            while True:  # software WebGL draws the splats a moment after the file arrives
                shot = np.asarray(_png(canvas.screenshot()))
                spread = shot[..., :3].reshape(-1, 3).std(0).max()
                if spread > 10 or time.monotonic() > deadline:
                    break
                time.sleep(1)
            assert spread > 10, f"the 3D view looks blank (pixel spread {spread:.1f})"
            page.screenshot(path=str(tmp_path / "result.png"))

            links = page.locator("#downloads a")
            rows = page.locator("#downloads td.filename")
            names = [rows.nth(i).get_attribute("aria-label") for i in range(rows.count())]
            assert names == ["surfels_3dgs.ply", "surfels.ply", "mesh.ply", "cameras.json", "surfsplat_result.zip"]
            files = {}
            for name in ("surfels_3dgs.ply", "surfsplat_result.zip"):
                with page.expect_download() as info:
                    links.nth(names.index(name)).click()
                files[name] = Path(info.value.path())
            archive = zipfile.ZipFile(files["surfsplat_result.zip"])
            summary = json.loads(archive.read("reconstruction.json"))
            vertices = PlyData.read(str(files["surfels_3dgs.ply"]))["vertex"].count
            assert vertices == summary["surfels"] > 0
            assert PlyData.read(io.BytesIO(archive.read("surfels.ply")))["vertex"].count == summary["surfels"]
            assert {"mesh.ply", "cameras.json", "path.mp4", "app/grid.png", "app/view.ply"} <= set(archive.namelist())
            assert PlyData.read(io.BytesIO(archive.read("app/view.ply")))["vertex"].count == summary["surfels"]

            broken = tmp_path / "IMG_9999.png"
            broken.write_bytes(b"this is not a PNG")
            page.locator("#photos button[aria-label='Clear']").first.click()
            page.locator("#photos input[type=file]").set_input_files([str(FERN / "IMG_4026.png"), str(broken)])
            page.locator("#photos td.filename[aria-label='IMG_9999.png']").wait_for(timeout=30_000)
            page.locator("#start").click()
            status = page.locator("#status")
            status.get_by_text("Cannot reconstruct").wait_for(timeout=120_000)
            text = status.inner_text().strip()
            page.screenshot(path=str(tmp_path / "error.png"))
        finally:
            browser.close()
    assert text.startswith("Cannot reconstruct: IMG_9999.png: cannot read image header"), text
    assert "\n" not in text and "Traceback" not in text and str(root) not in text


def _png(data: bytes):
    import imageio.v3 as iio

    return iio.imread(io.BytesIO(data))


def _photo(path: Path, size: tuple[int, int]) -> Path:
    import imageio.v3 as iio

    iio.imwrite(path, np.random.default_rng(0).integers(0, 255, (*size, 3), dtype=np.uint8))
    return path


def _still_video(path: Path) -> Path:
    """Five identical frames: the camera never moved, so one frame is usable."""
    import imageio.v3 as iio

    iio.imwrite(path, np.full((5, 64, 96, 3), 128, np.uint8), fps=5)
    return path


def _noise(path: Path, seed: int) -> Path:
    """A photo of pure noise: nothing in it matches another such photo."""
    import imageio.v3 as iio

    iio.imwrite(path, np.random.default_rng(seed).integers(0, 255, (64, 96, 3), dtype=np.uint8))
    return path


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda d: [_photo(d / "a.png", (40, 60))], "expected at least 2 images, got 1"),
        (lambda d: [_photo(d / "a.png", (40, 60)), d / "b.png"], "b.png: cannot read image header"),
        (lambda d: [_still_video(d / "still.mp4")], "only 1 usable frame among 5"),
        (
            lambda d: [_noise(d / "a.png", 1), _noise(d / "b.png", 2)],
            "only 0 verified matches (0 putative), at least 30 are needed: take the photos closer together",
        ),
    ],
    ids=["one photo", "not an image", "video without motion", "cameras not estimable"],
)
def test_the_librarys_one_line_reaches_the_page_without_server_paths(tmp_path, make, message):
    """What a run refuses before any heavy work, as the page shows it (`page._one_line`)."""
    from surfsplat.app.files import PathScrubber
    from surfsplat.app.page import _one_line
    from surfsplat.app.run import RunSettings, run_capture

    source = tmp_path / "browser"
    source.mkdir()
    (source / "b.png").write_bytes(b"not a PNG")
    session = tmp_path / "session"
    uploads = prepare_uploads(make(source), None, session, 10**9)
    with pytest.raises(SurfSplatInputError) as err:
        run_capture(uploads, RunSettings(working_size=64), session / "outputs")
    line = _one_line(err.value, PathScrubber(session))
    assert message in line and str(tmp_path) not in line and "\n" not in line


def test_the_space_is_the_package_and_the_app(tmp_path):
    """scripts/make_space.py lays out a Space whose requirements install the copy beside them."""
    import importlib.util

    script = Path(__file__).resolve().parents[2] / "scripts" / "make_space.py"
    spec = importlib.util.spec_from_file_location("make_space", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.make_space(tmp_path / "space")
    space = tmp_path / "space"
    assert (space / "src" / "surfsplat" / "app" / "__init__.py").is_file() and (space / "pyproject.toml").is_file()
    requirements = (space / "requirements.txt").read_text().split("\n")
    assert "torch==2.13.0" in requirements and ".[app]" in requirements
    front = (space / "README.md").read_text().split("---")[1]
    assert "sdk: gradio" in front and "app_file: app.py" in front and (space / "app.py").is_file()
    with pytest.raises(SystemExit, match="not empty"):
        module.make_space(space)


@pytest.mark.slow
def test_browser_a_zipped_capture_a_folder_upload_and_a_traversal_zip(served, tmp_path):
    """A zip of a COLMAP capture (photos in images/, the model in sparse/0) dropped in the photos box,
    then a nerfstudio capture folder chosen in the folder box (the browser sends its files flat):
    each run reads its own cameras and says so; then a zip with a '..' member is refused with one
    line. The page states the server's limits before anything is sent."""
    from tests.helpers.browser import chromium
    from tests.helpers.captures import write_capture, zip_folder

    sync_api = pytest.importorskip("playwright.sync_api", reason="needs playwright (pip install playwright)")
    exe = chromium()
    demo, root = served
    colmap = tmp_path / "colmap"
    write_capture(colmap, "colmap", views=2)
    archive = zip_folder(colmap, tmp_path / "fern_colmap.zip")
    nerfstudio = tmp_path / "nerfstudio"
    write_capture(nerfstudio, "transforms", views=2)
    bad = tmp_path / "bad.zip"
    with zipfile.ZipFile(bad, "w") as zf:
        zf.writestr("../evil.png", b"x")
    shots = Path(os.environ.get("SURFSPLAT_APP_SHOTS", tmp_path))
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=exe,
            args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
        )
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 1000})
            page.goto(demo.local_url, timeout=60_000)
            page.locator("#start").wait_for(timeout=60_000)
            status = page.locator("#status")
            limits = status.inner_text()
            page.screenshot(path=str(shots / "capture_empty.png"))

            page.locator("#photos input[type=file]").set_input_files([str(archive)])
            page.locator("#photos td.filename[aria-label='fern_colmap.zip']").wait_for(timeout=30_000)
            page.locator("#start").click()
            status.get_by_text("Done.").wait_for(timeout=300_000)
            zipped = status.inner_text()
            page.screenshot(path=str(shots / "capture_zip.png"), full_page=True)

            page.locator("#photos button[aria-label='Clear']").first.click()
            page.locator("#capture-folder input[type=file]").set_input_files(str(nerfstudio))
            page.locator("#capture-folder td.filename[aria-label='transforms.json']").wait_for(timeout=30_000)
            page.locator("#start").click()
            status.get_by_text("cameras: capture/transforms.json").wait_for(timeout=300_000)
            folder = status.inner_text()
            page.screenshot(path=str(shots / "capture_folder.png"), full_page=True)

            page.locator("#capture-folder button[aria-label='Clear']").first.click()
            page.locator("#photos input[type=file]").set_input_files([str(bad)])
            page.locator("#photos td.filename[aria-label='bad.zip']").wait_for(timeout=30_000)
            page.locator("#start").click()
            status.get_by_text("Cannot reconstruct").wait_for(timeout=120_000)
            refused = status.inner_text().strip()
            page.screenshot(path=str(shots / "capture_refused.png"), full_page=True)
        finally:
            browser.close()
    assert "20 MB of uploads and 60 views a run" in limits and "stops a run after 600 s" in limits, limits
    assert "cameras: fern_colmap/sparse/0 (COLMAP model of the capture folder)" in zipped, zipped
    assert "2 views" in zipped and "cameras: capture/transforms.json (transforms.json of the capture folder)" in folder
    assert refused == (
        "Cannot reconstruct: bad.zip: member '../evil.png' points outside the archive ('..'); "
        "refused (nothing was unpacked)"
    ), refused
    for text in (zipped, folder, refused):
        assert str(root) not in text and "/tmp" not in text, text
