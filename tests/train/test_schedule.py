"""The learning-rate schedule: OneCycleLR's cosine curve as a pure function of the step."""

from __future__ import annotations

import pytest
import torch

from surfsplat.train.schedule import learning_rate
from surfsplat.utils.checks import SurfSplatInputError


def _one_cycle_reference(total: int, peak: float, pct: float, div: float, final_div: float) -> list[float]:
    """The release's scheduler (torch's OneCycleLR as Lightning steps it): lr used by each step."""
    param = torch.nn.Parameter(torch.zeros(1))
    optimizer = torch.optim.AdamW([param], lr=peak)
    scheduler = torch.optim.lr_scheduler.OneCycleLR(
        optimizer,
        peak,
        total,
        pct_start=pct,
        cycle_momentum=False,
        anneal_strategy="cos",
        div_factor=div,
        final_div_factor=final_div,
    )
    rates = []
    for _ in range(total):
        rates.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    return rates


@pytest.mark.parametrize(
    "total, pct",
    [(400, 0.01), (200, 0.05), (37, 0.3), (150, 0.0)],
)
def test_matches_torch_one_cycle(total: int, pct: float) -> None:
    peak, div, final_div = 2e-4, 25.0, 1e4
    expected = _one_cycle_reference(total, peak, pct, div, final_div)
    ours = [learning_rate(s, peak, total, pct, div, final_div) for s in range(total)]
    assert ours == pytest.approx(expected, rel=1e-12, abs=1e-20)


def test_closed_form_endpoints() -> None:
    peak, total = 2e-4, 1000  # the release: warm-up breakpoint at step 0.01 * 1000 - 1 = 9
    assert learning_rate(0, peak, total) == pytest.approx(peak / 25)
    assert learning_rate(9, peak, total) == pytest.approx(peak)
    assert learning_rate(999, peak, total) == pytest.approx(peak / 25 / 1e4)
    # Half-way through the decay (step 9 + 990 / 2) the cosine is at the mean of its ends.
    assert learning_rate(504, peak, total) == pytest.approx((peak + peak / 25 / 1e4) / 2)
    # Past the end the final value holds.
    assert learning_rate(5000, peak, total) == learning_rate(999, peak, total)


def test_shape_rises_then_falls() -> None:
    rates = [learning_rate(s, 1.0, 400, 0.05) for s in range(400)]
    top = rates.index(max(rates))
    assert top == 19
    assert all(a < b for a, b in zip(rates[:top], rates[1 : top + 1]))
    assert all(a > b for a, b in zip(rates[top:-1], rates[top + 1 :]))


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"step": -1}, "step"),
        ({"step": 1.5}, "step"),
        ({"total_steps": 0}, "total_steps"),
        ({"warmup_fraction": 1.0}, "warmup_fraction"),
    ],
)
def test_rejects_bad_arguments(kwargs: dict, field: str) -> None:
    args = {"step": 0, "peak": 1.0, "total_steps": 10, "warmup_fraction": 0.1}
    args.update(kwargs)
    with pytest.raises(SurfSplatInputError, match=field):
        learning_rate(**args)
