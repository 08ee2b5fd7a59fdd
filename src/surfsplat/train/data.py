"""Training batches: deterministic, disjoint per rank, resumable from a step.

Two kinds of source, one batch layout (`TrainBatch`):

- map-style datasets (the synthetic rooms): the global batch of step s is positions
  s*G .. s*G + G - 1 of an endless sequence of epochs, each epoch a seeded permutation of the
  dataset; rank r takes its contiguous share. The data of a step is a pure function of
  (seed, step), whatever the number of ranks or workers, so resuming needs nothing but the step
  and a 1-process run sees exactly the samples of a 2-process run.
- streaming chunk datasets (RealEstate10K, ACID, and every `surfsplat convert` output): each rank
  reads its own share of chunks (`ChunkDataset` shards by rank and worker); the position is
  (epoch, batches taken this epoch) per rank, and resuming replays the epoch up to that point.
  The bounded view sampler's warm-up reads the training step from a shared counter, which the loop
  updates every step (with loader workers, prefetched samples see a slightly older step, as in the
  release; resume is exact with num_workers = 0).

Augmentation (the release's): with probability 1/2 a sample's context and target views are
mirrored left-right together with their cameras. The coin is seeded by the sample's key (its
global position), so it is also a function of (seed, step).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset, Sampler, default_collate

from ..data.dataset import ChunkDataset, ChunkDatasetConfig, mix_seed
from ..data.eval_index import EvaluationIndex
from ..data.synthetic import SyntheticDataset, SyntheticDatasetConfig
from ..data.transforms import horizontal_flip
from ..data.view_sampler import BoundedViewSampler, EvaluationViewSampler, StepCounter
from ..geometry.cameras import Cameras
from ..utils.checks import SurfSplatInputError
from .config import DataConfig

# Validation rooms come from this offset of the training seed: mix_seed makes the two sequences of
# rooms unrelated, so validation scenes are held out.
VALIDATION_SEED_OFFSET = 1_000_003
_VIEW_KEYS = ("image", "c2w", "K", "near", "far")


@dataclass
class ViewBatch:
    """One role's views (context or target) of B scenes."""

    images: Tensor  # [B, V, 3, H, W] in [0, 1]
    c2w: Tensor  # [B, V, 4, 4] camera-to-world, OpenCV axes
    K: Tensor  # [B, V, 3, 3] intrinsics in pixels of the images
    near: Tensor  # [B, V]
    far: Tensor  # [B, V]
    depths: Tensor | None = None  # [B, V, 1, H, W] ground-truth camera-z depth where the source has it
    images_hr: Tensor | None = None  # [B, V, 3, h, w] native truth of a window at s times the resolution
    K_hr: Tensor | None = None  # [B, V, 3, 3] intrinsics of that window (K scaled by s, shifted by the crop)

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """(B, V, H, W)."""
        b, v, _, h, w = self.images.shape
        return b, v, h, w

    def cameras(self) -> Cameras:
        """The B*V cameras, batch-major (as the model and the decoder expect)."""
        return Cameras(self.c2w.flatten(0, 1), self.K.flatten(0, 1), validate=False)

    def highres_cameras(self) -> Cameras:
        """The B*V cameras of the high-resolution windows (`images_hr`)."""
        if self.K_hr is None:
            raise SurfSplatInputError("this batch has no high-resolution truth (data.highres_factor is 0)")
        return Cameras(self.c2w.flatten(0, 1), self.K_hr.flatten(0, 1), validate=False)

    def to(self, device: torch.device) -> ViewBatch:
        def move(t: Tensor | None) -> Tensor | None:
            return None if t is None else t.to(device, non_blocking=True)

        return ViewBatch(
            *(t.to(device, non_blocking=True) for t in (self.images, self.c2w, self.K, self.near, self.far)),
            depths=move(self.depths),
            images_hr=move(self.images_hr),
            K_hr=move(self.K_hr),
        )


@dataclass
class TrainBatch:
    context: ViewBatch
    target: ViewBatch
    scenes: list[str]  # scene keys
    keys: list[int]  # per-sample seeds of the augmentation (unique within a run)

    def to(self, device: torch.device) -> TrainBatch:
        return replace(self, context=self.context.to(device), target=self.target.to(device))


