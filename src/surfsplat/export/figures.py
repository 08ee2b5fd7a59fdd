"""Pictures for reports: image grids and line charts, written without a plotting library.

grid = image_grid([[gt, render_x1], [depth, normal]], size=(128, 128))   # [3, 2*128+pad, ...]
write_png("grid.png", grid)
svg = line_chart({"loss": [(step, value), ...]}, log_y=True)             # an SVG document
"""

from __future__ import annotations

import html
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from ..utils import atomic
from ..utils.checks import SurfSplatInputError

# Colours of the chart's series, in order (a colour-blind-safe palette).
SERIES_COLOURS = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9")


def image_grid(
    rows: Sequence[Sequence[Tensor | None]],  # rows of [3 or 1, h, w] images in [0, 1]; None = empty cell
    size: tuple[int, int] | None = None,  # (H, W) of every cell; default: the largest image
    padding: int = 2,
    background: float = 1.0,
) -> Tensor:
    """One [3, H_total, W_total] picture of the images laid out in rows.

    Images of other sizes are resampled to the cell with nearest neighbours, so an x1 render shown
    beside an x4 render keeps its pixels visible instead of being smoothed into a fake x4 image.
    """
    if not rows or not any(rows):
        raise SurfSplatInputError("rows: expected at least one image")
    images = [im for row in rows for im in row if im is not None]
    if not images:
        raise SurfSplatInputError("rows: expected at least one image")
    for k, im in enumerate(images):
        if not isinstance(im, Tensor) or im.ndim != 3 or im.shape[0] not in (1, 3):
            raise SurfSplatInputError(
                f"rows: image {k} must be a [3 or 1, H, W] tensor, got {getattr(im, 'shape', type(im).__name__)}"
            )
    if size is None:
        size = (max(im.shape[1] for im in images), max(im.shape[2] for im in images))
    h, w = size
    cols = max(len(row) for row in rows)
    out = torch.full((3, len(rows) * (h + padding) + padding, cols * (w + padding) + padding), float(background))
    for i, row in enumerate(rows):
        for j, im in enumerate(row):
            if im is None:
                continue
            cell = im.detach().float().cpu().clamp(0, 1).expand(3, -1, -1)
            if tuple(cell.shape[1:]) != (h, w):
                cell = F.interpolate(cell[None], size=(h, w), mode="nearest-exact")[0]
            top, left = padding + i * (h + padding), padding + j * (w + padding)
            out[:, top : top + h, left : left + w] = cell
    return out


