"""RealEstate10K / ACID raw camera files: `<key>.txt` plus a folder of extracted frames.

The first line of the .txt is the video URL; every other line is a timestamp (microseconds)
followed by 18 numbers: fx, fy, cx, cy normalized by the image width/height, two zeros, and the
row-major 3x4 world-to-camera matrix (OpenCV axes). Frames are image files named by timestamp
(`<timestamp>.png` / `.jpg`) in `<key>/`, `frames/<key>/` or `frames/` beside the .txt. A listed
timestamp without its frame is left out with one warning that counts them (`common.present_views`).
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor

from ...geometry.cameras import Cameras, rigid_inverse, validate_c2w
from ...utils.checks import SurfSplatInputError
from ..images import is_image_file
from ..posed_images import PosedImages, check_finite_rows
from .common import camera_set, image_sizes, load_image_stack, make_cameras, present_views


def find_camera_file(path: Path) -> Path | None:
    if path.is_file() and path.suffix == ".txt":
        return path
    if path.is_dir():
        txts = sorted(p for p in path.iterdir() if p.is_file() and p.suffix == ".txt")
        if len(txts) == 1 and _first_line(txts[0]).startswith("http"):
            return txts[0]
    return None


def _first_line(path: Path) -> str:
    with path.open() as f:
        return f.readline().strip()


def is_re10k_raw(path: Path) -> bool:
    return find_camera_file(path) is not None


def read_camera_file(path: Path) -> tuple[str, Tensor, Tensor]:
    """(url, timestamps int64 [N], rows float64 [N, 18]) with each bad line named."""
    lines = path.read_text().splitlines()
    if not lines:
        raise SurfSplatInputError(f"{path}: empty camera file")
    url = lines[0].strip()
    timestamps, rows = [], []
    for line_no, line in enumerate(lines[1:], start=2):
        tokens = line.split()
        if not tokens:
            continue
        if len(tokens) != 19:
            raise SurfSplatInputError(
                f"{path}:{line_no}: expected a timestamp and 18 numbers, got {len(tokens)} fields"
            )
        try:
            timestamps.append(int(tokens[0]))
            rows.append([float(v) for v in tokens[1:]])
        except ValueError as err:
            raise SurfSplatInputError(f"{path}:{line_no}: {err}") from None
    if not rows:
        raise SurfSplatInputError(f"{path}: no camera lines after the URL line")
    return url, torch.tensor(timestamps, dtype=torch.int64), torch.tensor(rows, dtype=torch.float64)


def rows_to_cameras(rows: Tensor, width: int, height: int, source: str, dtype: torch.dtype) -> Cameras:
    """RealEstate10K 18-number rows [N, 18] -> validated Cameras with pixel K for (width, height)."""
    check_finite_rows(rows, source, "camera row")
    n = rows.shape[0]
    K = torch.zeros(n, 3, 3, dtype=torch.float64)
    K[:, 0, 0] = rows[:, 0] * width
    K[:, 1, 1] = rows[:, 1] * height
    K[:, 0, 2] = rows[:, 2] * width
    K[:, 1, 2] = rows[:, 3] * height
    K[:, 2, 2] = 1
    w2c = torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    w2c[:, :3, :] = rows[:, 6:].reshape(n, 3, 4).to(torch.float64)
    validate_c2w(f"{source}: world-to-camera of row", w2c)
    return make_cameras(rigid_inverse(w2c), K, source, dtype)


def _find_frames(txt: Path, frames: Path | None) -> Path:
    if frames is not None:
        if not frames.is_dir():
            raise FileNotFoundError(f"{frames}: frames folder not found")
        return frames
    for candidate in (txt.parent / txt.stem, txt.parent / "frames" / txt.stem, txt.parent / "frames"):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError(f"{txt}: no frames folder ({txt.stem}/, frames/{txt.stem}/ or frames/ beside it)")


def load_re10k_raw(
    path: Path,
    frames: Path | None = None,
    dtype: torch.dtype = torch.float32,
    cameras_only: bool = False,
) -> PosedImages:
    """Read a raw RealEstate10K/ACID camera file and its extracted frames (see module doc)."""
    txt = find_camera_file(path)
    if txt is None:
        raise FileNotFoundError(f"{path}: no RealEstate10K camera .txt")
    url, timestamps, rows = read_camera_file(txt)
    folder = _find_frames(txt, frames)
    by_stamp = {}
    for p in folder.iterdir():
        if is_image_file(p) and p.stem.isdigit():
            by_stamp[int(p.stem)] = p
    # a listed timestamp whose frame was not extracted is left out (one warning counts them), as in the
    # other camera files that list photos; its name in the warning takes the extracted frames' suffix
    suffix = next(iter(by_stamp.values())).suffix if by_stamp else ".png"
    paths = [by_stamp.get(ts, folder / f"{ts}{suffix}") for ts in timestamps.tolist()]
    keep = present_views(paths, str(txt))
    paths, timestamps, rows = [paths[i] for i in keep], timestamps[keep], rows[keep]
    sizes = image_sizes(paths)
    if len(set(sizes)) != 1:
        raise SurfSplatInputError(f"{folder}: frames have different sizes {sorted(set(sizes))}")
    width, height = sizes[0]
    cameras = rows_to_cameras(rows, width, height, str(txt), dtype)
    if cameras_only:
        return camera_set(cameras, paths, sizes, [str(ts) for ts in timestamps.tolist()])
    rgb, _ = load_image_stack(paths, background=None)
    return PosedImages(
        images=rgb,
        cameras=cameras,
        names=[str(ts) for ts in timestamps.tolist()],
        source=str(txt),
        extras={"url": url, "timestamps": timestamps},
    )
