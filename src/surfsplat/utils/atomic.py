"""Atomic file output: every file the package writes appears complete under its final name or not at all.

    with atomic_path(out / "surfels.ply") as tmp:    # a temporary name beside the target
        PlyData(...).write(str(tmp))                  # any writer that takes a file name
    # here: the data is on disk (fsync) and renamed over the target in one step

An exception inside the block, KeyboardInterrupt included, removes the temporary file and leaves
an earlier file under the final name untouched. A full disk (ENOSPC) or another operating-system
error while writing becomes `OutputError`, one line naming the final path.
"""

from __future__ import annotations

import errno
import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

logger = logging.getLogger(__name__)

TEMP_MARK = ".tmp"  # temporary names are ".<name>.tmp<suffix>", hidden and recognisable


class OutputError(OSError):
    """Writing an output failed (full disk, permissions): one line naming the file."""


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path in the target's folder; on success fsync it and rename it to `path`.

    `suffix` is appended to the temporary name for writers that choose a format from it (ffmpeg
    reads ".mp4", imageio ".png"). The folder is created when missing.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise output_error(path, err) from None
    tmp = path.with_name(f".{path.name}{TEMP_MARK}{suffix}")
    try:
        yield tmp
        _fsync(tmp)
        os.replace(tmp, path)
    except OSError as err:
        raise output_error(path, err) from None
    finally:
        # Gone after a rename; after any failure (KeyboardInterrupt included) no partial file stays.
        tmp.unlink(missing_ok=True)
    fsync_dir(path.parent)


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write `data` to `path` atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
    return Path(path)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 `text` to `path` atomically."""
    return write_bytes(path, text.encode("utf-8"))


def is_temporary(path: str | os.PathLike) -> bool:
    """Whether `path` is a temporary name of `atomic_path` (a leftover only if a process was killed -9)."""
    name = Path(path).name
    return name.startswith(".") and TEMP_MARK in name


def output_error(path: str | os.PathLike, err: OSError) -> OutputError:
    """`err` (raised while writing `path`) as one line naming `path`."""
    if isinstance(err, OutputError):
        return err
    if err.errno == errno.ENOSPC:
        reason = "no space left on the device"
    elif err.errno == errno.EDQUOT:
        reason = "disk quota exceeded"
    else:
        reason = err.strerror or str(err)
    error = OutputError(f"{path}: cannot write ({reason}); nothing was written under this name")
    error.errno = err.errno
    return error


def _fsync(path: Path) -> None:
    # A rename is only atomic for data already on disk: without this, a crash just after the rename
    # can leave an empty file under the final name on some file systems.
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_dir(folder: Path, strict: bool = False) -> None:
    """Make the renames inside `folder` durable. Not every platform opens folders and some file
    systems refuse fsync on one; the rename is atomic either way, so by default that is only noted
    (`strict`: raised, for training checkpoints, whose folder must be on disk before it is trusted)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError as err:
        if strict:
            raise
        logger.debug("%s: folder not synced (%s)", folder, err)
        return
    try:
        os.fsync(fd)
    except OSError as err:
        if strict:
            raise
        logger.debug("%s: folder not synced (%s)", folder, err)
    finally:
        os.close(fd)