def _views(batch: dict[str, Tensor], where: str) -> ViewBatch:
    missing = [k for k in _VIEW_KEYS if k not in batch]
    if missing:
        raise SurfSplatInputError(f"{where}: sample is missing {missing}")
    return ViewBatch(
        images=batch["image"].float(),
        c2w=batch["c2w"].float(),
        K=batch["K"].float(),
        near=batch["near"].float(),
        far=batch["far"].float(),
        depths=batch["depth"].float() if "depth" in batch else None,
        images_hr=batch["image_hr"].float() if "image_hr" in batch else None,
        K_hr=batch["K_hr"].float() if "K_hr" in batch else None,
    )


def to_train_batch(collated: dict[str, Any], keys: list[int]) -> TrainBatch:
    """A collated sample dict (layout of `surfsplat.data.dataset`) as a TrainBatch."""
    return TrainBatch(
        context=_views(collated["context"], "context"),
        target=_views(collated["target"], "target"),
        scenes=list(collated["scene"]),
        keys=keys,
    )


def flip_views(views: ViewBatch, flip: Tensor) -> ViewBatch:
    """Mirror the scenes where flip [B] is True (images, cameras, depth), leave the others."""
    if not bool(flip.any()):
        return views
    images, c2w, K = views.images.clone(), views.c2w.clone(), views.K.clone()
    depths = None if views.depths is None else views.depths.clone()
    highres = None if views.images_hr is None else (views.images_hr.clone(), views.K_hr.clone())
    for i in flip.nonzero().flatten().tolist():
        images[i], c2w[i], K[i] = horizontal_flip(views.images[i], views.c2w[i], views.K[i])
        if depths is not None:
            depths[i] = views.depths[i].flip(-1)
        if highres is not None:  # the window mirrors with its own width; the camera mirrors the same way
            highres[0][i], _, highres[1][i] = horizontal_flip(views.images_hr[i], views.c2w[i], views.K_hr[i])
    return ViewBatch(
        images,
        c2w,
        K,
        views.near,
        views.far,
        depths,
        images_hr=None if highres is None else highres[0],
        K_hr=None if highres is None else highres[1],
    )


def augment(batch: TrainBatch, probability: float, seed: int) -> TrainBatch:
    """The release's random horizontal flip, one coin per sample seeded by (seed, sample key)."""
    if probability <= 0:
        return batch
    coins = [
        float(torch.rand((), generator=torch.Generator().manual_seed(mix_seed(seed, 0xF11F, key)))) < probability
        for key in batch.keys
    ]
    flip = torch.tensor(coins)
    return replace(batch, context=flip_views(batch.context, flip), target=flip_views(batch.target, flip))


# ------------------------------------------------------------------------------------- map-style
class CachedDataset(Dataset):
    """Keeps every sample it produced (small synthetic pools: the ray caster runs once per room)."""

    def __init__(self, dataset: Dataset) -> None:
        self.dataset = dataset
        self._cache: dict[int, Any] = {}

    def __len__(self) -> int:
        return len(self.dataset)  # type: ignore[arg-type]

    def __getitem__(self, index: int) -> Any:
        if index not in self._cache:
            self._cache[index] = self.dataset[index]
        return self._cache[index]


class _KeyedDataset(Dataset):
    """Returns (sample, key) for (index, key) requests, so keys travel through loader workers."""

    def __init__(self, dataset: Dataset) -> None:
        self.dataset = dataset

    def __len__(self) -> int:
        return len(self.dataset)  # type: ignore[arg-type]

    def __getitem__(self, request: tuple[int, int]) -> tuple[Any, int]:
        index, key = request
        return self.dataset[index], key


class StepBatchSampler(Sampler):
    """Yields this rank's (index, position) lists for steps start_step, start_step + 1, ..."""

    def __init__(self, length: int, global_batch: int, rank: int, world_size: int, seed: int, start_step: int) -> None:
        if global_batch % world_size:
            raise SurfSplatInputError(f"batch_size: {global_batch} does not split evenly over {world_size} ranks")
        self.length = length
        self.global_batch = global_batch
        self.local_batch = global_batch // world_size
        self.rank = rank
        self.seed = seed
        self.start_step = start_step
        self._epoch = -1
        self._order: list[int] = []

    def _index(self, position: int) -> int:
        epoch, offset = divmod(position, self.length)
        if epoch != self._epoch:
            g = torch.Generator().manual_seed(mix_seed(self.seed, epoch))
            self._order = torch.randperm(self.length, generator=g).tolist()
            self._epoch = epoch
        return self._order[offset]

    def positions(self, step: int) -> list[int]:
        """Global sample positions of this rank at `step`."""
        first = step * self.global_batch + self.rank * self.local_batch
        return list(range(first, first + self.local_batch))

    def __iter__(self) -> Iterator[list[tuple[int, int]]]:
        step = self.start_step
        while True:
            yield [(self._index(p), p) for p in self.positions(step)]
            step += 1


