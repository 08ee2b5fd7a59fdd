"""Closure: does a reconstruction stay a continuous surface when it is looked at more closely?

A surface of surfels is closed when its accumulated alpha does not depend on the resolution it is
rendered at. The 2DGS screen-space low-pass (SPEC Sec. 3) widens any surfel to about a pixel at the
input's resolution, so a surfel of a third of a pixel looks whole there and leaves a gap at x4; and
forced alpha blending (paper Sec. 3.4) divides colour by alpha, which hides low alpha in our own
renders but not in a standard 3DGS viewer. These numbers make both visible:

- mean alpha and coverage (share of pixels with alpha >= 0.5 and >= 0.9) at every render factor;
- closure = mean alpha at the largest factor / mean alpha at x1 (1 for a closed surface);
- the share of scale multipliers (Eq. 9) sitting at each bound of their clamp [1/r, r];
- the share of surfels whose smaller tangent scale is under half their pixel footprint z / f (the
  surface one pixel of the view that predicted them spans at their depth): such a surfel cannot
  overlap its neighbours once a pixel is smaller than it;
- opacity quantiles (10 %, 50 %, 90 %).

`closed` is the verdict the reports print: closure >= 0.9 and at most 15 % undersized surfels.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..geometry.pixels import pixel_footprints
from ..utils.checks import SurfSplatInputError

CLOSURE_MIN = 0.9  # a closed surface keeps at least this share of its x1 alpha at the largest factor
UNDERSIZED_MAX = 0.15  # and at most this share of surfels under half their footprint
UNDERSIZE_FRACTION = 0.5  # "undersized": smaller tangent scale < this times the pixel footprint
COVERAGE_LEVELS = (0.5, 0.9)
OPACITY_QUANTILES = (0.1, 0.5, 0.9)
_AT_BOUND = 1e-4  # relative tolerance of "at a bound" (the clamp returns the bound exactly)


def undersized(gaussians: Gaussians, footprints: Tensor) -> Tensor:
    """[N] bool: the smaller tangent scale is under UNDERSIZE_FRACTION of the pixel footprint."""
    smallest = gaussians.scales.detach().float().min(-1).values
    return smallest < UNDERSIZE_FRACTION * footprints.to(smallest)


def at_bounds(multipliers: Tensor, multiplier_range: float) -> tuple[Tensor, Tensor]:
    """Per multiplier value, whether it sits at the clamp's lower bound 1/r and at its upper bound r
    (the clamp returns the bound exactly; a relative tolerance absorbs float rounding)."""
    m, r = multipliers.detach().float(), float(multiplier_range)
    return m <= (1 / r) * (1 + _AT_BOUND), m >= r * (1 - _AT_BOUND)


@dataclass
class ClosureMetrics:
    """Closure figures of one or more reconstructions (see the module docstring)."""

    mean_alpha: dict[int, float]  # factor -> mean accumulated alpha over every rendered pixel
    coverage: dict[int, dict[float, float]]  # factor -> {alpha level: share of pixels at or above it}
    undersized: float  # share of surfels with min tangent scale < 0.5 pixel footprint
    opacity_quantiles: dict[float, float]  # q -> opacity quantile
    multiplier_at_low: float | None = None  # share of scale multipliers at 1/r (None: not known)
    multiplier_at_high: float | None = None  # share at r
    surfels: int = 0
    size_ratio_median: float = float("nan")  # median of min tangent scale / footprint
    factors: tuple[int, ...] = field(default=())

    @property
    def closure(self) -> float | None:
        """Mean alpha at the largest factor over mean alpha at x1 (None without both)."""
        top = max(self.mean_alpha)
        if 1 not in self.mean_alpha or top == 1 or self.mean_alpha[1] <= 0:
            return None
        return self.mean_alpha[top] / self.mean_alpha[1]

    @property
    def closed(self) -> bool:
        closure = self.closure
        return closure is not None and closure >= CLOSURE_MIN and self.undersized <= UNDERSIZED_MAX

    def problems(self) -> list[str]:
        """What keeps the surface from counting as closed, one phrase each (empty when closed)."""
        out = []
        closure = self.closure
        if closure is None:
            out.append("closure unknown (needs x1 and a larger factor)")
        elif closure < CLOSURE_MIN:
            out.append(f"closure {closure:.2f} < {CLOSURE_MIN} (alpha x{max(self.mean_alpha)} / alpha x1)")
        if self.undersized > UNDERSIZED_MAX:
            out.append(f"{100 * self.undersized:.0f}% of surfels under half their pixel footprint")
        return out

    def to_json(self) -> dict:
        return {
            "closure": self.closure,
            "closed": self.closed,
            "mean_alpha": {f"x{s}": v for s, v in self.mean_alpha.items()},
            "coverage": {
                f"x{s}": {f"alpha>={a:g}": c for a, c in levels.items()} for s, levels in self.coverage.items()
            },
            "undersized_share": self.undersized,
            "size_ratio_median": self.size_ratio_median,
            "multiplier_at_low": self.multiplier_at_low,
            "multiplier_at_high": self.multiplier_at_high,
            "opacity_quantiles": {f"p{round(100 * q)}": v for q, v in self.opacity_quantiles.items()},
            "surfels": self.surfels,
            "problems": self.problems(),
        }


class ClosureAccumulator:
    """Adds up closure figures over scenes: alpha figures are pixel-weighted means, surfel shares are
    over every surfel added, quantiles over every opacity added.

    device: where the per-surfel values are kept and the figures computed. The host (default) for
    many scenes, whose surfels need not all fit on an accelerator beside the next scene; one
    scene's own device for `closure_metrics`, which then reads only the figures back."""

    def __init__(self, device: torch.device | str = "cpu") -> None:
        self.device = torch.device(device)
        self._alpha: dict[int, list[float]] = {}  # factor -> [sum alpha, pixels, count >= 0.5, count >= 0.9]
        self._ratios: list[Tensor] = []
        self._undersized: list[Tensor] = []
        self._opacities: list[Tensor] = []
        self._multipliers: list[Tensor] = []
        self._range: float | None = None

    def add_alpha(self, alphas: Mapping[int, Tensor]) -> None:
        """alphas: factor -> accumulated alpha maps [..., 1, H, W] of one scene's views at that factor."""
        for s, a in alphas.items():
            a = a.detach().float()
            row = self._alpha.setdefault(int(s), [0.0, 0.0] + [0.0] * len(COVERAGE_LEVELS))
            # the sum and the counts read at once (float64 holds the float32 sum and the counts exactly)
            sums = [a.sum(), *((a >= level).sum() for level in COVERAGE_LEVELS)]
            total, *counts = torch.stack([x.double() for x in sums]).tolist()
            row[0] += total
            row[1] += a.numel()
            for i, count in enumerate(counts):
                row[2 + i] += count

    def add_surfels(
        self,
        gaussians: Gaussians,
        footprints: Tensor,
        multipliers: Tensor | None = None,
        multiplier_range: float | None = None,
    ) -> None:
        """Unbatched surfels with their pixel footprints [N] (`pixel_footprints`) and, for model
        outputs, their scale multipliers [N, 2] and the clamp's r."""
        if footprints.shape != (len(gaussians),):
            raise SurfSplatInputError(f"footprints: expected [{len(gaussians)}], got {tuple(footprints.shape)}")
        smallest = gaussians.scales.detach().float().min(-1).values
        keep = self.device
        self._ratios.append((smallest / footprints.clamp_min(1e-12)).to(keep))
        self._undersized.append(undersized(gaussians, footprints).to(keep))
        self._opacities.append(gaussians.opacities.detach().float().flatten().to(keep))
        if multipliers is not None:
            if multiplier_range is None:
                raise SurfSplatInputError("multiplier_range: needed with multipliers (the clamp's r)")
            self._multipliers.append(multipliers.detach().float().flatten().to(keep))
            self._range = float(multiplier_range)

    def report(self) -> ClosureMetrics:
        if not self._alpha or not self._ratios:
            raise SurfSplatInputError("closure: nothing was added (alpha maps and surfels are both needed)")
        mean_alpha = {s: r[0] / r[1] for s, r in sorted(self._alpha.items())}
        coverage = {s: {lvl: r[2 + i] / r[1] for i, lvl in enumerate(COVERAGE_LEVELS)} for s, r in self._alpha.items()}
        ratios = torch.cat(self._ratios)
        opacities = torch.cat(self._opacities)
        q = torch.tensor(OPACITY_QUANTILES, device=self.device)
        quantiles = torch.quantile(_subsample(opacities), q) if opacities.numel() else torch.full_like(q, float("nan"))
        low = high = None
        if self._multipliers:
            at_low, at_high = at_bounds(torch.cat(self._multipliers), self._range)
            low, high = float(at_low.float().mean()), float(at_high.float().mean())
        return ClosureMetrics(
            mean_alpha=mean_alpha,
            coverage=dict(sorted(coverage.items())),
            undersized=float(torch.cat(self._undersized).float().mean()) if ratios.numel() else 0.0,
            opacity_quantiles={float(a): float(b) for a, b in zip(OPACITY_QUANTILES, quantiles)},
            multiplier_at_low=low,
            multiplier_at_high=high,
            surfels=int(ratios.numel()),
            size_ratio_median=float(_subsample(ratios).median()) if ratios.numel() else float("nan"),
            factors=tuple(sorted(mean_alpha)),
        )


