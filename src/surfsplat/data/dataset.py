"""Streaming datasets of training / evaluation samples, one layout for every source.

Sample layout (a dict; torch's default collate stacks it into a batch [B, ...]):

    sample["context"] / sample["target"]: dict of
        "image": [V, 3, H, W] float32 in [0, 1]
        "c2w":   [V, 4, 4]    float32 camera-to-world, OpenCV axes
        "K":     [V, 3, 3]    float32 intrinsics in pixels of these images
        "near":  [V]          float32 depth bounds (for the cost volume)
        "far":   [V]
        "index": [V]          int64 frame indices in the source scene
        "depth": [V, 1, H, W] float32 camera-z depth, only where the source has it (0 = unknown)
    sample["scene"]: str, the scene key (the evaluation entry key when an index is used)

`views_to_cameras(sample["context"])` gives a `Cameras`. The synthetic dataset yields the same
layout (plus "normal"), so training code handles both.

`ChunkDataset` streams RealEstate10K-style chunk folders: one chunk in memory at a time, only the
selected views decoded, each (rank, worker) pair reading a disjoint share. A bad example (corrupt
image, NaN camera, non-rotation, too few frames, ...) is skipped and counted in `summary` with
its chunk, key and reason; a non-empty summary is logged when a pass ends.
"""

from __future__ import annotations

import logging
import multiprocessing
import zlib
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from torch.utils.data import IterableDataset, get_worker_info

from ..geometry.cameras import Cameras
from ..utils.checks import SurfSplatInputError
from .chunks import decode_depths, decode_views, example_cameras, image_size, list_chunks, read_chunk, read_index
from .transforms import ResizeMethod, rescale_and_crop
from .view_sampler import BoundedViewSampler, EvaluationViewSampler, NotEnoughViews

logger = logging.getLogger("surfsplat.data")
Sample = dict[str, Any]


def views_to_cameras(views: dict[str, Tensor]) -> Cameras:
    """Cameras of one sample's view dict ("c2w" [V, 4, 4], "K" [V, 3, 3])."""
    return Cameras(views["c2w"], views["K"])


def mix_seed(*values: int) -> int:
    """A 63-bit seed from integers (splitmix64 steps), so random choices depend on what is being
    sampled, not on which worker samples it."""
    h = 0x9E3779B97F4A7C15
    for v in values:
        h = (h ^ (int(v) & 0xFFFFFFFFFFFFFFFF)) * 0xBF58476D1CE4E5B9 & 0xFFFFFFFFFFFFFFFF
        h = (h ^ (h >> 31)) * 0x94D049BB133111EB & 0xFFFFFFFFFFFFFFFF
    return h >> 1


@dataclass
class DatasetSummary:
    """What one pass over a dataset shard produced and skipped, by reason."""

    yielded: int = 0
    skipped: Counter = field(default_factory=Counter)
    messages: list[str] = field(default_factory=list)  # the first `max_messages` problems, verbatim
    max_messages: int = 20

    def skip(self, reason: str, message: str) -> None:
        self.skipped[reason] += 1
        if len(self.messages) < self.max_messages:
            self.messages.append(message)

    @property
    def num_skipped(self) -> int:
        return sum(self.skipped.values())

    def __str__(self) -> str:
        reasons = ", ".join(f"{n} {r}" for r, n in sorted(self.skipped.items())) or "none"
        lines = [f"{self.yielded} samples, {self.num_skipped} skipped ({reasons})"]
        lines += [f"  {m}" for m in self.messages]
        return "\n".join(lines)


def shard_info(rank: int | None = None, world_size: int | None = None) -> tuple[int, int]:
    """(shard id, number of shards) of the calling process: distributed rank x data-loader worker."""
    if rank is None or world_size is None:
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            rank, world_size = torch.distributed.get_rank(), torch.distributed.get_world_size()
        else:
            rank, world_size = 0, 1
    info = get_worker_info()
    worker, workers = (info.id, info.num_workers) if info is not None else (0, 1)
    return rank * workers + worker, world_size * workers


