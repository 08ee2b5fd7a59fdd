"""The app takes processed captures: a zip or a folder of photos with a transforms.json or a COLMAP
model, unpacked safely (traversal, links and bombs refused with one line, nothing written); a shared
server's limits on views and seconds, checked before the heavy work; and no server path in anything
the page gets."""

from __future__ import annotations

import json
import shutil
import stat
import struct
import tempfile
import time
import zipfile
from pathlib import Path

import pytest
import torch

from surfsplat.app.archive import arrange_folder, extract_zip
from surfsplat.app.config import AppConfig
from surfsplat.app.files import PathScrubber, SessionFolders, prepare_uploads
from surfsplat.app.run import STAGES, RunOverTime, StageTracker
from surfsplat.utils.checks import SurfSplatInputError
from tests.helpers.captures import FERN, write_capture, zip_folder

# the page's run at the smallest sizes: the tiny model at 64 px, a short export
SMALL = dict(
    working_size=64,
    refine_fits=0,
    optimize_seconds=0,
    export=dict(path_frames=4, turntable_frames=4, mesh_resolution=32, bake_steps=2),
)


def _request(config: AppConfig, files=(), capture_folder=(), camera_file=None):
    """One press of Start (`page.run_request`, what the page's button calls) and the session's folder."""
    from surfsplat.app.page import run_request

    sessions = SessionFolders(config.root(), 3600)
    before = set(config.root().iterdir()) if config.root().is_dir() else set()
    outputs = run_request(config, sessions, list(files), camera_file, list(capture_folder), "tiny-synthetic", 64, 0, 0)
    (folder,) = set(config.root().iterdir()) - before
    return outputs, folder


def _strings(value) -> list[str]:
    if isinstance(value, (list, tuple)):
        return [s for v in value for s in _strings(v)]
    return [] if value is None else [str(value)]


def _no_server_path(outputs, root: Path) -> None:
    """Nothing the page gets names the sessions' root or the temporary folder, except the files it
    serves (the 3D view, grid, plot, video and downloads: gradio needs their paths, and shows names)."""
    texts = [outputs[0], outputs[3]]  # the status line and the closure table
    for text in texts:
        assert str(root) not in text and tempfile.gettempdir() not in text and "/tmp" not in text, text


# ------------------------------------------------------------------------------------------ runs
@pytest.mark.slow
@pytest.mark.parametrize("kind", ["transforms", "colmap"])
def test_a_zipped_capture_runs_with_its_own_cameras(tmp_path, kind):
    """A zip of a folder holding the fern photos in images/ and their transforms.json (or sparse/0):
    the run's cameras are the file's, exactly (estimated cameras would sit in another frame and scale),
    and nothing the page gets or the downloads hold names the server's folders."""
    capture = tmp_path / "fern"
    cams = write_capture(capture, kind, views=2)
    archive = zip_folder(capture, tmp_path / "fern.zip", top="fern")
    config = AppConfig(sessions_dir=str(tmp_path / "sessions"), **SMALL)
    outputs, folder = _request(config, files=[archive])
    status = outputs[0]
    assert status.startswith("**Done.**"), status
    camera_file = "transforms.json" if kind == "transforms" else "sparse/0"
    assert f"cameras: fern/fern/{camera_file} (" in status, status
    _no_server_path(outputs, config.root())
    written = json.loads((folder / "outputs" / "cameras.json").read_text())
    assert [f["name"] for f in written["frames"]] == cams.names
    c2w = torch.tensor([f["c2w"] for f in written["frames"]], dtype=torch.float64)
    torch.testing.assert_close(c2w, cams.cameras.c2w, atol=1e-5, rtol=0)
    for text_file in (folder / "outputs").rglob("*.json"):  # the downloads name the uploads by their own names
        assert str(folder) not in text_file.read_text(), text_file


