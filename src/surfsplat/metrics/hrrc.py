"""High-Resolution Rendering Consistency (paper Sec. 3.6, Eq. 13) and the paper's table layout.

HRRC renders each scene at s times the input resolution (K' = diag(s, s, 1) K, s = 2, 4) and
scores the render against the ground truth upsampled by s:
  HRRC_metric = metric(I_HR, up_s(I_GT)),   metric in {PSNR, SSIM, LPIPS}.
The paper upsamples bicubically. The release's code (`upsample_gt_img` in its model wrapper)
calls `F.interpolate(gt, size=(int(h * s), int(w * s)), mode="bilinear", align_corners=False)`
(no antialiasing, no clamp); `upsample="bilinear"` reproduces it. Both modes here use that call
with the mode swapped, then clamp to [0, 1]: torch's bicubic kernel (Keys, a = -0.75) overshoots
at edges and ground truth outside [0, 1] is not an image. Clamping a bilinear result is a no-op,
so the release's numbers are unchanged.

Aggregation follows the release: per image PSNR (both images clipped to [0, 1]), SSIM and LPIPS
(renders not clipped), then means. The release averages per-scene means; with the same number of
target views per scene (as in every evaluation index) that equals the mean over images used here.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry.cameras import Cameras
from ..utils.checks import SurfSplatInputError, check_tensor
from .image import psnr, ssim
from .lpips import Lpips, LpipsUnavailable

UpsampleMode = Literal["bicubic", "bilinear"]
UPSAMPLE_MODES: tuple[str, ...] = ("bicubic", "bilinear")
METRICS: tuple[str, ...] = ("psnr", "ssim", "lpips")


def upsample_ground_truth(images: Tensor, factor: int, mode: UpsampleMode = "bicubic") -> Tensor:
    """Ground truth for an s-times render: [..., C, H, W] -> [..., C, s H, s W], clamped to [0, 1].

    Pixel centres follow the project convention (align_corners=False): output pixel j samples
    the input at (j + 0.5) / s - 0.5. factor 1 returns the (clamped) images unchanged.
    """
    if not isinstance(factor, int) or isinstance(factor, bool) or factor < 1:
        raise SurfSplatInputError(f"factor: expected a positive integer, got {factor!r}")
    if mode not in UPSAMPLE_MODES:
        raise SurfSplatInputError(f"mode: expected one of {UPSAMPLE_MODES}, got {mode!r}")
    if not isinstance(images, Tensor) or images.ndim < 3:
        raise SurfSplatInputError(
            f"images: expected a [..., C, H, W] tensor, got {getattr(images, 'shape', type(images).__name__)}"
        )
    check_tensor("images", images, (None,) * images.ndim)
    if factor == 1:
        return images.clamp(0.0, 1.0)
    lead, (c, h, w) = images.shape[:-3], images.shape[-3:]
    flat = images.reshape(-1, c, h, w)
    up = F.interpolate(flat, size=(h * factor, w * factor), mode=mode, align_corners=False)
    return up.clamp(0.0, 1.0).reshape(*lead, c, h * factor, w * factor)


def render_at_scales(
    render: Callable[[Cameras, int, int], Tensor],
    cameras: Cameras,
    width: int,
    height: int,
    factors: Sequence[int] = (1, 2, 4),
) -> dict[int, Tensor]:
    """Call `render(cameras, width, height)` once per factor s with K scaled by s and s-times sizes.

    `render` returns [C, 3, H', W'] images for the given cameras and size (e.g. a closure over
    `surfsplat.render(gaussians, ...)` taking `.color`). Returns {s: image batch}.
    """
    out = {}
    for s in factors:
        if not isinstance(s, int) or s < 1:
            raise SurfSplatInputError(f"factors: expected positive integers, got {s!r}")
        out[s] = render(cameras.scaled(float(s)), width * s, height * s)
    return out


@dataclass(frozen=True)
class HrrcConfig:
    """How HRRC is measured."""

    factors: tuple[int, ...] = (1, 2, 4)  # 1 = standard metrics; 2 and 4 = the paper's HRRC
    upsample: UpsampleMode = "bicubic"  # the paper; "bilinear" = the release's code
    max_batch_pixels: int = 1024 * 1024  # views scored together per call: bounds x4 SSIM/LPIPS memory


@dataclass
class HrrcReport:
    """Means per factor (over images), per-scene means, and why LPIPS is missing if it is."""

    factors: tuple[int, ...]
    upsample: str
    base_size: tuple[int, int] | None  # (height, width) of the factor-1 images if all scenes agree
    mean: dict[int, dict[str, float | None]]  # factor -> metric -> mean over images
    per_scene: dict[str, dict[int, dict[str, float | None]]]
    num_images: int
    lpips_unavailable: str | None  # "LPIPS unavailable: <reason>", or None when LPIPS was computed

    def average(self) -> dict[str, float | None]:
        """The paper's "Average" columns: the plain mean of each metric over the factors."""
        out: dict[str, float | None] = {}
        for metric in METRICS:
            values = [self.mean[s][metric] for s in self.factors]
            out[metric] = None if any(v is None for v in values) else sum(values) / len(values)  # type: ignore[arg-type]
        return out

    def to_json(self) -> dict:
        """A JSON-ready dict: settings, means per factor, the average and every scene."""
        return {
            "factors": list(self.factors),
            "upsample": self.upsample,
            "num_images": self.num_images,
            "lpips_unavailable": self.lpips_unavailable,
            "mean": {f"x{s}": self.mean[s] for s in self.factors},
            "average": self.average(),
            "per_scene": {name: {f"x{s}": m[s] for s in self.factors} for name, m in self.per_scene.items()},
        }