def line_chart(
    series: Mapping[str, Sequence[tuple[float, float]]],
    title: str = "",
    x_label: str = "step",
    y_label: str = "",
    log_y: bool = False,
    size: tuple[int, int] = (640, 320),
) -> str:
    """An SVG line chart of named (x, y) series with axes, ticks and a legend."""
    clean = {
        name: [(float(x), float(y)) for x, y in pts if math.isfinite(x) and math.isfinite(y) and (y > 0 or not log_y)]
        for name, pts in series.items()
    }
    clean = {k: v for k, v in clean.items() if v}
    if not clean:
        raise SurfSplatInputError(
            "series: expected at least one finite point" + (" (log_y needs positive values)" if log_y else "")
        )
    width, height = size
    left, right, top, bottom = 64, 16, 28 if title else 12, 40
    xs = [x for pts in clean.values() for x, _ in pts]
    ys = [math.log10(y) if log_y else y for pts in clean.values() for _, y in pts]
    x0, x1 = min(xs), max(xs)
    y0, y1 = min(ys), max(ys)
    if x1 == x0:
        x0, x1 = x0 - 1, x1 + 1
    if y1 == y0:
        y0, y1 = y0 - 0.5, y1 + 0.5
    pad = 0.05 * (y1 - y0)
    y0, y1 = y0 - pad, y1 + pad

    def px(x: float) -> float:
        return left + (x - x0) / (x1 - x0) * (width - left - right)

    def py(y: float) -> float:
        v = math.log10(y) if log_y else y
        return top + (1 - (v - y0) / (y1 - y0)) * (height - top - bottom)

    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" viewBox="0 0 {width} {height}" '
        'font-family="sans-serif" font-size="11">',
        f'<rect width="{width}" height="{height}" fill="white"/>',
        f'<rect x="{left}" y="{top}" width="{width - left - right}" height="{height - top - bottom}" fill="none" stroke="#888"/>',
    ]
    if title:
        parts.append(f'<text x="{width / 2}" y="16" text-anchor="middle" font-size="13">{html.escape(title)}</text>')
    for t in _ticks(x0, x1):
        parts.append(
            f'<line x1="{px(t):.1f}" x2="{px(t):.1f}" y1="{height - bottom}" y2="{height - bottom + 4}" stroke="#888"/>'
        )
        parts.append(f'<text x="{px(t):.1f}" y="{height - bottom + 16}" text-anchor="middle">{_fmt(t)}</text>')
    for t in _ticks(y0, y1):
        value = 10**t if log_y else t
        y = top + (1 - (t - y0) / (y1 - y0)) * (height - top - bottom)
        parts.append(f'<line x1="{left - 4}" x2="{width - right}" y1="{y:.1f}" y2="{y:.1f}" stroke="#eee"/>')
        parts.append(f'<text x="{left - 6}" y="{y + 4:.1f}" text-anchor="end">{_fmt(value)}</text>')
    parts.append(
        f'<text x="{(left + width - right) / 2}" y="{height - 6}" text-anchor="middle">{html.escape(x_label)}</text>'
    )
    if y_label:
        parts.append(
            f'<text x="14" y="{(top + height - bottom) / 2}" text-anchor="middle" '
            f'transform="rotate(-90 14 {(top + height - bottom) / 2})">{html.escape(y_label + (" (log)" if log_y else ""))}</text>'
        )
    # The legend sits in the top right corner on a white box as wide as its longest name (about
    # 6.5 px per character at this font size), so no name runs past the frame.
    legend_x = width - right - 34 - 6.5 * max(len(name) for name in clean)
    parts.append(
        f'<rect x="{legend_x - 4:.1f}" y="{top + 3}" width="{width - right - legend_x:.1f}" '
        f'height="{14 * len(clean) + 4}" fill="white" fill-opacity="0.85"/>'
    )
    for k, pts in enumerate(clean.values()):
        colour = SERIES_COLOURS[k % len(SERIES_COLOURS)]
        coords = " ".join(f"{px(x):.1f},{py(y):.1f}" for x, y in pts)
        parts.append(f'<polyline fill="none" stroke="{colour}" stroke-width="1.5" points="{coords}"/>')
    for k, name in enumerate(clean):
        colour = SERIES_COLOURS[k % len(SERIES_COLOURS)]
        ly = top + 14 + 14 * k
        parts.append(
            f'<line x1="{legend_x:.1f}" x2="{legend_x + 20:.1f}" y1="{ly - 4}" y2="{ly - 4}" stroke="{colour}" stroke-width="2"/>'
        )
        parts.append(f'<text x="{legend_x + 24:.1f}" y="{ly}">{html.escape(name)}</text>')
    parts.append("</svg>")
    return "\n".join(parts) + "\n"


def smooth(values: Sequence[tuple[float, float]], window: int) -> list[tuple[float, float]]:
    """A trailing moving average of (x, y) points over `window` points (noisy per-step losses)."""
    if window < 1:
        raise SurfSplatInputError(f"window: expected >= 1, got {window}")
    out, acc = [], []
    for x, y in values:
        acc.append(y)
        if len(acc) > window:
            acc.pop(0)
        out.append((x, sum(acc) / len(acc)))
    return out


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write a text file (SVG, HTML, CSV, JSON) atomically: a temporary name, then a rename."""
    return atomic.write_text(path, text)


def _ticks(lo: float, hi: float, target: int = 5) -> list[float]:
    """Round tick positions (1, 2, 5 x 10^k spacing) inside [lo, hi]."""
    span = hi - lo
    raw = span / target
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw)
    first = math.ceil(lo / step) * step
    return [first + k * step for k in range(int((hi - first) / step) + 1)]


def _fmt(value: float) -> str:
    if value == 0:
        return "0"
    if abs(value) >= 1e4 or abs(value) < 1e-3:
        return f"{value:.0e}"
    return f"{value:.4g}"