def _loader_generator(seed: int, rank: int, epoch: int) -> torch.Generator:
    """A DataLoader's own generator: starting an iterator draws a seed from it, and drawing from
    the global generator instead would make the run's random stream depend on when loaders start."""
    return torch.Generator().manual_seed(mix_seed(seed, rank, epoch, 0x10AD))


def _collate_keyed(items: list[tuple[Any, int]]) -> tuple[dict[str, Any], list[int]]:
    samples, keys = zip(*items)
    return default_collate(list(samples)), list(keys)


class MapBatches:
    """Endless batches of a map-style dataset, starting at `start_step`."""

    def __init__(
        self,
        dataset: Dataset,
        global_batch: int,
        rank: int,
        world_size: int,
        seed: int,
        start_step: int,
        num_workers: int,
    ) -> None:
        self.sampler = StepBatchSampler(len(dataset), global_batch, rank, world_size, seed, start_step)  # type: ignore[arg-type]
        self.loader = DataLoader(
            _KeyedDataset(dataset),
            batch_sampler=self.sampler,
            num_workers=num_workers,
            collate_fn=_collate_keyed,
            persistent_workers=num_workers > 0,
            generator=_loader_generator(seed, rank, 0),
        )
        self._iter = iter(self.loader)

    def next(self, step: int) -> TrainBatch:
        collated, keys = next(self._iter)
        return to_train_batch(collated, keys)

    def state(self) -> dict[str, Any]:
        return {"kind": "map"}  # the step alone fixes the position


# ------------------------------------------------------------------------------------- streaming
class StreamBatches:
    """Endless batches of a rank's share of a streaming dataset, epoch after epoch."""

    def __init__(
        self,
        dataset: ChunkDataset,
        local_batch: int,
        num_workers: int,
        step_counter: StepCounter,
        rank: int,
        state: dict[str, Any] | None = None,
        start_step: int = 0,
    ) -> None:
        self.dataset = dataset
        self.local_batch = local_batch
        self.num_workers = num_workers
        self.counter = step_counter
        self.rank = rank
        self.epoch = int(state["epoch"]) if state else 0
        self.batches = 0
        self._skip = int(state["batches"]) if state else 0
        self._skip_step = start_step - self._skip  # the step at which each replayed batch was drawn
        self._iter: Iterator[Any] | None = None

    def _start_epoch(self) -> None:
        self.dataset.set_epoch(self.epoch)
        loader = DataLoader(
            self.dataset,
            batch_size=self.local_batch,
            drop_last=True,
            num_workers=self.num_workers,
            collate_fn=default_collate,
            generator=_loader_generator(self.dataset.config.seed, self.rank, self.epoch),
        )
        self._iter = iter(loader)
        self.batches = 0

    def _draw(self) -> dict[str, Any]:
        # Terminates: a fresh epoch either yields a batch or raises.
        while True:
            if self._iter is None:
                self._start_epoch()
            try:
                out = next(self._iter)  # type: ignore[arg-type]
            except StopIteration:
                if self.batches == 0:
                    raise SurfSplatInputError(
                        f"data: rank {self.rank} got no full batch of {self.local_batch} in epoch {self.epoch} "
                        f"({self.dataset.summary}); use fewer ranks, a smaller batch or more scenes"
                    ) from None
                self.epoch += 1
                self._iter = None
                continue
            self.batches += 1
            return out

    def next(self, step: int) -> TrainBatch:
        while self._skip > 0:
            # Replay the batches this rank consumed before the checkpoint, at the steps they were drawn.
            self.counter.set(self._skip_step)
            self._draw()
            self._skip -= 1
            self._skip_step += 1
        self.counter.set(step)
        collated = self._draw()
        keys = [mix_seed(self.rank, self.epoch, self.batches, i) for i in range(self.local_batch)]
        return to_train_batch(collated, keys)

    def state(self) -> dict[str, Any]:
        return {"kind": "stream", "epoch": self.epoch, "batches": self.batches}


