"""RealEstate10K / ACID `.torch` chunks: reader, writer and `index.json`.

A chunk file is a list of examples, each a dict
    url:        str
    timestamps: int64 [V]
    cameras:    float32 [V, 18]: fx, fy, cx, cy normalized by image width/height, two zeros,
                then the row-major 3x4 world-to-camera matrix (OpenCV axes)
    images:     list of V uint8 tensors, each one encoded image file (JPEG in the releases)
    key:        str, unique across the dataset
and optionally `depths`: list of V uint8 tensors, 16-bit PNG depth in millimetres (ScanNet, synthetic).
`index.json` beside the chunks maps key -> chunk file name. Examples are decoded lazily: reading
a chunk keeps the encoded bytes, and only the views a sample uses are decoded.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..utils.atomic import atomic_path
from ..utils.atomic import write_text as atomic_write_text
from ..utils.checks import SurfSplatInputError, read_json
from .formats.re10k_raw import rows_to_cameras
from .images import decode_depth_png, decode_image_bytes, encode_depth_png, encode_image, image_bytes_size
from .posed_images import PosedImages

Example = dict[str, Any]
REQUIRED_KEYS = ("url", "timestamps", "cameras", "images", "key")
INDEX_FILE = "index.json"


def validate_example(example: object, source: str) -> Example:
    """Check one chunk entry's structure (not its pixels); errors name `source` and the field."""
    if not isinstance(example, dict):
        raise SurfSplatInputError(f"{source}: expected a dict, got {type(example).__name__}")
    key = example.get("key", "?")
    where = f"{source} ('{key}')"
    for field in REQUIRED_KEYS:
        if field not in example:
            raise SurfSplatInputError(f"{where}: missing field '{field}'")
    if not isinstance(example["key"], str) or not example["key"]:
        raise SurfSplatInputError(f"{where}: field 'key' must be a non-empty string")
    cameras = example["cameras"]
    if (
        not isinstance(cameras, Tensor)
        or cameras.ndim != 2
        or cameras.shape[1] != 18
        or not cameras.is_floating_point()
    ):
        shape = tuple(cameras.shape) if isinstance(cameras, Tensor) else type(cameras).__name__
        raise SurfSplatInputError(f"{where}: field 'cameras' must be a float tensor [V, 18], got {shape}")
    v = cameras.shape[0]
    if v == 0:
        raise SurfSplatInputError(f"{where}: no views (cameras is [0, 18])")
    ts = example["timestamps"]
    if not isinstance(ts, Tensor) or ts.shape != (v,) or ts.is_floating_point():
        shape = tuple(ts.shape) if isinstance(ts, Tensor) else type(ts).__name__
        raise SurfSplatInputError(f"{where}: field 'timestamps' must be an integer tensor [{v}], got {shape}")
    for field in ("images", "depths"):
        if field not in example:
            continue
        value = example[field]
        if not isinstance(value, (list, tuple)) or len(value) != v:
            n = len(value) if isinstance(value, (list, tuple)) else type(value).__name__
            raise SurfSplatInputError(f"{where}: field '{field}' must be a list of {v} byte tensors, got {n}")
        for i, item in enumerate(value):
            if not isinstance(item, Tensor) or item.dtype != torch.uint8 or item.ndim != 1 or item.numel() == 0:
                raise SurfSplatInputError(
                    f"{where}: {field}[{i}] must be a non-empty 1-D uint8 tensor of encoded bytes"
                )
    return example


def read_chunk(path: str | Path) -> list[Example]:
    """Load and validate a chunk file (all its examples' structure; pixels stay encoded)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: chunk file not found")
    try:
        # weights_only: a chunk holds only tensors, strings, lists and dicts; nothing to execute.
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - corrupt bytes surface as any of a dozen unpickler errors; all mean the same
        if isinstance(err, MemoryError):
            raise
        first = str(err).strip().splitlines()[0][:160] if str(err).strip() else ""
        raise SurfSplatInputError(f"{path}: cannot load chunk ({type(err).__name__}: {first})") from None
    if not isinstance(data, list):
        raise SurfSplatInputError(f"{path}: expected a list of examples, got {type(data).__name__}")
    if not data:
        raise SurfSplatInputError(f"{path}: chunk contains no examples")
    return [validate_example(ex, f"{path} example {i}") for i, ex in enumerate(data)]


def list_chunks(root: str | Path) -> list[Path]:
    """Chunk files of a folder in sorted order."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: chunk folder not found")
    return sorted(p for p in root.iterdir() if p.is_file() and p.suffix == ".torch")


