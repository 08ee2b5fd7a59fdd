"""Validation during training: PSNR, SSIM, LPIPS at the input resolution and HRRC at x2 / x4.

Each rank scores its own share of the held-out scenes in evaluation mode (tau_alpha 0.001), with
`surfsplat.metrics.HrrcEvaluator`: renders at s times the resolution (K scaled by s) against the
ground truth upsampled bicubically (paper Sec. 3.6). Per-image sums and counts are then reduced
over ranks, so every rank returns the same means, equal to a single process scoring all scenes.
Where the held-out views carry true depth (synthetic rooms), the predicted context depth is scored
too (abs rel, delta < 1.25). Closure (`surfsplat.metrics.closure`) is reported from the same renders:
the mean alpha at each factor and closure = alpha at the largest / alpha at x1, the share of surfels
under half their pixel footprint and of scale multipliers at the clamp's lower bound.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from ..export.figures import image_grid
from ..geometry.pixels import pixel_footprints, views_of_pixels
from ..metrics.closure import at_bounds, undersized
from ..metrics.depth import depth_metrics
from ..metrics.hrrc import METRICS, HrrcConfig, HrrcEvaluator, upsample_ground_truth
from ..metrics.lpips import Lpips, LpipsUnavailable
from ..model.decoder import render_views
from ..render.types import Backend, RenderMode
from .data import TrainBatch
from .distributed import DistributedContext, all_reduce_sum

_DEPTH_METRICS = ("abs_rel", "delta1")


@torch.no_grad()
def validate(
    model: nn.Module,
    samples: Sequence[TrainBatch],
    ctx: DistributedContext,
    *,
    mode: RenderMode,
    backend: Backend = "auto",
    lpips: Lpips | LpipsUnavailable,
    factors: tuple[int, ...] = (1, 2, 4),
    grids: dict[int, Tensor] | None = None,
    multiplier_range: float | None = None,
) -> dict[str, float]:
    """Means over every rank's held-out scenes: "x{s}/{metric}" for each factor, "depth/..." where
    true depth exists, and "num_images". LPIPS is absent when its weights are (see `lpips`).

    `grids`, when given, receives a picture per factor s of this rank's first scene and its first
    target view, the truth the metric compares with (upsampled) left of the render at s times the
    resolution (`surfsplat.export.figures.image_grid`: [3, s*H + 4, 2*s*W + 6], 2-pixel white borders).
    `multiplier_range`: the adapter's clamp r of the scale multipliers (None: not reported)."""
    was_training = model.training
    model.eval()
    evaluator = HrrcEvaluator(lpips, HrrcConfig(factors=factors))
    depth_sums = torch.zeros(len(_DEPTH_METRICS), dtype=torch.float64)
    depth_count = 0
    # Per factor: alpha sum and pixels; then undersized surfels, multipliers at 1/r, surfels.
    closure_sums = torch.zeros(2 * len(factors) + 3, dtype=torch.float64)
    for i, batch in enumerate(samples):
        batch = batch.to(ctx.device)
        context, target = batch.context, batch.target
        prediction = model(context.images, context.cameras(), context.near, context.far)
        _, _, h, w = target.shape
        renders = {}
        for s in factors:
            views = render_views(
                prediction.gaussians.to(torch.float32),
                target.cameras().scaled(float(s)),
                w * s,
                h * s,
                mode=mode,
                alpha_threshold=prediction.alpha_threshold,
                backend=backend,
            )
            renders[s] = views.color[0]
            k = factors.index(s)
            closure_sums[2 * k] += float(views.alpha[0].double().sum())
            closure_sums[2 * k + 1] += views.alpha[0].numel()
            if grids is not None and i == 0:
                truth = upsample_ground_truth(target.images[0], s, evaluator.config.upsample)
                grids[s] = image_grid([[truth[0], views.color[0, 0]]])
        evaluator.add_scene(f"{ctx.rank}:{i}:{batch.scenes[0]}", target.images[0], renders)
        closure_sums[-3:] += _surfel_counts(prediction, context.cameras(), h, w, multiplier_range)
        if context.depths is not None:
            errors = depth_metrics(prediction.depths[0].float(), context.depths[0, :, 0].float())
            keep = errors.num_valid > 0
            depth_sums += torch.stack([getattr(errors, m)[keep].double().sum().cpu() for m in _DEPTH_METRICS])
            depth_count += int(keep.sum())
    model.train(was_training)

    # Sums and counts per (factor, metric), reduced over ranks; a rank without scenes adds zeros.
    names = [(s, m) for s in factors for m in METRICS]
    sums = torch.zeros(len(names) + len(_DEPTH_METRICS) + 2, dtype=torch.float64)
    if samples:
        report = evaluator.report()
        for k, (s, m) in enumerate(names):
            value = report.mean[s][m]
            sums[k] = 0.0 if value is None else value * report.num_images
        sums[-2] = report.num_images
    sums[len(names) : len(names) + len(_DEPTH_METRICS)] = depth_sums
    sums[-1] = depth_count
    closure_total = all_reduce_sum(closure_sums, ctx)
    total = all_reduce_sum(sums, ctx)
    num_images, num_depth = float(total[-2]), float(total[-1])
    out: dict[str, float] = {"num_images": num_images}
    if num_images > 0:
        for k, (s, m) in enumerate(names):
            if m == "lpips" and isinstance(lpips, LpipsUnavailable):
                continue
            out[f"x{s}/{m}"] = float(total[k]) / num_images
    if num_depth > 0:
        for k, m in enumerate(_DEPTH_METRICS):
            out[f"depth/{m}"] = float(total[len(names) + k]) / num_depth
    if num_images > 0:
        alpha = {s: float(closure_total[2 * k] / closure_total[2 * k + 1]) for k, s in enumerate(factors)}
        out.update({f"closure/alpha_x{s}": a for s, a in alpha.items()})
        if 1 in alpha and max(factors) > 1 and alpha[1] > 0:
            out["closure/closure"] = alpha[max(factors)] / alpha[1]
        surfels = float(closure_total[-1])
        out["closure/undersized"] = float(closure_total[-3]) / surfels
        if multiplier_range is not None:
            out["closure/multiplier_at_low"] = float(closure_total[-2]) / surfels
    return out


def _surfel_counts(prediction, cameras, height: int, width: int, multiplier_range: float | None) -> Tensor:
    """[undersized surfels, multipliers at 1/r (either axis), surfels] of the batch's first scene."""
    gaussians = prediction.gaussians.select(0)
    v = prediction.depths.shape[1]
    footprints = pixel_footprints(gaussians, cameras[:v], width, height, views_of_pixels(v, height, width))
    small = float(undersized(gaussians, footprints).sum())
    at_low = 0.0
    if multiplier_range is not None:  # either axis at 1/r
        at_low = float(at_bounds(prediction.adapter_output.scales_mul[0], multiplier_range)[0].any(-1).sum())
    return torch.tensor([small, at_low, float(len(gaussians))], dtype=torch.float64)
