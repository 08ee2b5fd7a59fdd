"""Learning-rate schedule: the release's one-cycle cosine curve as a pure function of the step.

The release (Lightning) uses `torch.optim.lr_scheduler.OneCycleLR(pct_start=0.01,
anneal_strategy="cos", cycle_momentum=False)`: a cosine rise from peak / initial_div to the peak
over the first `warmup_fraction` of the run, then a cosine decay to peak / (initial_div * final_div).
Writing it as a function of the step (nanoGPT style) makes resuming exact by construction: the
scheduler's whole state is the step number, which every checkpoint carries.
"""

from __future__ import annotations

import math

from ..utils.checks import SurfSplatInputError


def _cosine(start: float, end: float, fraction: float) -> float:
    """Half a cosine from `start` (fraction 0) to `end` (fraction 1)."""
    return end + (start - end) * 0.5 * (1.0 + math.cos(math.pi * fraction))


def learning_rate(
    step: int,
    peak: float,
    total_steps: int,
    warmup_fraction: float = 0.01,
    initial_div: float = 25.0,
    final_div: float = 1e4,
) -> float:
    """The learning rate of optimizer step `step` (0-based) of a `total_steps` run.

    Phase 1 ends at step warmup_fraction * total_steps - 1 (OneCycleLR's breakpoint, a float), phase
    2 at total_steps - 1; each phase interpolates with a half cosine between its end values.
    Steps past the end keep the final value. Without a warm-up step (breakpoint <= 0) the decay
    starts from the peak at the breakpoint, as OneCycleLR's does.
    """
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        raise SurfSplatInputError(f"step: expected an integer >= 0, got {step!r}")
    if isinstance(total_steps, bool) or not isinstance(total_steps, int) or total_steps < 1:
        raise SurfSplatInputError(f"total_steps: expected a positive integer, got {total_steps!r}")
    if not 0 <= warmup_fraction < 1:
        raise SurfSplatInputError(f"warmup_fraction: expected a value in [0, 1), got {warmup_fraction!r}")
    initial = peak / initial_div
    final = initial / final_div
    warmup_end = warmup_fraction * total_steps - 1
    last = total_steps - 1
    if warmup_end > 0 and step <= warmup_end:
        return _cosine(initial, peak, step / warmup_end)
    if last <= warmup_end:
        return peak
    fraction = min((step - warmup_end) / (last - warmup_end), 1.0)
    return _cosine(peak, final, fraction)