@dataclass
class _Accumulator:
    values: dict[int, dict[str, list[float]]] = field(default_factory=dict)

    def add(self, factor: int, metric: str, values: Sequence[float]) -> None:
        self.values.setdefault(factor, {}).setdefault(metric, []).extend(values)

    def mean(self, factor: int, metric: str) -> float | None:
        values = self.values.get(factor, {}).get(metric)
        return None if not values else sum(values) / len(values)


class HrrcEvaluator:
    """Accumulates standard and HRRC metrics scene by scene (bounded memory), then reports.

    lpips: a loaded `Lpips`, or the `LpipsUnavailable` that says why there is none; the report
    then carries that message and no LPIPS number.
    """

    def __init__(self, lpips: Lpips | LpipsUnavailable, config: HrrcConfig = HrrcConfig()) -> None:
        if not isinstance(lpips, (Lpips, LpipsUnavailable)):
            raise SurfSplatInputError(f"lpips: expected Lpips or LpipsUnavailable, got {type(lpips).__name__}")
        if config.upsample not in UPSAMPLE_MODES:
            raise SurfSplatInputError(f"config.upsample: expected one of {UPSAMPLE_MODES}, got {config.upsample!r}")
        if not config.factors or any(not isinstance(s, int) or s < 1 for s in config.factors):
            raise SurfSplatInputError(f"config.factors: expected positive integers, got {config.factors!r}")
        if config.max_batch_pixels < 1:
            raise SurfSplatInputError(
                f"config.max_batch_pixels: expected a positive integer, got {config.max_batch_pixels}"
            )
        self.config = config
        self.lpips = lpips
        self._all = _Accumulator()
        self._scenes: dict[str, _Accumulator] = {}
        self._sizes: set[tuple[int, int]] = set()
        self._num_images = 0

    @torch.inference_mode()
    def add_scene(self, name: str, target: Tensor, renders: Mapping[int, Tensor]) -> dict[int, dict[str, float | None]]:
        """Score one scene. target: [V, 3, H, W]; renders: {s: [V, 3, s H, s W]} for every factor.

        Returns this scene's means per factor and metric.
        """
        if name in self._scenes:
            raise SurfSplatInputError(f"name: scene {name!r} was already added")
        check_tensor("target", target, ("V", 3, "H", "W"))
        views, _, h, w = target.shape
        missing = [s for s in self.config.factors if s not in renders]
        if missing:
            raise SurfSplatInputError(f"renders: scene {name!r} has no render for factors {missing}")
        scene = _Accumulator()
        for s in self.config.factors:
            pred = check_tensor(f"renders[{s}]", renders[s], (views, 3, h * s, w * s))
            chunk = max(1, self.config.max_batch_pixels // (h * s * w * s))
            for start in range(0, views, chunk):
                gt = upsample_ground_truth(target[start : start + chunk].to(pred.device), s, self.config.upsample)
                p = pred[start : start + chunk]
                # SSIM in float64 so the value equals scikit-image's to rounding.
                scores = {"psnr": psnr(p, gt), "ssim": ssim(p.double(), gt.double())}
                if isinstance(self.lpips, Lpips):
                    scores["lpips"] = self.lpips.to(p.device)(p.float(), gt.float())
                for metric, value in scores.items():
                    scene.add(s, metric, value.double().cpu().tolist())
                    self._all.add(s, metric, value.double().cpu().tolist())
        self._scenes[name] = scene
        self._sizes.add((h, w))
        self._num_images += views
        return {s: {m: scene.mean(s, m) for m in METRICS} for s in self.config.factors}

    def report(self) -> HrrcReport:
        """Means over every image added so far."""
        if self._num_images == 0:
            raise SurfSplatInputError("HRRC report: no scene was added")
        factors = self.config.factors
        return HrrcReport(
            factors=factors,
            upsample=self.config.upsample,
            base_size=next(iter(self._sizes)) if len(self._sizes) == 1 else None,
            mean={s: {m: self._all.mean(s, m) for m in METRICS} for s in factors},
            per_scene={
                n: {s: {m: acc.mean(s, m) for m in METRICS} for s in factors} for n, acc in self._scenes.items()
            },
            num_images=self._num_images,
            lpips_unavailable=str(self.lpips) if isinstance(self.lpips, LpipsUnavailable) else None,
        )


def evaluate_hrrc(
    scenes: Iterable[tuple[str, Tensor, Mapping[int, Tensor]]],
    lpips: Lpips | LpipsUnavailable,
    config: HrrcConfig = HrrcConfig(),
) -> HrrcReport:
    """Standard / x2 / x4 metrics of (name, target [V, 3, H, W], {s: render [V, 3, sH, sW]}) scenes."""
    evaluator = HrrcEvaluator(lpips, config)
    for name, target, renders in scenes:
        evaluator.add_scene(name, target, renders)
    return evaluator.report()


def _cell(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3f}"


def format_hrrc_table(rows: Mapping[str, HrrcReport]) -> str:
    """The paper's table layout (Tables 1-2) as aligned text, one row per method.

    Column groups: each factor named by its resolution when all reports agree on it (e.g.
    "256x256 (Standard)", "512x512 (HRRC)", "1024x1024 (HRRC)"), then "Average"; each group has
    PSNR, SSIM, LPIPS with 3 decimals. Missing LPIPS prints "n/a" and the reason under the table.
    """
    if not rows:
        raise SurfSplatInputError("rows: expected at least one method's report")
    reports = list(rows.values())
    factors = reports[0].factors
    if any(r.factors != factors for r in reports):
        raise SurfSplatInputError("rows: every report must use the same factors")
    sizes = {r.base_size for r in reports}
    base = sizes.pop() if len(sizes) == 1 else None

    def group_name(s: int) -> str:
        kind = "Standard" if s == 1 else "HRRC"
        return f"{base[0] * s}x{base[1] * s} ({kind})" if base is not None else f"x{s} ({kind})"

    groups = [group_name(s) for s in factors] + ["Average"]
    sub = ("PSNR↑", "SSIM↑", "LPIPS↓")
    body = []
    for report in reports:
        row = []
        for metrics in [report.mean[s] for s in factors] + [report.average()]:
            row.append(tuple(_cell(metrics[m]) for m in METRICS))
        body.append(row)
    cell_w = max(len(c) for c in (*sub, *(c for row in body for g in row for c in g)))
    group_w = max(3 * cell_w + 2, *(len(g) for g in groups))
    name_w = max(len("Method"), *(len(n) for n in rows))

    def fmt_group(cells: Sequence[str]) -> str:
        return " ".join(c.rjust(cell_w) for c in cells).rjust(group_w)

    lines = [
        " " * name_w + " | " + " | ".join(g.center(group_w) for g in groups),
        "Method".ljust(name_w) + " | " + " | ".join(fmt_group(sub) for _ in groups),
        "-" * name_w + "-+-" + "-+-".join("-" * group_w for _ in groups),
    ]
    for name, row in zip(rows, body):
        lines.append(name.ljust(name_w) + " | " + " | ".join(fmt_group(g) for g in row))
    upsample = ", ".join(sorted({r.upsample for r in reports}))
    lines.append(
        f"HRRC ground truth upsampled {upsample}; images per method: {', '.join(str(r.num_images) for r in reports)}"
    )
    lines += [f"{name}: {r.lpips_unavailable}" for name, r in rows.items() if r.lpips_unavailable is not None]
    return "\n".join(line.rstrip() for line in lines)
