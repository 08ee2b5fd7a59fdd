"""What a browser sends, made safe before the library sees it: uploads sorted into photos, one video
and a camera file, checked against the server's size limit, and copied into the session's own folder
under names made here; and the session folders, removed a while after their last run.

Nothing a request sends becomes a server path: an upload's original name only lends its letters,
digits, dots, dashes and underscores to the copy's name (camera files match views by name, so the
stem is kept where it is safe), and the copy always lands directly in the session's `inputs/`.
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ..capture.video import VIDEO_SUFFIXES
from ..data.images import IMAGE_SUFFIXES
from ..utils.checks import SurfSplatInputError

CAMERA_SUFFIXES = (".json",)  # the camera file `surfsplat poses` and `reconstruct` write
MAX_NAME = 80  # characters kept of an upload's stem
_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")
_SUFFIX = re.compile(r"\.[a-z0-9]{1,5}")
_SESSION = re.compile(r"^s[0-9]{13,}-[0-9a-f]{16}$")  # the folders `SessionFolders.new` makes, nothing else


@dataclass
class Uploads:
    """One run's inputs, copied into its session folder."""

    folder: Path  # the session's inputs/ folder
    images: list[Path]  # two or more photos, in the order given (empty for a video)
    video: Path | None
    cameras: Path | None  # a JSON camera file, or None to estimate the cameras

    @property
    def capture(self) -> list[Path] | Path:
        """What `surfsplat.reconstruct` takes: the list of photos, or the video."""
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
    return "other"


def _megabytes(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


def prepare_uploads(
    files: Sequence[str | os.PathLike] | None,
    cameras: str | os.PathLike | None,
    folder: str | os.PathLike,
    max_bytes: int,
    names: Sequence[str] | None = None,
) -> Uploads:
    """Check the uploads (what they are, how many, their total size) and copy them into
    `folder`/inputs under safe names; one SurfSplatInputError naming the upload by its own name.

    files:   the dropped files (photos or one video), as the server stored them
    cameras: an optional JSON camera file
    names:   the names the browser gave the files (default: the stored files' names)
    """
    files = [Path(f) for f in (files or [])]
    names = [Path(f).name for f in files] if names is None else [str(n) for n in names]
    if len(names) != len(files):
        raise SurfSplatInputError(f"names: expected {len(files)} names, got {len(names)}")
    if not files:
        raise SurfSplatInputError("photos: drop two or more photos of one scene, or one video")
    total = sum(f.stat().st_size for f in files) + (Path(cameras).stat().st_size if cameras else 0)
    if total > max_bytes:
        raise SurfSplatInputError(
            f"upload: {_megabytes(total)} in all is over this server's limit of {_megabytes(max_bytes)}; "
            "send fewer or smaller photos, or a shorter video"
        )
    kinds = [_kind(n) for n in names]
    for name, kind in zip(names, kinds):
        if kind == "cameras":
            raise SurfSplatInputError(f"{safe_name(name, 'file')}: a camera file goes in the camera file box")
        if kind == "other":
            raise SurfSplatInputError(
                f"{safe_name(name, 'file')}: neither a photo ({', '.join(IMAGE_SUFFIXES)}) "
                f"nor a video ({', '.join(VIDEO_SUFFIXES)})"
            )
    videos = kinds.count("video")
    if videos and (videos > 1 or len(files) > 1):
        raise SurfSplatInputError(
            f"photos: expected two or more photos or one video, got {kinds.count('image')} photos and {videos} videos"
        )
    if cameras is not None and _kind(Path(cameras).name) != "cameras":
        raise SurfSplatInputError(
            f"cameras: expected a JSON camera file (as `surfsplat poses` writes), got {safe_name(Path(cameras).name, 'file')}"
        )
    inputs = Path(folder) / "inputs"
    inputs.mkdir(parents=True, exist_ok=True)
    taken: set[str] = set()

    def copy(source: Path, name: str, fallback: str) -> Path:
        target = safe_name(name, fallback)
        stem, suffix = Path(target).stem, Path(target).suffix
        k = 1
        while target.lower() in taken:  # two uploads of one name: the second gets a number
            k += 1
            target = f"{stem}_{k}{suffix}"
        taken.add(target.lower())
        dest = inputs / target
        if dest.parent != inputs:  # safe_name leaves no separator; this guards the guarantee itself
            raise SurfSplatInputError(f"{target}: not a plain file name")
        shutil.copyfile(source, dest)
        return dest

    copied = [copy(f, n, f"view_{i:03d}") for i, (f, n) in enumerate(zip(files, names))]
    camera_copy = copy(Path(cameras), Path(cameras).name, "cameras") if cameras is not None else None
    if videos:
        return Uploads(inputs, [], copied[0], camera_copy)
    return Uploads(inputs, copied, None, camera_copy)


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
