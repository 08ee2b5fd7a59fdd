"""A processed capture sent to the app: a zip, or a folder (whose files the browser sends without their
folders), unpacked into the session's inputs so the photos sit where the camera file points.

A zip keeps its layout (transforms.json's `file_path`s relative to it; COLMAP's `images/` beside `sparse/`),
unpacked by hand with Python's `zipfile` rather than `ZipFile.extractall`, which would write whatever the
archive says: here every member is checked before a byte is written. Refused with one line each:
- names that leave the folder: absolute (`/x`, `C:x`), with a `..` component, or with control characters;
  backslashes count as separators (zips written on Windows);
- symbolic links (a Unix mode of S_IFLNK in the member's external attributes), encrypted members, two
  members of one name;
- more than MAX_MEMBERS members, or more bytes than the server's upload limit once unpacked: from the
  sizes the zip's headers declare before anything is written, and again from the bytes actually
  written while unpacking (a header can lie; a member that grows past its declared size stops it).
macOS's metadata (`__MACOSX/`, `._*`, `.DS_Store`) is left out, and counted in a note.

A folder upload arrives flat (gradio keeps each file's name only), so `arrange_folder` rebuilds the
layout: the camera file at the top (`transforms.json`) or in `sparse/0` (COLMAP's files), and each photo
it lists placed where it points, found by its file name; where several uploads share a name (nerfstudio's
`images/`, `images_2/`, ... hold the same names at other sizes), the one with the most pixels is used
(the full-size photos the camera file describes) and a note says so.

Either way every photo a camera file lists must lie inside the capture (no `..`, no absolute path):
a listed `/home/x.png` would otherwise reconstruct a file of the server.
"""

from __future__ import annotations

import re
import shutil
import stat
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

from ..utils.checks import SurfSplatInputError

MAX_MEMBERS = 5_000  # members of one zip at most (60 views with their downscaled copies and masks need ~500)
CHUNK = 1 << 20  # bytes copied at a time while unpacking (the running total is checked after each)
COLMAP_FILES = ("cameras.bin", "cameras.txt", "images.bin", "images.txt", "points3D.bin", "points3D.txt")
TRANSFORMS_FILES = ("transforms.json", "transforms_train.json")
_DRIVE = re.compile(r"^[A-Za-z]:")
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


def _megabytes(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


@dataclass
class Unpacked:
    """What a zip or a folder upload became."""

    root: Path  # the folder holding the capture (or the photos)
    files: list[Path] = field(default_factory=list)  # every file written, in order
    notes: list[str] = field(default_factory=list)  # what was left out or chosen, one line each


def _is_metadata(parts: list[str]) -> bool:
    return parts[0] == "__MACOSX" or parts[-1] == ".DS_Store" or parts[-1].startswith("._")


def member_parts(name: str, label: str) -> list[str]:
    """The path components of a zip member's name, or one SurfSplatInputError when it would leave
    the folder it is unpacked into."""
    shown = name if len(name) <= 80 else name[:77] + "..."
    if _CONTROL.search(name):
        raise SurfSplatInputError(f"{label}: member {shown!r} has control characters in its name; refused")
    normal = name.replace("\\", "/")
    if normal.startswith("/") or _DRIVE.match(normal):
        raise SurfSplatInputError(f"{label}: member {shown!r} is an absolute path; refused (nothing was unpacked)")
    parts = [p for p in normal.split("/") if p not in ("", ".")]
    if ".." in parts:
        raise SurfSplatInputError(
            f"{label}: member {shown!r} points outside the archive ('..'); refused (nothing was unpacked)"
        )
    if any(len(p.encode()) > 255 for p in parts):
        raise SurfSplatInputError(f"{label}: member {shown!r} has a name over 255 bytes; refused")
    return parts


def extract_zip(archive: Path, target: Path, max_bytes: int, label: str) -> Unpacked:
    """Unpack `archive` into `target` (made here, and removed again when the zip is refused); `label`
    (the upload's own name) names it in every message."""
    try:
        zf = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, OSError) as err:
        raise SurfSplatInputError(f"{label}: not a readable zip archive ({err})") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > MAX_MEMBERS:
            raise SurfSplatInputError(
                f"{label}: {len(infos):,} members, over this server's limit of {MAX_MEMBERS:,}; refused"
            )
        plan: list[tuple[zipfile.ZipInfo, list[str]]] = []
        seen: set[str] = set()
        declared, skipped = 0, 0
        for info in infos:
            parts = member_parts(info.filename, label)
            if stat.S_ISLNK(info.external_attr >> 16):
                raise SurfSplatInputError(f"{label}: member {info.filename!r} is a symbolic link; refused")
            if info.is_dir() or not parts:
                continue
            if info.flag_bits & 0x1:
                raise SurfSplatInputError(f"{label}: member {info.filename!r} is encrypted; send an unencrypted zip")
            if _is_metadata(parts):
                skipped += 1
                continue
            key = "/".join(parts)
            if key.lower() in seen:
                raise SurfSplatInputError(f"{label}: two members are named {key!r}; refused")
            seen.add(key.lower())
            declared += info.file_size
            if declared > max_bytes:
                raise SurfSplatInputError(
                    f"{label}: unpacks to more than this server's limit of {_megabytes(max_bytes)} "
                    f"(the zip's headers declare {_megabytes(sum(i.file_size for i in infos))}); refused"
                )
            plan.append((info, parts))
        target.mkdir(parents=True, exist_ok=False)
        out = Unpacked(target)
        written = 0
        try:
            for info, parts in plan:
                dest = target.joinpath(*parts)
                if target.resolve() not in dest.resolve().parents:  # guards the checks above
                    raise SurfSplatInputError(f"{label}: member {info.filename!r} would leave the folder; refused")
                dest.parent.mkdir(parents=True, exist_ok=True)
                size = 0
                with zf.open(info) as source, dest.open("xb") as sink:
                    while chunk := source.read(CHUNK):
                        size += len(chunk)
                        written += len(chunk)
                        if size > info.file_size or written > max_bytes:
                            raise SurfSplatInputError(
                                f"{label}: member {info.filename!r} unpacks past its declared size "
                                f"({_megabytes(info.file_size)}) or the server's limit of {_megabytes(max_bytes)}; "
                                "refused"
                            )
                        sink.write(chunk)
                out.files.append(dest)
        except (zipfile.BadZipFile, NotImplementedError, EOFError) as err:
            shutil.rmtree(target, ignore_errors=True)
            raise SurfSplatInputError(f"{label}: damaged or unsupported zip member ({err})") from None
        except BaseException:
            shutil.rmtree(target, ignore_errors=True)
            raise
    if skipped:
        out.notes.append(f"{label}: {skipped} macOS metadata files left out")
    return out


