"""Densification and pruning of the surfels during a fit: 3DGS's adaptive density control, for surfels.

    strategy = Densify(DensifyConfig(), extent)
    ... each step, after loss.backward():
    strategy.observe(free, cameras_of_the_step, width, height)
    strategy.step(free, optimizer, step)      # clones, splits, prunes and resets on their schedule

What it does (3DGS Sec. 5, `densify_and_prune`; 2DGS keeps it for surfels; gsplat's
`DefaultStrategy`), with every threshold in 3DGS's units:
* The screen-space gradient: each surfel's gradient of the loss with respect to its projected centre
  in normalized device coordinates, the norm accumulated over the views that saw it and averaged.
  It is read from the gradient of the mean: holding the surfel's camera depth z, a pixel move of the
  centre is a camera-frame move of (z / f_x, z / f_y), so dL/dc_px = (R_cw dL/dmu)_xy z / f and
  dL/dc_ndc = dL/dc_px * (W / 2, H / 2). Every backend differentiates the means, so every backend
  reports it, the same way; with one view a step (the schedule's default, as 3DGS) it is exactly the
  per-view gradient 3DGS accumulates.
* Every `every` steps from `start` to `stop`: surfels whose average exceeds `grad_threshold`
  (0.0002) are cloned when small (largest tangent scale <= `percent_dense` x the scene extent) and
  split in two when large: two samples of the surfel's own Gaussian (in its tangent plane), scales
  divided by 1.6, as 3DGS and 2DGS do. Then the surfels below `prune_opacity` (0.005) and, once the
  first opacity reset has passed, those larger than 0.1 x the extent in the world are removed.
* Every `reset_every` steps the opacities are set to at most 0.01 (3DGS's reset), so surfels the
  photos do not need fade and are pruned.
* `budget` bounds the count, 3DGS-MCMC's idea of a fixed cost: when cloning and splitting would pass
  it, only the surfels with the highest gradients grow.
* `absgrad` (AbsGS, Ye et al. 2024; gsplat's `DefaultStrategy(absgrad=True)`): the screen gradient of a
  view is instead the sum over its pixels of each pixel's own |dL_p/dc| (per axis, then the norm in
  NDC, as gsplat), which the renderer accumulates in its backward (`render(..., absgrad=True)`):
  shares of opposite sign no longer cancel, so large surfels over texture, whose plain gradient
  averages out, grow too. The threshold is then `abs_grad_threshold` (0.0008, gsplat's advice with
  absgrad). gsplat multiplies each view's sums by the number of views the step rendered (its loss
  averages over them), and so does this. For surfels the per-pixel share is taken of gsplat's 2DGS
  densification gradient (`gradient_2dgs`, z dL/dT[:2, 2]), not of its `means2d`, whose 2DGS kernel
  differentiates only the low-pass branch; the SH colour's dependence on the view direction is left
  out (as in gsplat; the plain gradient above includes it).
Adam's moments follow every clone, split and removal (new rows start with zero moments, as in
3DGS's `cat_tensors_to_optimizer`), and the reset zeroes the opacity moments.

Why not gsplat's `strategy.DefaultStrategy`: it is the field's maintained implementation and plain
PyTorch, but it wants one optimizer per parameter and 3-vector log-scales (its split samples a 3D
Gaussian), and reads the screen gradient from a `means2d` tensor the renderer returns; the fit loop
here keeps one Adam with a group per tensor and two tangent scales, and takes its gradient from the
means, which every backend (the compiled CPU kernels included) already differentiates. It is also an
optional dependency, while the optimizer is not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry.cameras import Cameras
from ..utils.checks import SurfSplatInputError


@dataclass(frozen=True)
class DensifyConfig:
    """3DGS's adaptive density control. When it runs is given in shares of the fit (its progress: the
    share of the steps run, or of a time budget spent), so one configuration serves any length."""

    start: float = 0.25  # densification begins (3DGS: step 500 of 30,000; OpenSplat: 500 of 2,000)
    stop: float = 0.5  # ... and ends (3DGS: 15,000 of 30,000)
    # steps between densifications (3DGS: densification_interval 100 of 30,000 steps): 50, so that a fit of
    # 1,500 steps grows in 8 rounds, not 4 (DTU scan 24 held out: 20.20 -> 20.72 dB; 25 overgrew: 19.63)
    every: int = 50
    reset_every: float | None = None  # share of the fit between opacity resets (3DGS: 0.1; None: never)
    grad_threshold: float = 0.0002  # mean NDC screen-space gradient above which a surfel grows (3DGS)
    percent_dense: float = 0.01  # clone below, split above this share of the scene extent (3DGS)
    prune_opacity: float = 0.005  # surfels below this opacity are removed (3DGS: min_opacity)
    max_world_size: float = 0.1  # after the first reset, surfels larger than this share of the extent go (3DGS)
    reset_opacity: float = 0.01  # opacities capped at this by a reset (3DGS)
    split_factor: float = 1.6  # a split's two surfels have the scales / this (3DGS: 0.8 * N with N = 2)
    # surfels at most: growth past it keeps the highest gradients (a bound on a step's cost). 30,000 from the
    # fern curve (docs/optimize.md, "The budget"): 50,000 / 40,000 / 35,000 / 30,000 surfels held out 25.45 /
    # 25.38 / 25.28 / 25.24 dB in 344 / 318 / 292 / 279 CPU s for the whole fit
    budget: int = 30_000
    absgrad: bool = False  # AbsGS: the screen gradient sums each pixel's |dL_p/dc| (module docstring)
    abs_grad_threshold: float = 0.0008  # ... and its threshold (gsplat's grow_grad2d advice with absgrad)

    def __post_init__(self) -> None:
        if not 0 <= self.start <= self.stop <= 1:
            raise SurfSplatInputError(f"densify: expected 0 <= start <= stop <= 1, got {self.start}, {self.stop}")
        if self.every < 1:
            raise SurfSplatInputError(f"densify every: expected at least 1 step, got {self.every}")
        if self.reset_every is not None and not 0 < self.reset_every <= 1:
            raise SurfSplatInputError(
                f"densify reset_every: expected a share in (0, 1] or None, got {self.reset_every}"
            )
        if self.budget < 1:
            raise SurfSplatInputError(f"densify budget: expected at least 1 surfel, got {self.budget}")
        if self.grad_threshold <= 0 or self.abs_grad_threshold <= 0:
            raise SurfSplatInputError(
                f"densify grad_threshold, abs_grad_threshold: expected > 0, got {self.grad_threshold}, "
                f"{self.abs_grad_threshold}"
            )


def screen_gradients(
    means: Tensor,  # [N, 3] world
    grad: Tensor,  # [N, 3] dL/dmeans of one step
    cameras: Cameras,  # [C] the step's views
    width: int,
    height: int,
    absgrad: Tensor | None = None,  # [C, N, 2] per view the sums of |dL_p/dc| (`RenderOutput.absgrad`'s grad)
) -> tuple[Tensor, Tensor]:
    """Each surfel's NDC screen-space gradient norm for the step's views ([N], summed over the views that
    see it) and how many of them see it ([N]): the centre in front of the camera and inside the image.
    With several views a step the mean's gradient is their sum, so the norm is that of the summed
    gradient, counted once per seeing view (module docstring). With `absgrad`, each view's own
    absolute sums in NDC, times the number of views (gsplat), replace it."""
    norms = torch.zeros(len(means), dtype=means.dtype, device=means.device)
    seen = torch.zeros_like(norms)
    c2w = cameras.c2w.to(means)
    K = cameras.K.to(means)
    for c in range(len(cameras)):
        R_cw = c2w[c, :3, :3].T
        camera_point = (means - c2w[c, :3, 3]) @ R_cw.T
        z = camera_point[:, 2]
        in_front = z > 1e-6
        zc = torch.where(in_front, z, torch.ones_like(z))
        px = K[c, 0, 0] * camera_point[:, 0] / zc + K[c, 0, 2]
        py = K[c, 1, 1] * camera_point[:, 1] / zc + K[c, 1, 2]
        visible = in_front & (px >= 0) & (px <= width) & (py >= 0) & (py <= height)
        if absgrad is None:
            g_cam = grad @ R_cw.T  # dL/d(camera point) = R_cw dL/dmu
            g_px = torch.stack((g_cam[:, 0] * zc / K[c, 0, 0], g_cam[:, 1] * zc / K[c, 1, 1]), -1)
        else:
            g_px = absgrad[c].to(means) * len(cameras)
        g_ndc = g_px * torch.tensor([width / 2, height / 2], dtype=means.dtype, device=means.device)
        norms += torch.where(visible, g_ndc.norm(dim=-1), torch.zeros_like(z))
        seen += visible.to(seen.dtype)
    return norms, seen


class Densify:
    """The running statistics and the schedule of one fit's densification (module docstring)."""

    def __init__(self, config: DensifyConfig, extent: float, n: int, device: torch.device) -> None:
        self.config, self.extent = config, extent
        self.grad_sum = torch.zeros(n, device=device)
        self.count = torch.zeros(n, device=device)
        self.resets = 0  # opacity resets so far
        self.history: list[dict] = []  # one entry per densification or reset

    def wants_absgrad(self, done: float) -> bool:
        """Whether the step at progress `done` needs the renderer's absolute screen gradient."""
        return self.config.absgrad and self.config.start <= done < self.config.stop

    def penalty(self, free) -> Tensor | None:
        """No term of its own in the loss."""
        return None

    def observe(
        self,
        means: Tensor,
        grad: Tensor,
        cameras: Cameras,
        width: int,
        height: int,
        done: float,
        absgrad: Tensor | None = None,
    ) -> None:
        """Accumulate the step's screen-space gradients (only while densification runs); `absgrad` [C, N, 2]
        is needed when the configuration's absgrad is on."""
        if not self.config.start <= done < self.config.stop:
            return
        if self.config.absgrad and absgrad is None:
            raise SurfSplatInputError("densify: absgrad is on, but the render gave no absolute screen gradient")
        use = absgrad.detach() if self.config.absgrad else None
        norms, seen = screen_gradients(means.detach(), grad.detach(), cameras, width, height, use)
        self.grad_sum += norms.to(self.grad_sum)
        self.count += seen.to(self.count)

    def step(self, free, optimizer: torch.optim.Optimizer, step: int, done: float, generator: torch.Generator) -> None:
        """Run what falls after `step` (counted from 0) at progress `done`."""
        cfg = self.config
        if cfg.start <= done < cfg.stop and (step + 1) % cfg.every == 0:
            self._grow_and_prune(free, optimizer, step + 1, generator)
        if cfg.reset_every is not None and done < cfg.stop and int(done / cfg.reset_every) > self.resets:
            self.resets = int(done / cfg.reset_every)
            self._reset_opacity(free, optimizer)
            self.history.append({"step": step + 1, "reset": self.resets})

    def _grow_and_prune(self, free, optimizer, iteration: int, generator: torch.Generator) -> None:
        cfg = self.config
        t = free.tensors
        average = self.grad_sum / self.count.clamp_min(1)
        grow = average >= (cfg.abs_grad_threshold if cfg.absgrad else cfg.grad_threshold)
        size = t["log_scales"].detach().exp().amax(-1)
        small = size <= cfg.percent_dense * self.extent
        n = len(size)
        room = max(0, cfg.budget - n)
        # a split adds one surfel (two replace one), a clone one: growth past the budget keeps the strongest
        if int(grow.sum()) > room:
            order = torch.argsort(torch.where(grow, average, torch.full_like(average, -1.0)), descending=True)
            keep = torch.zeros_like(grow)
            keep[order[:room]] = True
            grow &= keep
        clone, split = grow & small, grow & ~small
        before = n
        # new rows: clones (copies), then the splits' second halves; the split surfels themselves move
        # to their first sample and shrink in place, which keeps every row's Adam state where it is
        new: dict[str, Tensor] = {}
        index_clone = clone.nonzero().squeeze(-1)
        index_split = split.nonzero().squeeze(-1)
        if len(index_split):
            first, second = self._split_samples(t, index_split, generator)
        for name, tensor in t.items():
            rows = [tensor.detach()[index_clone]]
            if len(index_split):
                if name == "means":
                    rows.append(second)
                elif name == "log_scales":
                    rows.append(tensor.detach()[index_split] - math.log(cfg.split_factor))
                else:
                    rows.append(tensor.detach()[index_split])
            new[name] = torch.cat(rows)
        if len(index_split):
            with torch.no_grad():
                t["means"][index_split] = first
                t["log_scales"][index_split] -= math.log(cfg.split_factor)
            for name in t:  # the split surfels' moments restart, as their replacements' do in 3DGS
                _zero_state(optimizer, t[name], index_split)
        free.append(optimizer, new)
        # every statistic restarts after a densification (3DGS's densification_postfix)
        self.grad_sum = torch.zeros(len(free.tensors["means"]), device=self.grad_sum.device)
        self.count = torch.zeros_like(self.grad_sum)
        # prune: faint surfels, and after the first reset the ones too large in the world
        opacity = torch.sigmoid(free.tensors["logits"].detach())
        remove = opacity < cfg.prune_opacity
        if self.resets > 0:
            remove |= free.tensors["log_scales"].detach().exp().amax(-1) > cfg.max_world_size * self.extent
        removed = int(remove.sum())
        if removed and removed < len(remove):
            free.keep(optimizer, ~remove)
            self.grad_sum = self.grad_sum[~remove]
            self.count = self.count[~remove]
        self.history.append(
            {
                "step": iteration,
                "cloned": len(index_clone),
                "split": len(index_split),
                "pruned": removed,
                "before": before,
                "after": len(free.tensors["means"]),
            }
        )

    def _split_samples(self, t: dict[str, Tensor], index: Tensor, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """Two positions drawn from each surfel's own Gaussian in its tangent plane (3DGS's split, in 2D)."""
        quats = F.normalize(t["quats"].detach()[index], dim=-1)
        w, x, y, z = quats.unbind(-1)
        # the first two columns of the rotation: the tangent axes u, v in the world
        u = torch.stack((1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)), -1)
        v = torch.stack((2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)), -1)
        scales = t["log_scales"].detach()[index].exp()
        noise = torch.randn(2, len(index), 2, generator=generator).to(scales)
        offsets = noise[..., :1] * scales[:, :1] * u + noise[..., 1:] * scales[:, 1:] * v
        means = t["means"].detach()[index]
        return means + offsets[0], means + offsets[1]

    def _reset_opacity(self, free, optimizer) -> None:
        cap = torch.logit(torch.tensor(self.config.reset_opacity))
        logits = free.tensors["logits"]
        with torch.no_grad():
            logits.clamp_(max=float(cap))
        _zero_state(optimizer, logits, None)


def _zero_state(optimizer: torch.optim.Optimizer, tensor: Tensor, index: Tensor | None) -> None:
    """Zero Adam's moments of `tensor` (at the rows `index`, or all)."""
    state = optimizer.state.get(tensor)
    if not state:
        return
    for key in ("exp_avg", "exp_avg_sq"):
        if key in state:
            if index is None:
                state[key].zero_()
            else:
                state[key][index] = 0
