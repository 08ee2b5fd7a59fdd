"""3DGS-MCMC's densification for surfels (Kheradmand et al. 2024): a fixed budget, dead surfels relocated.

    strategy = MCMC(MCMCConfig(), extent, len(surfels), device)
    ... each step: loss = loss + strategy.penalty(free); loss.backward(); optimizer.step()
    strategy.step(free, optimizer, step, done, generator)   # relocate / add on its schedule, then the noise

What it does (the paper's Algorithm 1; gsplat's `strategy.MCMCStrategy` with `ops.relocate`,
`ops.sample_add`, `ops.inject_noise_to_position` and its trainer's regularizers), as a plan of the
one fit loop:
* Every `every` steps from `start` to `stop` (shares of the fit): the dead surfels (opacity <=
  `min_opacity`, 0.005) are moved onto live ones drawn in proportion to their opacity; then
  `growth` (5 %) more surfels are drawn the same way and added, up to `cap_max` in all. A surfel
  drawn N - 1 times becomes N surfels that together render as it did (the paper's Eq. 9, gsplat's
  `relocation` CUDA op, written here in PyTorch from the formula: `relocation`): opacity
  1 - (1 - o)^(1/N) each, and the scales times o / sum_{i=1}^{N} sum_{k=0}^{i-1} C(i-1, k) (-1)^k
  o'^(k+1) / sqrt(k+1). Nothing is ever removed: the count only grows, to `cap_max`.
* After every step the positions get noise: eps ~ N(0, I), times sigmoid(-k (o - t)) (k 100,
  t 0.995: gsplat's op_sigmoid(1 - o), so only nearly transparent surfels move far), times the
  surfel's covariance, times the position rate of the step times `noise_lr` (5e5).
* The loss gains `opacity_reg` mean(o) + `scale_reg` mean(s) (0.01 each, gsplat's trainer), which
  drive unneeded surfels to die and so to be relocated.

Surfels: the covariance of the noise is the surfel's own, R diag(s_u^2, s_v^2, 0) R^T, so the noise
moves a surfel within its tangent plane and never along its normal (a 3D Gaussian's third axis is
its thinnest; a surfel's is zero). Eq. 9 scales the two tangent scales by the one coefficient, as
gsplat scales all three (the third is zero and stays so).

Adam's moments: the rows a relocation or an addition rewrote start again at zero - the drawn
sources, whose opacity and scales changed, and the dead rows now holding their copies (gsplat zeroes
the sources and leaves the dead rows' moments from their previous life; a relocated row is a new
surfel, so here it starts as one). Added rows start at zero (`_Free.append`); no other row is touched.

Why not gsplat's class: as `densify.py` says of `DefaultStrategy` - one optimizer per tensor and
3-vector log-scales, and its relocation is a CUDA op; the draws here come from the fit's seeded
generator on the host, so a fit repeats bit for bit on any device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from ..utils.checks import SurfSplatInputError

N_MAX = 51  # copies of one surfel at most in one relocation (gsplat's binomial table, n_max 51)


@dataclass(frozen=True)
class MCMCConfig:
    """3DGS-MCMC's schedule and constants; when it runs is given in shares of the fit, as `DensifyConfig`."""

    start: float = 500 / 30_000  # relocation begins (gsplat: refine_start_iter 500 of 30,000)
    stop: float = 25_000 / 30_000  # ... and ends (gsplat: refine_stop_iter 25,000)
    every: int = 100  # steps between relocations (gsplat: refine_every)
    cap_max: int = 50_000  # surfels at most (gsplat: cap_max; the figures of docs/optimize.md were measured at it)
    growth: float = 0.05  # each relocation adds this share of the count, up to cap_max (gsplat: 1.05x)
    min_opacity: float = 0.005  # dead at or below this opacity (gsplat: min_opacity)
    noise_lr: float = 5e5  # the position noise's factor on the position rate (gsplat: noise_lr)
    noise_k: float = 100.0  # steepness of the noise's opacity gate (gsplat's op_sigmoid k)
    noise_t: float = 0.995  # ... and its centre, on 1 - o (gsplat's op_sigmoid x0)
    opacity_reg: float = 0.01  # weight of mean(opacity) in the loss (gsplat's trainer with MCMC)
    scale_reg: float = 0.01  # weight of mean(tangent scale) in the loss (gsplat's trainer with MCMC)

    def __post_init__(self) -> None:
        if not 0 <= self.start <= self.stop <= 1:
            raise SurfSplatInputError(f"mcmc: expected 0 <= start <= stop <= 1, got {self.start}, {self.stop}")
        if self.every < 1:
            raise SurfSplatInputError(f"mcmc every: expected at least 1 step, got {self.every}")
        if self.cap_max < 1:
            raise SurfSplatInputError(f"mcmc cap_max: expected at least 1 surfel, got {self.cap_max}")
        if not 0 <= self.growth <= 1:
            raise SurfSplatInputError(f"mcmc growth: expected a share in [0, 1], got {self.growth}")
        if not 0 <= self.min_opacity < 1:
            raise SurfSplatInputError(f"mcmc min_opacity: expected an opacity in [0, 1), got {self.min_opacity}")
        for name in ("noise_lr", "opacity_reg", "scale_reg"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise SurfSplatInputError(f"mcmc {name}: expected >= 0, got {getattr(self, name)}")


def relocation(opacities: Tensor, scales: Tensor, copies: Tensor) -> tuple[Tensor, Tensor]:
    """The paper's Eq. 9: the opacity [M] and scales [M, S] of each of `copies` [M] (N >= 1) surfels that
    replace one of opacity o and scales s, so that together they render as it did:
    o' = 1 - (1 - o)^(1/N), s' = s o / sum_{i=1}^{N} sum_{k=0}^{i-1} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1).
    N is clamped to [1, N_MAX] as gsplat's kernel does; computed in float64."""
    n = copies.clamp(1, N_MAX).to(torch.float64)
    o = opacities.to(torch.float64)
    new = 1 - (1 - o).pow(1 / n)
    # sum_{i=1}^{N} sum_{k<i} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1) = sum_k (-1)^k o'^(k+1) / sqrt(k+1) sum_{i=k+1}^{N} C(i-1, k),
    # and sum_{i=k+1}^{N} C(i-1, k) = C(N, k+1) (the hockey-stick identity)
    k = torch.arange(N_MAX, dtype=torch.float64, device=o.device)  # [K]
    log_binom = torch.lgamma(n[:, None] + 1) - torch.lgamma(k + 2) - torch.lgamma(n[:, None] - k)
    binom = torch.where(k[None] + 1 <= n[:, None], log_binom.exp().round(), torch.zeros_like(log_binom))
    terms = binom * (-1.0) ** k * new[:, None].pow(k + 1) / (k + 1).sqrt()
    coefficient = o / terms.sum(-1)
    return new.to(opacities.dtype), (scales.to(torch.float64) * coefficient[:, None]).to(scales.dtype)


class MCMC:
    """The schedule and the operations of one fit's 3DGS-MCMC (module docstring)."""

    def __init__(self, config: MCMCConfig, extent: float, n: int, device: torch.device) -> None:
        self.config, self.extent = config, extent
        self.history: list[dict] = []

    def wants_absgrad(self, done: float) -> bool:
        return False

    def observe(self, *args, **kwargs) -> None:
        """Nothing to accumulate: relocation reads the opacities alone."""

    def penalty(self, free) -> Tensor | None:
        """The opacity and scale regularizers of the step's loss (gsplat's trainer)."""
        cfg = self.config
        t = free.tensors
        return cfg.opacity_reg * torch.sigmoid(t["logits"]).mean() + cfg.scale_reg * t["log_scales"].exp().mean()

    def step(self, free, optimizer: torch.optim.Optimizer, step: int, done: float, generator: torch.Generator) -> None:
        """After the optimizer's step `step` (counted from 0) at progress `done`: relocation and growth on
        their schedule, then the position noise (every step)."""
        cfg = self.config
        if cfg.start <= done < cfg.stop and (step + 1) % cfg.every == 0:
            relocated = self.relocate(free, optimizer, generator)
            added = self.add(free, optimizer, generator)
            self.history.append(
                {"step": step + 1, "relocated": relocated, "added": added, "after": len(free.tensors["means"])}
            )
        self.inject_noise(free, optimizer, generator)

    @torch.no_grad()
    def relocate(self, free, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> int:
        """Move the dead surfels onto live ones drawn in proportion to opacity; returns how many moved."""
        t = free.tensors
        opacity = torch.sigmoid(t["logits"].detach())
        dead = opacity <= self.config.min_opacity
        n_dead = int(dead.sum())  # one host read per relocation
        if n_dead == 0 or n_dead == len(dead):
            return 0
        dead_rows = dead.nonzero().squeeze(-1)
        alive_rows = (~dead).nonzero().squeeze(-1)
        sources = alive_rows[_draw(opacity[alive_rows], n_dead, generator)]
        self._share(free, optimizer, sources)
        for tensor in t.values():
            tensor[dead_rows] = tensor[sources]
        moved = torch.cat((sources, dead_rows))
        for tensor in t.values():
            _zero_rows(optimizer, tensor, moved)
        return n_dead

    @torch.no_grad()
    def add(self, free, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> int:
        """Add `growth` of the count (up to cap_max) as copies of surfels drawn in proportion to opacity."""
        t = free.tensors
        n = len(t["means"])
        target = min(self.config.cap_max, int((1 + self.config.growth) * n))
        count = max(0, target - n)
        if count == 0:
            return 0
        opacity = torch.sigmoid(t["logits"].detach())
        sources = _draw(opacity, count, generator)
        self._share(free, optimizer, sources)
        for tensor in t.values():
            _zero_rows(optimizer, tensor, sources)
        free.append(optimizer, {name: tensor.detach()[sources] for name, tensor in t.items()})
        return count

    def _share(self, free, optimizer, sources: Tensor) -> None:
        """Each drawn surfel's opacity and scales as one of its copies (Eq. 9): drawn m times, it becomes
        m + 1 surfels (itself and m copies)."""
        t = free.tensors
        copies = torch.bincount(sources, minlength=len(t["means"]))[sources] + 1
        opacity = torch.sigmoid(t["logits"].detach()[sources])
        new_opacity, new_scales = relocation(opacity, t["log_scales"].detach()[sources].exp(), copies)
        eps = torch.finfo(torch.float32).eps
        new_opacity = new_opacity.clamp(min=self.config.min_opacity, max=1 - eps)  # gsplat's clamp
        t["logits"][sources] = torch.logit(new_opacity)
        t["log_scales"][sources] = new_scales.log()

    @torch.no_grad()
    def inject_noise(self, free, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> None:
        """eps ~ N(0, I) times the opacity gate, the surfel's tangent covariance, the step's position rate
        and noise_lr, added to the positions (gsplat's `inject_noise_to_position`)."""
        cfg = self.config
        t = free.tensors
        rate = next(g["lr"] for g in optimizer.param_groups if g["name"] == "means")
        opacity = torch.sigmoid(t["logits"].detach())
        gate = torch.sigmoid(-cfg.noise_k * (opacity - (1 - cfg.noise_t)))  # op_sigmoid(1 - o)
        means = t["means"]
        eps = torch.randn(means.shape, generator=generator, dtype=torch.float32).to(means)
        covariance = tangent_covariances(t["quats"].detach(), t["log_scales"].detach().exp())
        noise = (covariance @ (eps * (gate * rate * cfg.noise_lr)[:, None])[..., None])[..., 0]
        means.add_(noise)


def tangent_covariances(quats: Tensor, scales: Tensor) -> Tensor:
    """[N, 3, 3] R diag(s_u^2, s_v^2, 0) R^T of surfels (quaternions w, x, y, z, any norm; tangent scales [N, 2])."""
    w, x, y, z = F.normalize(quats, dim=-1).unbind(-1)
    u = torch.stack((1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)), -1)
    v = torch.stack((2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)), -1)
    su, sv = scales[:, :1, None] ** 2, scales[:, 1:2, None] ** 2
    return su * u[:, :, None] * u[:, None, :] + sv * v[:, :, None] * v[:, None, :]


def _draw(weights: Tensor, n: int, generator: torch.Generator) -> Tensor:
    """n indices drawn with replacement in proportion to `weights`, on the host's seeded generator (the
    same draws on every device), returned on the weights' device."""
    drawn = torch.multinomial(weights.detach().to("cpu", torch.float64), n, replacement=True, generator=generator)
    return drawn.to(weights.device)


def _zero_rows(optimizer: torch.optim.Optimizer, tensor: Tensor, rows: Tensor) -> None:
    state = optimizer.state.get(tensor)
    if not state:
        return
    for key in ("exp_avg", "exp_avg_sq"):
        if key in state:
            state[key][rows] = 0
