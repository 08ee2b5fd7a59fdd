"""Zoom scores: is a scene right at every zoom? Held-out views rendered smaller and larger than the size it
was fitted at, each scored against what that render should look like.

    scores = zoom_scores(lambda cams, w, h: render(g, cams, w, h, antialiased=True), cameras, photos, W, H)
    scores.to_dict()      # {"x1": dB, "x1/2": ..., "x1/4": ..., "x1/2_vs_render": ..., "x2": ..., "coverage": ...}

- x1/s (s = 2, 4): the render at (W / s) x (H / s), K' = diag(1/s, 1/s, 1) K, against the photos area-averaged
  down by s (what a camera of 1/s the resolution would have recorded) and against the x1 render
  area-averaged down (what a consistent renderer gives: a render at 1/s of the size should be the full
  render seen through larger pixels). The second isolates the renderer's behaviour from the fit's error.
  Beside them, the x1 render averaged down against the photos averaged down: what a consistent renderer
  would score at x1/s (the target of the x1/s figure).
- xs (s = 2, 4): the render at s times the size against the photos upsampled bicubically and clamped
  (the paper's HRRC protocol, `hrrc.upsample_ground_truth`).
- coverage: the mean alpha at each scale, and at x4 relative to x1 (a surface that opens into holes
  when magnified loses alpha).
- colour shift: the mean of (render - reference) over pixels and channels at x1/s, against the photos
  averaged down (a washed-out small render has a positive shift).

Sizes not divisible by s are cropped at the bottom and right to the largest multiple of s (which
leaves K unchanged), so every small pixel covers exactly s x s pixels of the x1 grid. PSNR is
`metrics.psnr` (per image on [0, 1]-clipped images), then the mean over views.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry.cameras import Cameras
from ..utils.checks import SurfSplatInputError, check_tensor
from .hrrc import UpsampleMode, upsample_ground_truth
from .image import psnr


@dataclass
class ZoomScores:
    """Mean PSNR over views at each zoom (dB) and the coverage figures (see the module docstring)."""

    x1: float
    down: dict[int, float] = field(default_factory=dict)  # s -> x1/s against the photos averaged down
    down_vs_render: dict[int, float] = field(default_factory=dict)  # s -> x1/s against the x1 render averaged down
    averaged: dict[int, float] = field(default_factory=dict)  # s -> the x1 render averaged down against the photos
    up: dict[int, float] = field(default_factory=dict)  # s -> xs against the photos upsampled
    coverage: dict[str, float] = field(default_factory=dict)  # "x1", "x1/2", "x4", ...: mean alpha at that scale
    colour_shift: dict[int, float] = field(default_factory=dict)  # s -> mean (x1/s render - photos averaged down)
    upsample: str = "bicubic"

    def to_dict(self) -> dict:
        out: dict = {"x1": self.x1}
        for s in sorted(self.down):
            out[f"x1/{s}"] = self.down[s]
            out[f"x1/{s}_vs_render"] = self.down_vs_render[s]
            out[f"x1/{s}_target"] = self.averaged[s]
            out[f"x1/{s}_colour_shift"] = self.colour_shift[s]
        for s in sorted(self.up):
            out[f"x{s}"] = self.up[s]
        out["coverage"] = dict(self.coverage)
        if "x4" in self.coverage and self.coverage.get("x1", 0) > 0:
            out["coverage_x4_over_x1"] = self.coverage["x4"] / self.coverage["x1"]
        out["upsample"] = self.upsample
        return out

    def line(self) -> str:
        """One line for a report: every figure, in dB."""
        parts = [f"x1 {self.x1:.2f}"]
        parts += [
            f"x1/{s} {self.down[s]:.2f} (the x1 render averaged down: {self.averaged[s]:.2f}; the two compared: "
            f"{self.down_vs_render[s]:.2f})"
            for s in self.down
        ]
        parts += [f"x{s} {self.up[s]:.2f}" for s in sorted(self.up)]
        line = "held-out PSNR by zoom: " + ", ".join(parts) + " dB"
        if "x4" in self.coverage and self.coverage.get("x1", 0) > 0:
            line += f"; mean alpha x4 / x1 {self.coverage['x4'] / self.coverage['x1']:.3f}"
        return line


def area_down(images: Tensor, factor: int) -> Tensor:
    """[..., C, H, W] -> [..., C, H // s, W // s]: each pixel the mean of its s x s block (bottom and right
    rows beyond a multiple of s dropped)."""
    h, w = images.shape[-2] // factor * factor, images.shape[-1] // factor * factor
    lead = images.shape[:-3]
    flat = images[..., :h, :w].reshape(-1, *images.shape[-3:-2], h, w)
    return F.avg_pool2d(flat, factor).reshape(*lead, *images.shape[-3:-2], h // factor, w // factor)


def zoom_scores(
    render: Callable[[Cameras, int, int], object],  # (cameras, width, height) -> RenderOutput (colour, alpha)
    cameras: Cameras,  # [V] K in pixels of width x height
    images: Tensor,  # [V, 3, height, width] the photos in [0, 1]
    width: int,
    height: int,
    *,
    down: Sequence[int] = (2, 4),
    up: Sequence[int] = (2, 4),
    upsample: UpsampleMode = "bicubic",
) -> ZoomScores:
    """Render the views at x1, x1/s for s in `down` and xs for s in `up`, one view at a time (bounded
    memory), and score them (see the module docstring)."""
    check_tensor("images", images, (len(cameras), 3, height, width))
    for s in (*down, *up):
        if not isinstance(s, int) or isinstance(s, bool) or s < 2:
            raise SurfSplatInputError(f"zoom factors: expected integers >= 2, got {s!r}")
        if s in down and (width < s or height < s):
            raise SurfSplatInputError(f"zoom factors: x1/{s} of {width}x{height} has no pixel")
    truth = images.clamp(0, 1)

    def at(scale: float, w: int, h: int, v: int):
        return render(cameras[v].scaled(scale), w, h)

    views = range(len(cameras))
    x1 = [at(1.0, width, height, v) for v in views]
    colour = torch.cat([o.color for o in x1]).clamp(0, 1)
    coverage = {"x1": float(torch.cat([o.alpha for o in x1]).mean())}
    scores = ZoomScores(x1=float(psnr(colour, truth.to(colour)).mean()), upsample=upsample)
    for s in down:
        w, h = width // s, height // s
        outs = [at(1.0 / s, w, h, v) for v in views]
        small = torch.cat([o.color for o in outs]).clamp(0, 1)
        coverage[f"x1/{s}"] = float(torch.cat([o.alpha for o in outs]).mean())
        photos = area_down(truth.to(small), s)
        averaged = area_down(colour, s)
        scores.down[s] = float(psnr(small, photos).mean())
        scores.down_vs_render[s] = float(psnr(small, averaged).mean())
        scores.averaged[s] = float(psnr(averaged, photos).mean())
        scores.colour_shift[s] = float((small - photos).mean())
    for s in up:
        big, alphas = [], []
        for v in views:
            out = at(float(s), width * s, height * s, v)
            reference = upsample_ground_truth(truth[v : v + 1].to(out.color), s, upsample)
            big.append(psnr(out.color.clamp(0, 1), reference))
            alphas.append(out.alpha.mean())
        scores.up[s] = float(torch.cat(big).mean())
        coverage[f"x{s}"] = float(torch.stack(alphas).mean())
    scores.coverage = coverage
    return scores