def _subsample(values: Tensor, limit: int = 4_000_000) -> Tensor:
    """torch.quantile refuses very large inputs; an evenly strided subset keeps quantiles exact enough."""
    return values if values.numel() <= limit else values[:: values.numel() // limit + 1]


@torch.inference_mode()
def closure_metrics(
    gaussians: Gaussians,
    cameras: Cameras,
    width: int,
    height: int,
    factors: Sequence[int] = (1, 2, 4),
    *,
    source_cameras: Cameras | None = None,
    views: Tensor | None = None,
    multipliers: Tensor | None = None,
    multiplier_range: float | None = None,
    mode: Literal["surfel", "ewa"] = "surfel",
    backend: str = "auto",
) -> ClosureMetrics:
    """Closure of unbatched surfels seen from `cameras` (width x height at x1) at every factor.

    source_cameras: the cameras the surfels were predicted from (default `cameras`), whose pixel
    footprints judge the surfels' size; views: [N] which of them predicted each surfel (None: the
    finest that sees it); multipliers [N, 2] and multiplier_range: the adapter's scale multipliers
    and clamp, for the share at each bound.
    """
    from ..render import render

    if 1 not in factors:
        raise SurfSplatInputError(f"factors: closure compares with x1, got {tuple(factors)}")
    acc = ClosureAccumulator(gaussians.means.device)  # one scene: its figures computed where it is
    alphas = {}
    for s in sorted(set(int(f) for f in factors)):
        out = render(
            gaussians, cameras.scaled(float(s)), width * s, height * s, mode=mode, alpha_threshold=None, backend=backend
        )
        alphas[s] = out.alpha
    acc.add_alpha(alphas)
    source = source_cameras if source_cameras is not None else cameras
    acc.add_surfels(gaussians, pixel_footprints(gaussians, source, width, height, views), multipliers, multiplier_range)
    return acc.report()


def format_closure_table(rows: Mapping[str, ClosureMetrics]) -> str:
    """A markdown table: one row per model or scene set."""
    factors = sorted({s for m in rows.values() for s in m.mean_alpha})
    head = (
        ["", "closure"]
        + [f"alpha x{s}" for s in factors]
        + [f"cov>=0.5 x{s}" for s in factors]
        + ["undersized", "mult at 1/r", "mult at r", "opacity p10/p50/p90", "closed"]
    )
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def pct(v: float | None) -> str:
        return "n/a" if v is None else f"{100 * v:.0f}%"

    for name, m in rows.items():
        q = m.opacity_quantiles
        cells = (
            [name, "n/a" if m.closure is None else f"{m.closure:.3f}"]
            + [f"{m.mean_alpha[s]:.3f}" if s in m.mean_alpha else "" for s in factors]
            + [f"{m.coverage[s][0.5]:.3f}" if s in m.coverage else "" for s in factors]
            + [pct(m.undersized), pct(m.multiplier_at_low), pct(m.multiplier_at_high)]
            + ["/".join(f"{v:.2f}" for v in q.values()), "yes" if m.closed else "no"]
        )
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
