"""What a browser sends, made safe before the library sees it: uploads sorted into photos, one video,
a zip or a folder of a processed capture (`archive`), and a camera file, checked against the server's
limits (bytes, views), and copied into the session's own folder under names made here; the session
folders, removed a while after their last run; and `PathScrubber`, which takes the server's folders
out of every message the page shows.

Nothing a request sends becomes a server path outside the session: an upload's original name only
lends its letters, digits, dots, dashes and underscores to the copy's name (camera files match views
by name, so the stem is kept where it is safe), and the copy always lands directly in the session's
`inputs/`; a zip's members keep their names below `inputs/<zip name>/` once `archive` has checked them.
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ..capture.video import VIDEO_SUFFIXES
from ..data.images import IMAGE_SUFFIXES
from ..utils.checks import SurfSplatInputError

CAMERA_SUFFIXES = (".json",)  # the camera file `surfsplat poses` and `reconstruct` write
ARCHIVE_SUFFIXES = (".zip",)  # a processed capture (photos + transforms.json or a COLMAP model), or photos
MAX_NAME = 80  # characters kept of an upload's stem
_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")
_SUFFIX = re.compile(r"\.[a-z0-9]{1,5}")
_SESSION = re.compile(r"^s[0-9]{13,}-[0-9a-f]{16}$")  # the folders `SessionFolders.new` makes, nothing else


@dataclass
class Uploads:
    """One run's inputs, copied into its session folder."""

    folder: Path  # the session's inputs/ folder
    images: list[Path]  # two or more photos, in the order given (empty for a video or a processed capture)
    video: Path | None
    cameras: Path | None  # a JSON camera file or a processed capture's folder, or None to estimate the cameras
    scene: Path | None = None  # a processed capture's folder: its photos and its camera file (transforms.json, COLMAP)
    notes: list[str] = field(default_factory=list)  # what unpacking left out or chose, one line each

    @property
    def capture(self) -> list[Path] | Path:
        """What `surfsplat.reconstruct` takes: the processed capture's folder, the list of photos, or the video."""
        if self.scene is not None:
            return self.scene
        return self.video if self.video is not None else self.images


def safe_name(name: str, fallback: str) -> str:
    """A file name of letters, digits, '.', '-' and '_' only, from the last component of `name`
    (either slash); its lower-case suffix kept when it is a plain one; `fallback` as the stem when
    nothing safe is left (e.g. '../..' or a name of other scripts)."""
    base = re.split(r"[\\/]", str(name))[-1]
    stem, dot, suffix = base.rpartition(".")
    if not dot:
        stem, suffix = base, ""
    suffix = "." + suffix.lower() if _SUFFIX.fullmatch("." + suffix.lower()) else ""
    stem = _UNSAFE.sub("_", stem).strip("._-")[:MAX_NAME]
    return (stem or fallback) + suffix


def _kind(name: str) -> str:
    suffix = Path(name).suffix.lower()
    if suffix in IMAGE_SUFFIXES:
        return "image"
    if suffix in VIDEO_SUFFIXES:
        return "video"
    if suffix in CAMERA_SUFFIXES:
        return "cameras"
    if suffix in ARCHIVE_SUFFIXES:
        return "archive"
    return "other"