def capture_root(folder: Path) -> Path:
    """The folder of a capture unpacked into `folder`: itself, or its only entry when that is a folder
    (a zip of a folder, as most zip tools write it)."""
    entries = [p for p in folder.iterdir()]
    if len(entries) == 1 and entries[0].is_dir():
        return entries[0]
    return folder


def check_listed_inside(root: Path, photos: list[Path], label: str) -> None:
    """Every photo a camera file lists lies inside the capture `root` (see the module docstring)."""
    inside = root.resolve()
    for photo in photos:
        resolved = photo.resolve()
        if resolved != inside and inside not in resolved.parents:
            try:
                shown = str(photo.relative_to(root))
            except ValueError:
                shown = photo.name
            raise SurfSplatInputError(f"{label}: the camera file lists a photo outside the capture ({shown}); refused")


def arrange_folder(files: list[Path], names: list[str], target: Path, label: str) -> Unpacked:
    """Lay out a flat folder upload in `target` (see the module docstring): the camera file where the
    readers look for it and each photo it lists where it points. Without a camera file, every photo
    of the folder is copied to `target` (photos whose cameras are estimated)."""
    from ..data.images import IMAGE_SUFFIXES, read_image_size
    from ..reconstruction.capture_folder import find_processed_capture

    target.mkdir(parents=True, exist_ok=False)
    out = Unpacked(target)
    by_name: dict[str, list[Path]] = {}
    for path, name in zip(files, names):
        base = re.split(r"[\\/]", name)[-1]
        by_name.setdefault(base, []).append(path)
    transforms = next((n for n in TRANSFORMS_FILES if n in by_name), None)
    colmap = [n for n in COLMAP_FILES if n in by_name]
    for name in [transforms] if transforms is not None else colmap:
        if len(by_name[name]) > 1:
            raise SurfSplatInputError(f"{label}: {len(by_name[name])} files named {name}; send one capture at a time")
    if transforms is not None:
        dest = target / transforms
        shutil.copyfile(by_name[transforms][0], dest)
        out.files.append(dest)
    elif colmap:
        model = target / "sparse" / "0"
        model.mkdir(parents=True)
        for name in colmap:
            shutil.copyfile(by_name[name][0], model / name)
            out.files.append(model / name)
    else:  # a folder of photos
        from .files import _Copier

        copy, several = _Copier(target), 0
        for base, paths in sorted(by_name.items()):
            if Path(base).suffix.lower() in IMAGE_SUFFIXES and not base.startswith("."):
                several += len(paths) > 1
                out.files.append(copy(_largest(paths, read_image_size), base, f"view_{len(out.files):03d}"))
        if several:
            out.notes.append(f"{label}: {several} photos came in several sizes; the largest of each is used")
        return out
    capture = find_processed_capture(target)
    if capture is None:  # e.g. a COLMAP images file without its cameras file
        raise SurfSplatInputError(f"{label}: {', '.join(colmap)} without cameras.bin or cameras.txt")
    check_listed_inside(target, capture.photos, label)
    several = 0
    for photo in capture.photos:
        candidates = by_name.get(photo.name, [])
        if not candidates:
            continue  # a listed photo the folder lacks: the readers count and report it
        several += len(candidates) > 1
        photo.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(_largest(candidates, read_image_size), photo)
        out.files.append(photo)
    if several:
        out.notes.append(
            f"{label}: {several} listed photos came in several sizes (downscaled copies); the largest of each is used"
        )
    return out


def _largest(paths: list[Path], size_of) -> Path:
    if len(paths) == 1:
        return paths[0]
    return max(paths, key=lambda p: (lambda s: s[0] * s[1])(size_of(p)))