# ---------------------------------------------------------------------------------------- builders
def synthetic_dataset(config: DataConfig, validation: bool = False, with_depth: bool = False) -> SyntheticDataset:
    """Procedural rooms for training or validation; validation scenes always carry their depth."""
    length = config.val_samples if validation else config.synthetic_length
    seed = config.synthetic_seed + (VALIDATION_SEED_OFFSET if validation else 0)
    return SyntheticDataset(
        SyntheticDatasetConfig(
            length=max(length, 1),
            seed=seed,
            image_shape=config.image_shape,
            num_context_views=config.num_context_views,
            num_target_views=config.num_target_views,
            supersample=config.synthetic_supersample,
            with_depth=validation or with_depth,
            highres_factor=0 if validation else config.highres_factor,
            highres_crop=config.highres_crop,
        )
    )


def _chunk_config(
    config: DataConfig, roots: tuple[str, ...], seed: int, shuffle: bool, highres: bool = False
) -> ChunkDatasetConfig:
    return ChunkDatasetConfig(
        roots=[Path(r) for r in roots],
        image_shape=config.image_shape,
        near=config.near,
        far=config.far,
        shuffle=shuffle,
        seed=seed,
        highres_factor=config.highres_factor if highres else 0,
        highres_crop=config.highres_crop,
    )


def build_train_batches(
    config: DataConfig,
    global_batch: int,
    rank: int,
    world_size: int,
    seed: int,
    start_step: int,
    stream_state: dict[str, Any] | None = None,
    with_depth: bool = False,
) -> MapBatches | StreamBatches:
    """The training batch source of this rank, positioned at `start_step`; `with_depth` adds the true
    depth of procedural rooms (chunks add it wherever they store it)."""
    if global_batch % world_size:
        raise SurfSplatInputError(f"batch_size: {global_batch} does not split evenly over {world_size} ranks")
    if config.dataset == "synthetic":
        dataset: Dataset = synthetic_dataset(config, with_depth=with_depth)
        if config.cache_samples:
            dataset = CachedDataset(dataset)
        return MapBatches(dataset, global_batch, rank, world_size, seed, start_step, config.num_workers)
    if not config.roots:
        raise SurfSplatInputError("data.roots: dataset 'chunks' needs at least one chunk folder (--roots)")
    sampler_config = replace(
        config.view_sampler, num_context_views=config.num_context_views, num_target_views=config.num_target_views
    )
    counter = StepCounter(start_step)
    sampler = BoundedViewSampler(sampler_config, counter)
    dataset = ChunkDataset(
        _chunk_config(config, config.roots, seed, shuffle=True, highres=True), sampler, rank=rank, world_size=world_size
    )
    return StreamBatches(
        dataset, global_batch // world_size, config.num_workers, counter, rank, stream_state, start_step
    )


def build_validation_samples(config: DataConfig, rank: int, world_size: int, seed: int) -> list[TrainBatch]:
    """This rank's share of the held-out samples, as batches of one scene (fixed for the whole run)."""
    if config.val_samples == 0:
        return []
    if config.dataset == "synthetic":
        dataset = synthetic_dataset(config, validation=True)
        mine = range(rank, config.val_samples, world_size)
        return [to_train_batch(default_collate([dataset[i]]), [i]) for i in mine]
    if not config.val_roots:
        return []
    if config.val_index is not None:
        sampler: BoundedViewSampler | EvaluationViewSampler = EvaluationViewSampler(
            EvaluationIndex.load(config.val_index)
        )
    else:
        # Final gap range from the start: validation should not change with the training step.
        sampler = BoundedViewSampler(
            replace(
                config.view_sampler,
                num_context_views=config.num_context_views,
                num_target_views=config.num_target_views,
                warm_up_steps=0,
            )
        )
    dataset = ChunkDataset(
        _chunk_config(config, config.val_roots, seed + VALIDATION_SEED_OFFSET, shuffle=False),
        sampler,
        rank=rank,
        world_size=world_size,
    )
    share = len(range(rank, config.val_samples, world_size))
    out: list[TrainBatch] = []
    for i, sample in enumerate(dataset):
        if len(out) == share:
            break
        out.append(to_train_batch(default_collate([sample]), [i]))
    return out