@dataclass
class ChunkDatasetConfig:
    """A RealEstate10K-style chunk dataset (RealEstate10K, ACID, DTU/DL3DV/ScanNet conversions)."""

    roots: list[Path] = field(default_factory=list)  # chunk folders (*.torch and index.json)
    image_shape: tuple[int, int] | None = (256, 256)  # (H, W) after rescale-and-crop; None keeps the source size
    resize_method: ResizeMethod = "lanczos"  # the release resizes with Pillow's Lanczos filter
    near: float = 0.5  # depth bounds given to the model (RealEstate10K training values)
    far: float = 100.0
    max_fov_deg: float = 100.0  # skip videos with a wider horizontal field of view (as the release)
    shuffle: bool = True  # shuffle chunks and examples per epoch (same order on every rank)
    seed: int = 0  # base seed of shuffling and view sampling
    use_index: bool = False  # list chunks from index.json instead of the folder
    with_depth: bool = True  # add "depth" where the chunk stores depths
    # Truth of the targets at s times image_shape, from frames that large or larger (a sample whose
    # frames are smaller is skipped and counted): "image_hr" / "K_hr" of a random highres_crop-pixel
    # window (0: all of it), as the procedural rooms give; 0 = none.
    highres_factor: int = 0
    highres_crop: int = 0