def test_the_python_api_takes_a_capture_folder_and_says_what_wins(tmp_path, caplog):
    """reconstruct("capture/"): a folder with a transforms.json is a processed capture (its listed photos,
    its cameras); with cameras=None its photos get estimated cameras; a plain folder of photos is
    photos whose cameras are estimated, as before."""
    from surfsplat.reconstruction.capture_folder import capture_views

    capture = tmp_path / "capture"
    cams = write_capture(capture, "transforms", views=3)
    (capture / "images" / "not_listed.png").write_bytes((FERN / "images_16" / "IMG_4031.png").read_bytes())
    with caplog.at_level("INFO", logger="surfsplat"):
        images, given, source = capture_views(capture, "auto", None)
    assert images == [capture / "images" / n for n in cams.names]  # the listed ones, in the file's order
    torch.testing.assert_close(given.cameras.c2w, cams.cameras.c2w, atol=1e-12, rtol=0)
    assert source == f"{capture / 'transforms.json'} (transforms.json of the capture folder)"
    assert "a processed capture (transforms.json): its 3 listed photos and their cameras are used" in caplog.text
    assert capture_views(capture, None, None)[1:] == (None, None)
    assert capture_views(capture, None, None)[0] == images
    photos = tmp_path / "photos"
    photos.mkdir()
    assert capture_views(photos, "auto", None) == (photos, None, None)  # a plain folder: estimated


def test_reconstruct_a_colmap_capture_folder_by_default(tmp_path):
    """The default cameras="auto" reads a folder's sparse/0: the scene's cameras are the model's."""
    import surfsplat

    capture = tmp_path / "capture"
    cams = write_capture(capture, "colmap", views=2)
    scene = surfsplat.reconstruct(capture, size=(64, 64), device="cpu", progress=False)
    assert scene.names == cams.names and "COLMAP model of the capture folder" in scene.cameras_source
    torch.testing.assert_close(scene.cameras.c2w.double(), cams.cameras.c2w, atol=1e-5, rtol=0)


# ------------------------------------------------------------------------------------------ no server path
def test_errors_of_a_capture_reach_the_page_without_server_paths(tmp_path):
    """A transforms.json listing a photo the zip lacks, and a listed photo that is not one: the page
    gets the library's one line, naming the files by the zip's own names."""
    config = AppConfig(sessions_dir=str(tmp_path / "sessions"), **SMALL)
    missing = tmp_path / "missing"
    write_capture(missing, "transforms", views=2)
    (missing / "images" / "IMG_4027.png").unlink()
    outputs, folder = _request(config, files=[zip_folder(missing, tmp_path / "fern.zip")])
    assert outputs[0].startswith("**Cannot reconstruct:**") and "fern/transforms.json" in outputs[0], outputs[0]
    _no_server_path(outputs, config.root())
    assert not (folder / "outputs").exists()

    corrupt = tmp_path / "corrupt"
    write_capture(corrupt, "transforms", views=2)
    (corrupt / "images" / "IMG_4027.png").write_bytes(b"not a PNG")
    outputs, _ = _request(config, files=[zip_folder(corrupt, tmp_path / "broken.zip")])
    assert outputs[0].startswith("**Cannot reconstruct:** broken/images/IMG_4027.png: cannot read image"), outputs[0]
    _no_server_path(outputs, config.root())


def test_the_scrubber_names_uploads_and_cuts_other_server_paths(tmp_path):
    session = tmp_path / "root" / "s1-ab"
    scrub = PathScrubber(session, tmp_path / "root")
    text = (
        f"{session}/inputs/cap/images/b.png: cannot identify image file '{session}/inputs/cap/images/b.png' "
        f"(listed in {session}/inputs/cap/transforms.json); weights {Path.home()}/.cache/w.safetensors; "
        f"{tmp_path}/root/s2-cd/inputs/x.png; x4 / x1 at hf://a/b"
    )
    assert scrub(text) == (
        "cap/images/b.png: cannot identify image file 'cap/images/b.png' (listed in cap/transforms.json); "
        "weights w.safetensors; x.png; x4 / x1 at hf://a/b"
    )


# ------------------------------------------------------------------------------------------ unsafe zips
def _zip(path: Path, members: dict[str, bytes], link: str | None = None) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
        if link is not None:
            info = zipfile.ZipInfo(link)
            info.external_attr = (stat.S_IFLNK | 0o777) << 16
            zf.writestr(info, "/etc/passwd")
    return path