def read_index(root: str | Path) -> dict[str, Path]:
    """index.json of a chunk folder: key -> chunk path."""
    path = Path(root) / INDEX_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: index file not found")
    data = read_json(path)
    if not isinstance(data, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
        raise SurfSplatInputError(f"{path}: expected an object mapping scene keys to chunk file names")
    return {k: Path(root) / v for k, v in data.items()}


def load_example(root: str | Path, key: str) -> Example:
    """The example with `key`, found through index.json."""
    index = read_index(root)
    if key not in index:
        raise SurfSplatInputError(f"{Path(root) / INDEX_FILE}: key '{key}' not found ({len(index)} keys)")
    for example in read_chunk(index[key]):
        if example["key"] == key:
            return example
    raise SurfSplatInputError(f"{index[key]}: index.json lists key '{key}' here but the chunk does not hold it")


def image_size(example: Example, view: int, source: str) -> tuple[int, int]:
    """(width, height) of one view from its encoded header, without decoding pixels."""
    return image_bytes_size(example["images"][view], f"{source} ('{example['key']}') image {view}")


def example_cameras(
    example: Example, width: int, height: int, source: str, dtype: torch.dtype = torch.float32
) -> Cameras:
    """All V cameras of an example with pixel K for width x height images."""
    return rows_to_cameras(example["cameras"].to(torch.float64), width, height, f"{source} ('{example['key']}')", dtype)


def decode_views(example: Example, views: list[int], source: str) -> Tensor:
    """Decode the listed views only: [len(views), 3, H, W] in [0, 1]."""
    where = f"{source} ('{example['key']}')"
    images = [decode_image_bytes(example["images"][v], f"{where} image {v}") for v in views]
    shapes = {tuple(im.shape) for im in images}
    if len(shapes) != 1:
        raise SurfSplatInputError(f"{where}: views {views} have different sizes {sorted(shapes)}")
    return torch.stack(images)


def decode_depths(example: Example, views: list[int], source: str) -> Tensor | None:
    """[len(views), 1, H, W] metres from the optional `depths` field, or None when absent."""
    if "depths" not in example:
        return None
    where = f"{source} ('{example['key']}')"
    return torch.stack([decode_depth_png(example["depths"][v], f"{where} depth {v}") for v in views])[:, None]


def example_to_scene(example: Example, source: str = "chunk", views: list[int] | None = None) -> PosedImages:
    """Decode an example (or some of its views) into PosedImages; names are the timestamps."""
    validate_example(example, source)
    views = list(range(example["cameras"].shape[0])) if views is None else list(views)
    images = decode_views(example, views, source)
    h, w = images.shape[2:]
    cameras = example_cameras(example, w, h, source)[torch.tensor(views)]
    depths = decode_depths(example, views, source)
    if depths is not None and depths.shape[2:] != images.shape[2:]:
        depths = torch.nn.functional.interpolate(depths, size=(h, w), mode="nearest-exact")
    return PosedImages(
        images=images,
        cameras=cameras,
        names=[str(int(example["timestamps"][v])) for v in views],
        depths=depths,
        source=f"{source} ('{example['key']}')",
        extras={"url": example["url"], "key": example["key"]},
    )


def scene_to_example(
    scene: PosedImages,
    key: str,
    url: str = "",
    image_format: str = "jpeg",
    quality: int = 95,
    timestamps: Tensor | None = None,
) -> Example:
    """Encode PosedImages as a chunk example (cameras normalized by the image size, as the format wants)."""
    rows = scene.cameras.to(torch.float64).to_re10k(scene.width, scene.height).to(torch.float32)
    example: Example = {
        "url": url,
        "timestamps": torch.arange(len(scene), dtype=torch.int64) if timestamps is None else timestamps.to(torch.int64),
        "cameras": rows,
        "images": [encode_image(img, image_format, quality) for img in scene.images],
        "key": key,
    }
    if scene.depths is not None:
        example["depths"] = [encode_depth_png(d[0]) for d in scene.depths]
    return validate_example(example, f"scene_to_example('{key}')")


def _atomic_save(obj: object, path: Path) -> None:
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def _atomic_write_text(text: str, path: Path) -> None:
    atomic_write_text(path, text)


def _example_bytes(example: Example) -> int:
    total = sum(int(t.numel()) for t in example["images"])
    return total + sum(int(t.numel()) for t in example.get("depths", []))


class ChunkWriter:
    """Writes examples into `000000.torch`, `000001.torch`, ... of about `target_bytes` each,
    then `index.json`. Files are written to a temporary name and renamed, so an interrupted
    run leaves no half-written chunk; `abort()` (called on an exception inside a `with` block)
    removes this run's chunks. Refuses a folder that already holds chunks unless `append`."""

    def __init__(self, out_dir: str | Path, target_bytes: int = int(1e8), append: bool = False) -> None:
        self.out_dir = Path(out_dir)
        self.created_dir = not self.out_dir.exists()
        self.out_dir.mkdir(parents=True, exist_ok=True)
        existing = list_chunks(self.out_dir)
        if existing and not append:
            raise SurfSplatInputError(f"{self.out_dir}: already holds {len(existing)} chunks; choose an empty folder")
        self.index: dict[str, str] = {}
        if append and (self.out_dir / INDEX_FILE).is_file():
            self.index = {k: v.name for k, v in read_index(self.out_dir).items()}
        self.next_chunk = (int(existing[-1].stem) + 1) if existing else 0
        self.target_bytes = target_bytes
        self.pending: list[Example] = []
        self.pending_bytes = 0
        self.created: list[Path] = []

    def add(self, example: Example) -> None:
        validate_example(example, f"example '{example.get('key', '?') if isinstance(example, dict) else '?'}'")
        key = example["key"]
        if key in self.index or any(e["key"] == key for e in self.pending):
            raise SurfSplatInputError(f"example key '{key}' is written twice; keys must be unique")
        self.pending.append(example)
        self.pending_bytes += _example_bytes(example)
        if self.pending_bytes >= self.target_bytes:
            self.flush()

    def flush(self) -> None:
        if not self.pending:
            return
        name = f"{self.next_chunk:06d}.torch"
        _atomic_save(self.pending, self.out_dir / name)
        self.created.append(self.out_dir / name)
        for example in self.pending:
            self.index[example["key"]] = name
        self.next_chunk += 1
        self.pending = []
        self.pending_bytes = 0

    def close(self) -> dict[str, str]:
        """Write the last chunk and index.json; returns the index (key -> file name)."""
        self.flush()
        _atomic_write_text(json.dumps(self.index, indent=1, sort_keys=True), self.out_dir / INDEX_FILE)
        return dict(self.index)

    def abort(self) -> None:
        """Delete the chunks this writer created (and its folder, if it made it and it is now
        empty); an existing index.json is left as it was."""
        for path in self.created:
            path.unlink(missing_ok=True)
        self.created = []
        if self.created_dir and not any(self.out_dir.iterdir()):
            self.out_dir.rmdir()
        self.pending = []
        self.pending_bytes = 0

    def __enter__(self) -> ChunkWriter:
        return self

    def __exit__(self, exc_type: object, *_: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_chunks(
    examples: Iterable[Example], out_dir: str | Path, target_bytes: int = int(1e8), append: bool = False
) -> dict[str, str]:
    """Write examples as chunks plus index.json (see ChunkWriter); returns the index."""
    with ChunkWriter(out_dir, target_bytes=target_bytes, append=append) as writer:
        for example in examples:
            writer.add(example)
    return dict(writer.index)