def _megabytes(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


def prepare_uploads(
    files: Sequence[str | os.PathLike] | None,
    cameras: str | os.PathLike | None,
    folder: str | os.PathLike,
    max_bytes: int,
    names: Sequence[str] | None = None,
    *,
    max_views: int | None = None,
    capture_files: Sequence[str | os.PathLike] | None = None,
    capture_names: Sequence[str] | None = None,
) -> Uploads:
    """Check the uploads (what they are, how many, their total size, the views they hold) and copy
    them into `folder`/inputs under safe names; one SurfSplatInputError naming the upload by its own
    name, before anything heavy runs.

    files:   the dropped files (photos, one video, or one zip), as the server stored them
    cameras: an optional JSON camera file
    names:   the names the browser gave the files (default: the stored files' names)
    max_views: views of one run at most (photos, or the photos a capture's camera file lists); None: no limit
    capture_files, capture_names: the files of a folder upload (a processed capture, or photos), and their names
    """
    files = [Path(f) for f in (files or [])]
    names = [Path(f).name for f in files] if names is None else [str(n) for n in names]
    capture_files = [Path(f) for f in (capture_files or [])]
    capture_names = [f.name for f in capture_files] if capture_names is None else [str(n) for n in capture_names]
    if len(names) != len(files) or len(capture_names) != len(capture_files):
        raise SurfSplatInputError(f"names: expected {len(files)} + {len(capture_files)} names, got {len(names)}")
    if not files and not capture_files:
        raise SurfSplatInputError(
            "photos: drop two or more photos of one scene, one video, or a zip or folder of a processed capture"
        )
    if files and capture_files:
        raise SurfSplatInputError("photos: drop photos, a video or a zip, or send a capture folder; not both")
    every = [*files, *capture_files, *([Path(cameras)] if cameras else [])]
    total = sum(f.stat().st_size for f in every)
    if total > max_bytes:
        raise SurfSplatInputError(
            f"upload: {_megabytes(total)} in all is over this server's limit of {_megabytes(max_bytes)}; "
            "send fewer or smaller photos, or a shorter video"
        )
    if cameras is not None and _kind(Path(cameras).name) != "cameras":
        raise SurfSplatInputError(
            f"cameras: expected a JSON camera file (as `surfsplat poses` writes), got {safe_name(Path(cameras).name, 'file')}"
        )
    inputs = Path(folder) / "inputs"
    if capture_files:
        from .archive import arrange_folder

        inputs.mkdir(parents=True, exist_ok=True)
        unpacked = arrange_folder(capture_files, capture_names, inputs / "capture", "capture folder")
        return _unpacked_uploads(unpacked, "capture folder", cameras, inputs, max_views)
    kinds = [_kind(n) for n in names]
    for name, kind in zip(names, kinds):
        if kind == "cameras":
            raise SurfSplatInputError(f"{safe_name(name, 'file')}: a camera file goes in the camera file box")
        if kind == "other":
            raise SurfSplatInputError(
                f"{safe_name(name, 'file')}: neither a photo ({', '.join(IMAGE_SUFFIXES)}), a video "
                f"({', '.join(VIDEO_SUFFIXES)}) nor a zip"
            )
    if "archive" in kinds:
        if len(files) > 1:
            raise SurfSplatInputError(
                f"photos: a zip comes alone (a processed capture, or photos), got {len(files)} files with it"
            )
        from .archive import extract_zip

        label = safe_name(names[0], "capture.zip")
        inputs.mkdir(parents=True, exist_ok=True)
        unpacked = extract_zip(files[0], inputs / Path(label).stem, max_bytes, label)
        return _unpacked_uploads(unpacked, label, cameras, inputs, max_views)
    videos = kinds.count("video")
    if videos and (videos > 1 or len(files) > 1):
        raise SurfSplatInputError(
            f"photos: expected two or more photos or one video, got {kinds.count('image')} photos and {videos} videos"
        )
    _check_views(len(files) if not videos else 0, max_views, "photos")
    inputs.mkdir(parents=True, exist_ok=True)
    copy = _Copier(inputs)
    copied = [copy(f, n, f"view_{i:03d}") for i, (f, n) in enumerate(zip(files, names))]
    camera_copy = copy(Path(cameras), Path(cameras).name, "cameras") if cameras is not None else None
    if videos:
        return Uploads(inputs, [], copied[0], camera_copy)
    return Uploads(inputs, copied, None, camera_copy)


def _check_views(count: int, max_views: int | None, label: str, what: str = "photos") -> None:
    if max_views is not None and count > max_views:
        raise SurfSplatInputError(
            f"{label}: {count} {what}, over this server's limit of {max_views} views a run; send at most {max_views}"
        )


class _Copier:
    """Copies uploads into `inputs` under safe names, numbering a second upload of one name."""

    def __init__(self, inputs: Path) -> None:
        self.inputs = inputs
        self.taken: set[str] = set()

    def __call__(self, source: Path, name: str, fallback: str) -> Path:
        target = safe_name(name, fallback)
        stem, suffix = Path(target).stem, Path(target).suffix
        k = 1
        while target.lower() in self.taken:  # two uploads of one name: the second gets a number
            k += 1
            target = f"{stem}_{k}{suffix}"
        self.taken.add(target.lower())
        dest = self.inputs / target
        if dest.parent != self.inputs:  # safe_name leaves no separator; this guards the guarantee itself
            raise SurfSplatInputError(f"{target}: not a plain file name")
        shutil.copyfile(source, dest)
        return dest


def _unpacked_uploads(unpacked, label: str, cameras, inputs: Path, max_views: int | None) -> Uploads:
    """The Uploads of an unpacked zip or folder: a processed capture (its folder is the run's images and
    cameras), or plain photos (with the camera file box's file, if any)."""
    from ..data.images import is_image_file
    from ..reconstruction.capture_folder import find_processed_capture
    from .archive import capture_root, check_listed_inside

    root = capture_root(unpacked.root)
    capture = find_processed_capture(root)
    if capture is not None:
        if cameras is not None:
            raise SurfSplatInputError(
                f"cameras: {label} brings its own cameras ({capture.kind}); leave the camera file box empty"
            )
        check_listed_inside(root, capture.photos, label)
        present = sum(p.is_file() for p in capture.photos)
        _check_views(present, max_views, label, f"photos listed in its {capture.kind}")
        return Uploads(inputs, [], None, root, scene=root, notes=list(unpacked.notes))
    photos = sorted(p for p in root.rglob("*") if is_image_file(p))
    if not photos:
        raise SurfSplatInputError(
            f"{label}: no photos ({', '.join(IMAGE_SUFFIXES)}) and no transforms.json or COLMAP model "
            "(sparse/0/cameras.bin or .txt) in it"
        )
    _check_views(len(photos), max_views, label)
    camera_copy = _Copier(inputs)(Path(cameras), Path(cameras).name, "cameras") if cameras is not None else None
    return Uploads(inputs, photos, None, camera_copy, notes=list(unpacked.notes))


class PathScrubber:
    """Takes the server's folders out of a text shown on the page: paths inside the session's inputs
    become the upload's own names (`a.png`, `capture/images/b.png`), the session's other folders are
    removed, and any other path under the sessions root, the temporary folder or the home folder is
    cut to its last component."""

    def __init__(self, session: str | os.PathLike, root: str | os.PathLike | None = None) -> None:
        session = Path(session)
        self.strip = [session / "inputs", session / "outputs", session]
        self.roots = sorted(
            {str(p) for p in (root, tempfile.gettempdir(), Path.home()) if p is not None and str(p) not in ("", "/")},
            key=len,
            reverse=True,
        )
        for strip in list(self.strip):
            resolved = strip.resolve()
            if resolved != strip:
                self.strip.append(resolved)
        self._other = [re.compile(re.escape(r) + r"(?![\w.-])(?:/[^\s'\"(),;:]*)?") for r in self.roots]

    def __call__(self, text: str) -> str:
        for prefix in self.strip:
            text = text.replace(f"{prefix}/", "").replace(str(prefix), "")
        for pattern in self._other:
            text = pattern.sub(lambda m: m.group(0).rstrip("/").rsplit("/", 1)[-1], text)
        return text


class SessionFolders:
    """One temporary folder per run under `root`, removed `keep_seconds` after it was made (a folder
    still in use is kept until its run ends). Only folders named as `new` names them are ever removed."""

    def __init__(self, root: str | os.PathLike, keep_seconds: float) -> None:
        if not keep_seconds > 0:
            raise SurfSplatInputError(f"keep_seconds: expected a positive time, got {keep_seconds}")
        self.root = Path(root)
        self.keep_seconds = float(keep_seconds)
        self._busy: set[Path] = set()
        self._lock = threading.Lock()

    def new(self) -> Path:
        """A fresh, empty folder (expired ones are removed first); `release` it when its run ends."""
        self.remove_expired()
        self.root.mkdir(parents=True, exist_ok=True)
        folder = self.root / f"s{time.time_ns() // 1000}-{secrets.token_hex(8)}"
        folder.mkdir()
        with self._lock:
            self._busy.add(folder)
        return folder

    def release(self, folder: Path) -> None:
        with self._lock:
            self._busy.discard(Path(folder))

    def remove_expired(self, now: float | None = None) -> list[Path]:
        """Remove the session folders made more than keep_seconds before `now`; returns them."""
        now = time.time() if now is None else now
        if not self.root.is_dir():
            return []
        removed = []
        for folder in sorted(self.root.iterdir()):
            if not (folder.is_dir() and _SESSION.match(folder.name)):
                continue
            made = int(folder.name[1:].split("-")[0]) / 1e6
            with self._lock:
                busy = folder in self._busy
            if not busy and now - made > self.keep_seconds:
                shutil.rmtree(folder, ignore_errors=True)  # a file held open elsewhere: the next sweep takes it
                removed.append(folder)
        return removed

    def sweep_every(self, seconds: float) -> threading.Event:
        """Remove expired folders every `seconds` in a daemon thread; set the returned event to stop."""
        stop = threading.Event()

        def loop() -> None:
            while not stop.wait(seconds):
                self.remove_expired()

        threading.Thread(target=loop, name="surfsplat-app-cleanup", daemon=True).start()
        return stop