@pytest.mark.parametrize(
    "members, link, message",
    [
        ({"../evil.png": b"x"}, None, "member '../evil.png' points outside the archive ('..'); refused"),
        ({"a/../../evil.png": b"x"}, None, "points outside the archive ('..')"),
        ({"..\\..\\evil.png": b"x"}, None, "points outside the archive ('..')"),
        ({"/etc/evil.png": b"x"}, None, "member '/etc/evil.png' is an absolute path; refused"),
        ({"C:/evil.png": b"x"}, None, "is an absolute path"),
        ({"a.png": b"x"}, "images/b.png", "member 'images/b.png' is a symbolic link; refused"),
        ({"a\x01.png": b"x"}, None, "has control characters in its name"),
    ],
    ids=["dotdot", "nested dotdot", "backslashes", "absolute", "drive", "symlink", "control"],
)
def test_zips_that_leave_their_folder_are_refused_before_anything_is_written(tmp_path, members, link, message):
    archive = _zip(tmp_path / "bad.zip", {"ok.png": b"fine", **members}, link)
    with pytest.raises(SurfSplatInputError) as err:
        prepare_uploads([archive], None, tmp_path / "session", 10**9)
    assert str(err.value).startswith("bad.zip: member ") and message in str(err.value), str(err.value)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "session" / "inputs" / "bad").exists()
    assert not (tmp_path / "evil.png").exists() and not (tmp_path / "session" / "evil.png").exists()


def test_a_zip_bomb_is_refused_from_its_headers(tmp_path):
    """2 MB of zeros compress to about 2 kB: refused from the declared sizes, nothing written."""
    archive = _zip(tmp_path / "bomb.zip", {"a.png": b"\0" * 2_000_000})
    assert archive.stat().st_size < 10_000
    with pytest.raises(SurfSplatInputError, match=r"bomb.zip: unpacks to more than this server's limit of 1.0 MB"):
        prepare_uploads([archive], None, tmp_path / "session", 1_000_000)
    assert not (tmp_path / "session" / "inputs" / "bomb").exists()


def test_a_zip_whose_headers_lie_about_sizes_stops_while_unpacking(tmp_path):
    """The same member declared as 1,000 bytes in both headers: unpacking stops at the declared size
    (the bytes past it never reach the disk) and the member fails its check; the folder is removed."""
    archive = _zip(tmp_path / "liar.zip", {"a.png": b"\0" * 2_000_000})
    data = bytearray(archive.read_bytes())
    local = data.index(b"PK\x03\x04")
    central = data.index(b"PK\x01\x02")
    struct.pack_into("<I", data, local + 22, 1_000)  # the local header's uncompressed size
    struct.pack_into("<I", data, central + 24, 1_000)  # the central directory's
    archive.write_bytes(bytes(data))
    with pytest.raises(SurfSplatInputError, match="liar.zip: damaged or unsupported zip member"):
        extract_zip(archive, tmp_path / "out", 1_000_000, "liar.zip")
    assert not (tmp_path / "out").exists()


def test_too_many_members_and_duplicates_are_refused(tmp_path, monkeypatch):
    from surfsplat.app import archive as archive_module

    monkeypatch.setattr(archive_module, "MAX_MEMBERS", 3)
    many = _zip(tmp_path / "many.zip", {f"{i}.png": b"x" for i in range(4)})
    with pytest.raises(SurfSplatInputError, match="many.zip: 4 members, over this server's limit of 3"):
        extract_zip(many, tmp_path / "a", 10**9, "many.zip")
    with zipfile.ZipFile(tmp_path / "twice.zip", "w") as zf:
        zf.writestr("a.png", b"1")
        with pytest.warns(UserWarning, match="Duplicate name"):
            zf.writestr("a.png", b"2")
    with pytest.raises(SurfSplatInputError, match="twice.zip: two members are named 'a.png'"):
        extract_zip(tmp_path / "twice.zip", tmp_path / "b", 10**9, "twice.zip")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_a_camera_file_listing_photos_outside_the_capture_is_refused(tmp_path):
    """A transforms.json whose file_path leaves the zip (it would read a file of the server)."""
    capture = tmp_path / "capture"
    write_capture(capture, "transforms", views=2)
    document = json.loads((capture / "transforms.json").read_text())
    document["frames"][1]["file_path"] = "../../../../etc/passwd.png"
    (capture / "transforms.json").write_text(json.dumps(document))
    with pytest.raises(SurfSplatInputError, match=r"cap.zip: the camera file lists a photo outside the capture"):
        prepare_uploads([zip_folder(capture, tmp_path / "cap.zip")], None, tmp_path / "session", 10**9)


