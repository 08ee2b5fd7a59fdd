"""Converters from public raw layouts into RealEstate10K-style chunks.

- dtu, llff, blender, colmap: SRC is one scene folder or a folder of scene folders; each scene is
  read with `load_scene` (so it gets the same checks) and its images re-encoded (PNG by default,
  lossless after 8 bits). The key is the scene folder's name.
- dl3dv: SRC holds DL3DV scene folders `<hash>/` with `transforms.json` (nerfstudio format) either
  directly or under `nerfstudio/`, and an image folder (`images_8` by default, 270x480). Image
  files are copied byte for byte; frames keep the JSON order (the release's evaluation indices
  refer to it) and timestamps are the frame numbers of `frame_00001.png`-style names.
- scannet: SRC holds ScanNet scene folders as exported by the official SensReader
  (`color/<i>.jpg`, `pose/<i>.txt` camera-to-world, `intrinsic/intrinsic_color.txt`, optional
  `depth/<i>.png` in millimetres). Frames whose pose has inf/NaN (ScanNet's tracking failures) are
  skipped and counted. Colour JPEGs and depth PNGs are copied byte for byte; note that ScanNet's
  depth camera has its own intrinsics (`intrinsic_depth.txt`), so depth resized to the colour
  image is only approximately registered.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..utils.checks import SurfSplatInputError
from .chunks import ChunkWriter, Example, scene_to_example, validate_example
from .formats.blender import read_transforms
from .formats.common import make_cameras
from .images import image_bytes_size, is_image_file
from .load import DETECTORS, load_scene

CONVERTERS = ("dtu", "llff", "blender", "colmap", "dl3dv", "scannet")


@dataclass
class ConvertReport:
    """What a conversion wrote and skipped."""

    written: list[str] = field(default_factory=list)  # keys written
    skipped: list[str] = field(default_factory=list)  # "<path>: <reason>" per skipped scene or frame group
    index: dict[str, str] = field(default_factory=dict)

    def __str__(self) -> str:
        lines = [f"wrote {len(self.written)} scenes, skipped {len(self.skipped)}"]
        lines += [f"  skipped {s}" for s in self.skipped]
        return "\n".join(lines)


def _read_bytes(path: Path) -> torch.Tensor:
    data = path.read_bytes()
    if not data:
        raise SurfSplatInputError(f"{path}: empty file")
    return torch.frombuffer(bytearray(data), dtype=torch.uint8)


def _scene_dirs(src: Path, is_scene: Callable[[Path], bool], what: str) -> list[Path]:
    if not src.exists():
        raise FileNotFoundError(f"{src}: not found")
    if is_scene(src):
        return [src]
    found = sorted(p for p in src.iterdir() if p.is_dir() and is_scene(p)) if src.is_dir() else []
    if not found:
        raise FileNotFoundError(f"{src}: neither a {what} scene nor a folder of them")
    return found


# ------------------------------------------------------------------------- single-scene formats
def _scene_examples(
    fmt: str,
    dirs: list[Path],
    images: str | None,
    image_format: str,
    quality: int,
    report: ConvertReport,
    skip_bad: bool,
) -> Iterator[Example]:
    for scene_dir in dirs:
        try:
            scene = load_scene(scene_dir, format=fmt, images=images)
        except (SurfSplatInputError, FileNotFoundError) as err:
            if not skip_bad:
                raise
            report.skipped.append(f"{scene_dir}: {err}")
            continue
        yield scene_to_example(
            scene, key=scene_dir.name, url=str(scene_dir.name), image_format=image_format, quality=quality
        )


# ---------------------------------------------------------------------------------------- DL3DV
def _is_dl3dv(path: Path) -> bool:
    return path.is_dir() and (
        (path / "transforms.json").is_file() or (path / "nerfstudio" / "transforms.json").is_file()
    )


def _frame_number(file_path: str, source: str) -> int:
    stem = Path(file_path).stem
    digits = stem.split("_")[-1]
    if not digits.isdigit():
        raise SurfSplatInputError(f"{source}: cannot read a frame number from '{file_path}'")
    return int(digits)


def dl3dv_example(scene_dir: Path, images: str = "images_8") -> Example:
    """One DL3DV scene as a chunk example (raw image bytes, cameras normalized by image size)."""
    base = scene_dir / "nerfstudio" if (scene_dir / "nerfstudio" / "transforms.json").is_file() else scene_dir
    parsed = read_transforms(base, images=images, dtype=torch.float64)
    if parsed.lenses is None:  # the photos' bytes as they are
        photos = [_read_bytes(p) for p in parsed.paths]
        width, height = image_bytes_size(photos[0], str(parsed.paths[0]))
    else:  # a lens: each photo undistorted to its pinhole (the cameras' K) and stored as PNG
        from .formats.common import undistort_photo
        from .images import encode_image, read_image

        photos = [
            encode_image(undistort_photo(read_image(p, background=(0.0, 0.0, 0.0))[0], lens).clamp(0, 1), "png")
            for p, lens in zip(parsed.paths, parsed.lenses)
        ]
        width, height = parsed.sizes[0]
    timestamps = torch.tensor(
        [_frame_number(str(f["file_path"]), str(parsed.json_path)) for f in parsed.frames], dtype=torch.int64
    )
    example = {
        "url": scene_dir.name,
        "timestamps": timestamps,
        "cameras": parsed.cameras.to_re10k(width, height).to(torch.float32),
        "images": photos,
        "key": scene_dir.name,
    }
    return validate_example(example, str(parsed.json_path))


# -------------------------------------------------------------------------------------- ScanNet
def _is_scannet(path: Path) -> bool:
    return path.is_dir() and (path / "color").is_dir() and (path / "pose").is_dir() and (path / "intrinsic").is_dir()


def _read_matrix(path: Path, shape: tuple[int, int]) -> torch.Tensor:
    try:
        values = [float(v) for v in path.read_text().split()]
    except ValueError as err:
        raise SurfSplatInputError(f"{path}: {err}") from None
    if len(values) != shape[0] * shape[1]:
        raise SurfSplatInputError(f"{path}: expected {shape[0]}x{shape[1]} numbers, got {len(values)}")
    return torch.tensor(values, dtype=torch.float64).reshape(shape)


def scannet_example(scene_dir: Path, frame_step: int = 1, with_depth: bool = True) -> tuple[Example, int]:
    """One ScanNet scene as a chunk example; returns (example, number of frames skipped for an invalid pose)."""
    if frame_step < 1:
        raise SurfSplatInputError(f"frame_step: expected >= 1, got {frame_step}")
    colors = {int(p.stem): p for p in (scene_dir / "color").iterdir() if is_image_file(p) and p.stem.isdigit()}
    if not colors:
        raise SurfSplatInputError(f"{scene_dir / 'color'}: no frames named <index>.jpg")
    K4 = _read_matrix(scene_dir / "intrinsic" / "intrinsic_color.txt", (4, 4))
    K = K4[:3, :3]
    ids = sorted(colors)[::frame_step]
    first = _read_bytes(colors[ids[0]])
    width, height = image_bytes_size(first, str(colors[ids[0]]))
    kept, c2ws, skipped = [], [], 0
    for i in ids:
        pose_path = scene_dir / "pose" / f"{i}.txt"
        if not pose_path.is_file():
            raise FileNotFoundError(f"{pose_path}: pose of frame {i} not found")
        c2w = _read_matrix(pose_path, (4, 4))
        if not bool(torch.isfinite(c2w).all()):
            skipped += 1  # ScanNet writes -inf poses where tracking failed
            continue
        kept.append(i)
        c2ws.append(c2w)
    if not kept:
        raise SurfSplatInputError(f"{scene_dir}: every frame has an invalid pose")
    cameras = make_cameras(torch.stack(c2ws), K.expand(len(kept), 3, 3).clone(), str(scene_dir / "pose"), torch.float64)
    example = {
        "url": scene_dir.name,
        "timestamps": torch.tensor(kept, dtype=torch.int64),
        "cameras": cameras.to_re10k(width, height).to(torch.float32),
        "images": [_read_bytes(colors[i]) for i in kept],
        "key": scene_dir.name,
    }
    if with_depth and (scene_dir / "depth").is_dir():
        depth_paths = [scene_dir / "depth" / f"{i}.png" for i in kept]
        for p in depth_paths:
            if not p.is_file():
                raise FileNotFoundError(f"{p}: depth of a colour frame not found")
        example["depths"] = [_read_bytes(p) for p in depth_paths]
    return validate_example(example, str(scene_dir)), skipped


# ----------------------------------------------------------------------------------------- main
def convert(
    fmt: str,
    src: str | Path,
    out: str | Path,
    images: str | None = None,
    image_format: str = "png",
    quality: int = 95,
    target_bytes: int = int(1e8),
    frame_step: int = 1,
    skip_bad: bool = False,
    append: bool = False,
) -> ConvertReport:
    """Convert SRC (one scene or a folder of scenes) in format `fmt` into chunks in OUT.

    A bad scene raises (and this run's chunks are removed) unless `skip_bad`, which skips it and
    lists it in the report. Returns the report with the written index.
    """
    if fmt not in CONVERTERS:
        raise SurfSplatInputError(f"format: expected one of {', '.join(CONVERTERS)}, got {fmt!r}")
    src = Path(src)
    report = ConvertReport()
    if fmt in ("dtu", "llff", "blender", "colmap"):
        dirs = _scene_dirs(src, DETECTORS[fmt], fmt)
        examples: Iterator[Example] = _scene_examples(fmt, dirs, images, image_format, quality, report, skip_bad)
    elif fmt == "dl3dv":
        examples = _raw_examples(
            _scene_dirs(src, _is_dl3dv, "DL3DV"),
            lambda d: (dl3dv_example(d, images or "images_8"), 0),
            report,
            skip_bad,
        )
    else:
        examples = _raw_examples(
            _scene_dirs(src, _is_scannet, "ScanNet"), lambda d: scannet_example(d, frame_step), report, skip_bad
        )
    with ChunkWriter(out, target_bytes=target_bytes, append=append) as writer:
        for example in examples:
            writer.add(example)
            report.written.append(example["key"])
    if not report.written:
        raise SurfSplatInputError(f"{src}: no scene could be converted\n{report}")
    report.index = dict(writer.index)
    return report


def _raw_examples(
    dirs: list[Path], make: Callable[[Path], tuple[Example, int]], report: ConvertReport, skip_bad: bool
) -> Iterator[Example]:
    for d in dirs:
        try:
            example, dropped = make(d)
        except (SurfSplatInputError, FileNotFoundError) as err:
            if not skip_bad:
                raise
            report.skipped.append(f"{d}: {err}")
            continue
        if dropped:
            report.skipped.append(f"{d}: {dropped} frames with an invalid (inf/NaN) pose")
        yield example
