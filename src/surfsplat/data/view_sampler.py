"""Which frames of a video become context and target views.

`BoundedViewSampler` is pixelSplat's training sampler as DepthSplat/SurfSplat configure it for
RealEstate10K: two context frames a random gap apart, the gap range widening linearly from
[25, 45] to [45, 135] frames over the first 30,000 steps, and 4 target frames drawn uniformly
between them (inclusive). `EvaluationViewSampler` reads the fixed views of an evaluation index.
"""

from __future__ import annotations

import multiprocessing
from dataclasses import dataclass

import torch
from torch import Tensor

from ..utils.checks import SurfSplatInputError
from .eval_index import EvaluationIndex


class NotEnoughViews(SurfSplatInputError):
    """The scene has too few frames for the requested context gap."""


class StepCounter:
    """The training step, shared with data-loader worker processes (a multiprocessing Value), so
    the sampler's warm-up follows training even with persistent workers."""

    def __init__(self, step: int = 0) -> None:
        self._value = multiprocessing.Value("q", step)

    def set(self, step: int) -> None:
        self._value.value = int(step)

    def get(self) -> int:
        return int(self._value.value)


@dataclass
class BoundedViewSamplerConfig:
    """pixelSplat's bounded sampler; defaults are DepthSplat/SurfSplat's RealEstate10K settings."""

    num_context_views: int = 2  # views 0 and -1 bound the gap; extra ones are drawn between them
    num_target_views: int = 4  # drawn uniformly (with repetition) between the outer context views
    min_distance_between_context_views: int = 45  # gap range after warm-up (frames)
    max_distance_between_context_views: int = 135
    min_distance_to_context_views: int = 0  # targets keep at least this many frames from the context
    warm_up_steps: int = 30_000  # steps over which the gap range moves from initial to final
    initial_min_distance_between_context_views: int = 25  # gap range at step 0
    initial_max_distance_between_context_views: int = 45
    cameras_are_circular: bool = False  # frames wrap around (turntable captures)


class BoundedViewSampler:
    def __init__(self, config: BoundedViewSamplerConfig | None = None, step: StepCounter | None = None) -> None:
        self.config = config or BoundedViewSamplerConfig()
        if self.config.num_context_views < 2:
            raise SurfSplatInputError(f"num_context_views: expected >= 2, got {self.config.num_context_views}")
        self.step = step or StepCounter()

    def gap_range(self, step: int) -> tuple[int, int]:
        """(min_gap, max_gap) at a training step: linear interpolation, truncated to integers as the
        release does, reaching the final range at warm_up_steps."""
        c = self.config
        if c.warm_up_steps <= 0:
            return c.min_distance_between_context_views, c.max_distance_between_context_views
        fraction = step / c.warm_up_steps

        def schedule(initial: int, final: int) -> int:
            return min(initial + int((final - initial) * fraction), final)

        return (
            schedule(c.initial_min_distance_between_context_views, c.min_distance_between_context_views),
            schedule(c.initial_max_distance_between_context_views, c.max_distance_between_context_views),
        )

    def sample(self, num_views: int, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """(context indices [num_context_views], target indices [num_target_views]), int64."""
        c = self.config
        min_gap, max_gap = self.gap_range(self.step.get())
        if not c.cameras_are_circular:
            max_gap = min(num_views - 1, max_gap)
        min_gap = max(2 * c.min_distance_to_context_views, min_gap)
        if c.num_context_views > 2:
            min_gap = max(min_gap, c.num_context_views - 1)  # room for distinct inner context frames
        if max_gap < min_gap:
            raise NotEnoughViews(f"{num_views} frames are too few for a context gap of at least {min_gap}")
        gap = int(torch.randint(min_gap, max_gap + 1, (), generator=generator))
        left_range = num_views if c.cameras_are_circular else num_views - gap
        left = int(torch.randint(left_range, (), generator=generator))
        right = left + gap
        inner = []
        if c.num_context_views > 2:
            # Extra context views: distinct frames strictly between the outer two.
            order = torch.randperm(gap - 1, generator=generator)[: c.num_context_views - 2] + left + 1
            inner = sorted(order.tolist())
        context = torch.tensor([left, *inner, right], dtype=torch.int64)
        lo = left + c.min_distance_to_context_views
        hi = right - c.min_distance_to_context_views
        target = torch.randint(lo, hi + 1, (c.num_target_views,), generator=generator, dtype=torch.int64)
        if c.cameras_are_circular:
            context, target = context % num_views, target % num_views
        return context, target


class EvaluationViewSampler:
    """Fixed views from an evaluation index; `views(key, num_views)` returns every entry of a scene."""

    def __init__(self, index: EvaluationIndex) -> None:
        self.index = index

    def views(self, scene_key: str, num_views: int) -> list[tuple[str, Tensor, Tensor] | tuple[str, None, None]]:
        """[(entry key, context [Vc], target [Vt])] or (entry key, None, None) for an excluded entry;
        raises when an index refers to a frame the scene does not have."""
        out: list = []
        for entry_key, entry in self.index.lookup(scene_key):
            if entry is None:
                out.append((entry_key, None, None))
                continue
            largest = max(entry.context + entry.target)
            if largest >= num_views:
                raise SurfSplatInputError(
                    f"{self.index.source}: entry '{entry_key}' uses view {largest} but scene '{scene_key}' has {num_views} views"
                )
            out.append((entry_key, torch.tensor(entry.context), torch.tensor(entry.target)))
        return out