# ------------------------------------------------------------------------------------------ folder uploads
def test_a_folder_upload_is_laid_out_as_its_camera_file_says(tmp_path):
    """The browser sends a folder's files without their folders: transforms.json goes to the top and
    each listed photo where its file_path points; the half-size copies of images_2/ lose to the photos."""
    from PIL import Image

    capture = tmp_path / "capture"
    cams = write_capture(capture, "transforms", views=2)
    sent = tmp_path / "sent"
    files, names = [], []
    for k, path in enumerate(sorted(capture.rglob("*.*"))):
        for copy, scale in ((path, 1), (path, 2)) if path.suffix == ".png" else ((path, 1),):
            dest = sent / f"{k}-{scale}" / path.name
            dest.parent.mkdir(parents=True)
            if scale == 1:
                shutil.copyfile(copy, dest)
            else:
                with Image.open(copy) as image:
                    image.resize((image.width // 2, image.height // 2)).save(dest)
            files.append(dest)
            names.append(path.name)
    unpacked = arrange_folder(files, names, tmp_path / "out", "capture folder")
    laid = sorted(p.relative_to(tmp_path / "out").as_posix() for p in unpacked.files)
    assert laid == ["images/IMG_4026.png", "images/IMG_4027.png", "transforms.json"]
    for name in cams.names:
        assert (tmp_path / "out" / "images" / name).read_bytes() == (capture / "images" / name).read_bytes()
    assert unpacked.notes == [
        "capture folder: 2 listed photos came in several sizes (downscaled copies); the largest of each is used"
    ]
    uploads = prepare_uploads([], None, tmp_path / "session", 10**9, capture_files=files, capture_names=names)
    assert uploads.scene == uploads.cameras == tmp_path / "session" / "inputs" / "capture"


def test_a_flat_colmap_folder_gets_sparse_0_and_images(tmp_path):
    capture = tmp_path / "capture"
    write_capture(capture, "colmap", views=2)
    files = sorted(p for p in capture.rglob("*") if p.is_file())
    unpacked = arrange_folder(files, [p.name for p in files], tmp_path / "out", "capture folder")
    laid = sorted(p.relative_to(tmp_path / "out").as_posix() for p in unpacked.files)
    assert laid == ["images/IMG_4026.png", "images/IMG_4027.png", "sparse/0/cameras.bin", "sparse/0/images.bin"]


# ------------------------------------------------------------------------------------------ limits
def test_300_photos_are_refused_at_once(tmp_path):
    """Before any photo is read or copied: the count alone (files of one byte are never decoded)."""
    files = []
    for i in range(300):
        path = tmp_path / "upload" / f"{i:03d}.png"
        path.parent.mkdir(exist_ok=True)
        path.write_bytes(b"x")
        files.append(path)
    config = AppConfig(sessions_dir=str(tmp_path / "sessions"), **SMALL)
    tick = time.perf_counter()
    outputs, folder = _request(config, files=files)
    seconds = time.perf_counter() - tick
    assert outputs[0] == (
        "**Cannot reconstruct:** photos: 300 photos, over this server's limit of 60 views a run; send at most 60"
    )
    assert not (folder / "inputs").exists() and not (folder / "outputs").exists()
    assert seconds < 10, f"refused after {seconds:.1f} s"  # no model, no pose estimation: well under a second


def test_a_capture_listing_more_views_than_the_limit_is_refused(tmp_path):
    capture = tmp_path / "capture"
    write_capture(capture, "transforms", views=3)
    with pytest.raises(SurfSplatInputError) as err:
        prepare_uploads([zip_folder(capture, tmp_path / "big.zip")], None, tmp_path / "s", 10**9, max_views=2)
    assert str(err.value) == (
        "big.zip: 3 photos listed in its transforms.json, over this server's limit of 2 views a run; send at most 2"
    )


def test_the_limits_are_options_and_on_the_page():
    from surfsplat.app.page import _optimize_max, limits_text
    from surfsplat.cli import build_parser

    args = build_parser().parse_args(["app", "--max-views", "30", "--max-run-seconds", "120"])
    assert (args.max_views, args.max_run_seconds) == (30, 120)
    defaults = build_parser().parse_args(["app"])
    assert (defaults.max_views, defaults.max_run_seconds) == (AppConfig.max_views, AppConfig.max_seconds) == (60, 600)
    text = limits_text(AppConfig(max_views=30, max_seconds=120, max_upload_mb=50))
    assert "up to 50 MB of uploads and 30 views a run" in text and "stops a run after 120 s" in text
    assert _optimize_max(AppConfig(max_seconds=120)) == 60 and _optimize_max(AppConfig()) == 300
    with pytest.raises(SurfSplatInputError, match="--max-views"):
        AppConfig(max_views=1)
    with pytest.raises(SurfSplatInputError, match="--max-run-seconds"):
        AppConfig(max_seconds=0)


def test_the_tracker_stops_a_run_past_its_seconds():
    now = [0.0]
    reports = []
    tracker = StageTracker(lambda f, text: reports.append(text), max_seconds=10, clock=lambda: now[0])
    tracker.enter("cameras")
    now[0] = 9.9
    tracker("forward passes", 1, 2)
    now[0] = 10.1
    with pytest.raises(RunOverTime, match=r"limit of 10 s for one run \(during network passes and fusion\)"):
        tracker("forward passes", 2, 2)
    assert reports == ["cameras", "network passes and fusion: 1/2"]
    assert STAGES[0][0] == "cameras"


def test_a_run_over_its_seconds_keeps_nothing(tmp_path):
    capture = tmp_path / "fern"
    write_capture(capture, "transforms", views=2)
    config = AppConfig(sessions_dir=str(tmp_path / "sessions"), max_seconds=0.01, **SMALL)
    outputs, folder = _request(config, files=[zip_folder(capture, tmp_path / "fern.zip")])
    assert outputs[0].startswith("**Stopped:** the run went past this server's limit of 0.01 s for one run (during ")
    assert outputs[1:] == (None, None, "", None, None, None)
    assert not (folder / "outputs").exists() and not (folder / "surfsplat_result.zip").exists()


def test_the_runs_warnings_are_collected_from_its_own_thread_only(tmp_path):
    """What the page shows of the library's log: the run's warnings (another thread's are not its own),
    each as logged; `run_capture` then scrubs them like every other line."""
    import logging
    import threading

    from surfsplat.app.run import _warnings

    session = tmp_path / "s1-ab"
    log = logging.getLogger("surfsplat.data.formats.blender")
    with _warnings() as warned:
        log.warning(f"1 of 3 frames listed in {session}/inputs/cap/transforms.json have no photo; left out")
        log.info("not a warning")
        other = threading.Thread(target=lambda: log.warning("another run's warning"))
        other.start()
        other.join()
    log.warning("after the run")
    assert warned == [f"1 of 3 frames listed in {session}/inputs/cap/transforms.json have no photo; left out"]
    assert PathScrubber(session)(warned[0]) == "1 of 3 frames listed in cap/transforms.json have no photo; left out"


def test_colmap_files_at_a_zips_top_and_zips_or_folders_of_plain_photos(tmp_path):
    """COLMAP's cameras/images files at the zip's top with images/ beside them are a capture; a zip or a
    folder of photos alone is photos (the camera file box applies, cameras estimated without it)."""
    from surfsplat.reconstruction.capture_folder import find_processed_capture

    capture = tmp_path / "capture"
    cams = write_capture(capture, "colmap", views=2)
    for path in (capture / "sparse" / "0").iterdir():
        path.rename(capture / path.name)
    shutil.rmtree(capture / "sparse")
    uploads = prepare_uploads([zip_folder(capture, tmp_path / "top.zip")], None, tmp_path / "s1", 10**9)
    assert uploads.scene == uploads.cameras == uploads.capture == tmp_path / "s1" / "inputs" / "top"
    found = find_processed_capture(uploads.scene)
    assert found.kind == "COLMAP model" and found.photos == [uploads.scene / "images" / n for n in cams.names]

    photos = zip_folder(capture / "images", tmp_path / "photos.zip", top="holiday")
    camera_file = tmp_path / "cams.json"
    camera_file.write_text("{}")
    uploads = prepare_uploads([photos], camera_file, tmp_path / "s2", 10**9)
    assert uploads.scene is None and uploads.cameras == tmp_path / "s2" / "inputs" / "cams.json"
    assert uploads.capture == [tmp_path / "s2" / "inputs" / "photos" / "holiday" / n for n in cams.names]
    files = sorted((capture / "images").iterdir())
    uploads = prepare_uploads([], None, tmp_path / "s3", 10**9, capture_files=files)
    assert uploads.capture == [tmp_path / "s3" / "inputs" / "capture" / n for n in cams.names]
    assert uploads.cameras is None and uploads.notes == []


def test_the_command_reads_a_capture_folders_cameras_unless_told(tmp_path, monkeypatch):
    """`surfsplat reconstruct --images capture/` passes cameras="auto" (the folder's own), and --cameras
    as given."""
    import surfsplat.reconstruction as reconstruction
    from surfsplat.cli import build_parser
    from surfsplat.commands import reconstruct as command

    seen = []

    class Seen(Exception):
        pass

    def stub(images, **kwargs):
        seen.append((images, kwargs["cameras"]))
        raise Seen

    monkeypatch.setattr(reconstruction, "reconstruct", stub)
    capture = tmp_path / "capture"
    write_capture(capture, "transforms", views=2)
    for extra in ([], ["--cameras", str(capture / "transforms.json")]):
        args = build_parser().parse_args(
            ["reconstruct", "--images", str(capture), "--out", str(tmp_path / "o"), *extra]
        )
        with pytest.raises(Seen):
            command.run(args)
    assert seen == [(capture, "auto"), (capture, capture / "transforms.json")]


# ----------------------------------------------------------------------- bad processed captures, uploaded
def _bad_capture_cases():
    from tests.commands.test_reliability import CAPTURE_CASES

    return CAPTURE_CASES


@pytest.mark.parametrize(
    "make, needles", [c[1:] for c in _bad_capture_cases()], ids=[c[0] for c in _bad_capture_cases()]
)
def test_bad_processed_capture_uploaded_is_one_line_without_server_paths(tmp_path, make, needles):
    """The CLI's processed-capture corpus (tests/commands/test_reliability.py) zipped and uploaded: the page
    gets the same one line, naming the file by the zip's own name, and keeps no outputs."""
    from tests.commands.test_reliability import _photos

    capture = tmp_path / "capture"
    capture.mkdir()
    _photos(capture)
    make(capture)
    config = AppConfig(sessions_dir=str(tmp_path / "sessions"), **SMALL)
    outputs, folder = _request(config, files=[zip_folder(capture, tmp_path / "capture.zip")])
    status = outputs[0]
    assert status.startswith("**Cannot reconstruct:** capture/") and "\n" not in status, status
    for needle in needles:
        assert needle in status, (needle, status)
    _no_server_path(outputs, config.root())
    assert not (folder / "outputs").exists()


def test_heic_upload_without_the_extra_is_one_line_naming_it(tmp_path, monkeypatch):
    pillow_heif = pytest.importorskip("pillow_heif", reason="pillow-heif (the 'heic' extra) makes the HEIC fixture")
    import sys

    from PIL import Image

    pillow_heif.register_heif_opener()
    photos = tmp_path / "phone"
    photos.mkdir()
    for name in ("IMG_4026.png", "IMG_4027.png"):
        Image.open(FERN / "images_16" / name).convert("RGB").save(photos / name.replace(".png", ".heic"), "HEIF")
    monkeypatch.setitem(sys.modules, "pillow_heif", None)  # the extra uninstalled
    config = AppConfig(sessions_dir=str(tmp_path / "sessions"), **SMALL)
    outputs, folder = _request(config, files=[zip_folder(photos, tmp_path / "phone.zip")])
    status = outputs[0]
    assert status.startswith("**Cannot reconstruct:** phone/IMG_4026.heic") and "\n" not in status, status
    assert "pip install 'surfsplat[heic]'" in status, status
    _no_server_path(outputs, config.root())
    assert not (folder / "outputs").exists()