class ChunkDataset(IterableDataset):
    """Streams samples from chunk folders with a bounded (training) or evaluation view sampler."""

    def __init__(
        self,
        config: ChunkDatasetConfig,
        sampler: BoundedViewSampler | EvaluationViewSampler,
        rank: int | None = None,
        world_size: int | None = None,
    ) -> None:
        super().__init__()
        if not config.roots:
            raise SurfSplatInputError("roots: expected at least one chunk folder")
        self.config = config
        self.sampler = sampler
        self.rank, self.world_size = rank, world_size
        chunks: list[Path] = []
        for root in config.roots:
            found = sorted(set(read_index(root).values())) if config.use_index else list_chunks(root)
            if not found:
                raise SurfSplatInputError(f"{root}: no .torch chunks")
            chunks.extend(found)
        self.chunks = chunks
        self._epoch = multiprocessing.Value("q", 0)
        self.summary = DatasetSummary()

    def set_epoch(self, epoch: int) -> None:
        """Changes the shuffle order and the sampled views; visible to running workers."""
        self._epoch.value = int(epoch)

    def _ordered_chunks(self, epoch: int) -> list[tuple[int, Path]]:
        order = list(range(len(self.chunks)))
        if self.config.shuffle:
            g = torch.Generator().manual_seed(mix_seed(self.config.seed, epoch))
            order = torch.randperm(len(order), generator=g).tolist()
        return [(i, self.chunks[i]) for i in order]

    def __iter__(self) -> Iterator[Sample]:
        epoch = int(self._epoch.value)
        shard, num_shards = shard_info(self.rank, self.world_size)
        summary = self.summary = DatasetSummary()
        chunks = self._ordered_chunks(epoch)
        # Disjoint shares: whole chunks when there are enough of them, else every num_shards-th example.
        by_chunk = len(chunks) >= num_shards
        if by_chunk:
            chunks = chunks[shard::num_shards]
        counter = 0
        for chunk_id, path in chunks:
            try:
                examples = read_chunk(path)
            except SurfSplatInputError as err:
                summary.skip("unreadable chunk", str(err))
                continue
            order = list(range(len(examples)))
            if self.config.shuffle:
                g = torch.Generator().manual_seed(mix_seed(self.config.seed, epoch, chunk_id))
                order = torch.randperm(len(order), generator=g).tolist()
            for example_id in order:
                mine = by_chunk or counter % num_shards == shard
                counter += 1
                if not mine:
                    continue
                yield from self._samples(
                    path, examples[example_id], mix_seed(self.config.seed, epoch, chunk_id, example_id), summary
                )
        if summary.num_skipped:
            logger.warning("%s shard %d/%d: %s", type(self).__name__, shard, num_shards, summary)

    def _samples(self, path: Path, example: dict, seed: int, summary: DatasetSummary) -> Iterator[Sample]:
        key = example["key"]
        where = f"{path} ('{key}')"
        try:
            width, height = image_size(example, 0, str(path))
            cameras = example_cameras(example, width, height, str(path))
        except SurfSplatInputError as err:
            summary.skip("bad cameras or image header", str(err))
            return
        fov = torch.rad2deg(2 * torch.atan(width / (2 * cameras.K[:, 0, 0])))
        if bool((fov > self.config.max_fov_deg).any()):
            summary.skip(
                "field of view too wide",
                f"{where}: field of view {float(fov.max()):.1f} deg > {self.config.max_fov_deg}",
            )
            return
        num_views = len(cameras)
        if isinstance(self.sampler, EvaluationViewSampler):
            try:
                entries = self.sampler.views(key, num_views)
            except SurfSplatInputError as err:
                summary.skip("index out of range", f"{where}: {err}")
                return
            if not entries:
                summary.skip("not in evaluation index", f"{where}: no entry in {self.sampler.index.source}")
                return
            for entry_key, context, target in entries:
                if context is None:
                    summary.skip("excluded by evaluation index", f"{where}: entry '{entry_key}' is null")
                    continue
                sample = self._build(example, where, entry_key, context, target, cameras, width, height, summary)
                if sample is not None:
                    yield sample
            return
        try:
            context, target = self.sampler.sample(num_views, torch.Generator().manual_seed(seed))
        except NotEnoughViews as err:
            summary.skip("too few frames", f"{where}: {err}")
            return
        sample = self._build(example, where, key, context, target, cameras, width, height, summary)
        if sample is not None:
            yield sample

    def _build(
        self,
        example: dict,
        where: str,
        scene: str,
        context: Tensor,
        target: Tensor,
        cameras: Cameras,
        width: int,
        height: int,
        summary: DatasetSummary,
    ) -> Sample | None:
        views = sorted(set(context.tolist()) | set(target.tolist()))
        try:
            images = decode_views(example, views, where)
            if images.shape[2:] != (height, width):
                raise SurfSplatInputError(
                    f"{where}: images are {images.shape[3]}x{images.shape[2]} but view 0's header says {width}x{height}"
                )
            depths = decode_depths(example, views, where) if self.config.with_depth else None
        except SurfSplatInputError as err:
            summary.skip("undecodable image", str(err))
            return None
        if depths is not None and depths.shape[2:] != images.shape[2:]:
            depths = torch.nn.functional.interpolate(depths, size=images.shape[2:], mode="nearest-exact")
        K = cameras.K[torch.tensor(views)]
        highres = None
        if self.config.highres_factor:
            highres = self._highres(images, K, views, target, scene, where, summary)
            if highres is None:
                return None
        if self.config.image_shape is not None:
            images, K, depths = rescale_and_crop(images, K, self.config.image_shape, self.config.resize_method, depths)
        position = {v: i for i, v in enumerate(views)}
        c2w_all = cameras.c2w[torch.tensor(views)]

        def pick(indices: Tensor) -> dict[str, Tensor]:
            rows = torch.tensor([position[int(i)] for i in indices])
            out = {
                "image": images[rows],
                "c2w": c2w_all[rows].float(),
                "K": K[rows].float(),
                "near": torch.full((len(rows),), self.config.near),
                "far": torch.full((len(rows),), self.config.far),
                "index": indices.to(torch.int64),
            }
            if depths is not None:
                out["depth"] = depths[rows]
            return out

        summary.yielded += 1
        sample = {"context": pick(context), "target": pick(target), "scene": scene}
        if highres is not None:
            sample["target"].update(highres)
        return sample

    def _highres(
        self, images: Tensor, K: Tensor, views: list[int], target: Tensor, scene: str, where: str, summary
    ) -> dict[str, Tensor] | None:
        """The targets' frames at s times image_shape (resized down from the frames, never up), and a
        random window of them with its intrinsics; None (counted) when the frames are smaller."""
        c, s = self.config, self.config.highres_factor
        if c.image_shape is None:
            raise SurfSplatInputError("highres_factor: needs image_shape (the size it multiplies)")
        h, w = c.image_shape[0] * s, c.image_shape[1] * s
        H, W = images.shape[-2:]
        if H < h or W < w:
            summary.skip(
                f"frames too small for x{s} truth",
                f"{where}: frames are {W}x{H}, x{s} truth at {c.image_shape[1]}x{c.image_shape[0]} needs {w}x{h}",
            )
            return None
        rows = torch.tensor([views.index(int(i)) for i in target])
        frames, K_hr, _ = rescale_and_crop(images[rows], K[rows], (h, w), c.resize_method)
        cw, ch = (c.highres_crop, c.highres_crop) if c.highres_crop else (w, h)
        if cw > w or ch > h:
            raise SurfSplatInputError(f"highres_crop: {c.highres_crop} is larger than the x{s} image {w}x{h}")
        g = torch.Generator().manual_seed(mix_seed(c.seed, zlib.crc32(scene.encode()), len(views)))
        x0 = torch.randint(0, w - cw + 1, (len(rows),), generator=g)
        y0 = torch.randint(0, h - ch + 1, (len(rows),), generator=g)
        windows = torch.stack([f[:, y : y + ch, x : x + cw] for f, x, y in zip(frames, x0.tolist(), y0.tolist())])
        K_hr = K_hr.clone()
        K_hr[:, 0, 2] -= x0.to(K_hr.dtype)  # a crop only moves the principal point
        K_hr[:, 1, 2] -= y0.to(K_hr.dtype)
        return {"image_hr": windows, "K_hr": K_hr.float()}
