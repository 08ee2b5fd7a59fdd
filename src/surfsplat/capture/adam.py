"""Selective (sparse) Adam: a step updates only the rows of the surfels the step's views saw.

    optimizer = SelectiveAdam(groups)
    loss.backward()
    optimizer.step(visible)          # visible [N] bool: rows updated; the others keep parameters and moments

Taming 3DGS (Mallick et al. 2024, Sec. 4.3) and gsplat's `SelectiveAdam` (`gsplat.optimizers`): with one
view a step most surfels of a large scene are out of view, and dense Adam still moves them by their
decaying momentum and rewrites their moments. Here a row is visible where any fitted tensor's gradient
row is not zero (`visible_rows`): the renderer composited the surfel into some pixel of the step's views
(a surfel that reaches no pixel has an exactly zero gradient; the compiled CPU backend's tile lists stay
inside it, and the gradient says the same without another output). Each tensor's step count is the
fit's (bias corrections as dense Adam's, gsplat's choice), so a row visible at every step follows dense
Adam exactly.

Written here rather than taken from gsplat: gsplat's is a CUDA kernel (`selective_adam_update`) and an
optional dependency; this is the same update in torch ops, on any device. The state is torch Adam's
("step", "exp_avg", "exp_avg_sq" per tensor), so the densification's row appends and removals
(`fit._Free.append` / `keep`) follow it unchanged.
"""

from __future__ import annotations

import torch
from torch import Tensor


class SelectiveAdam(torch.optim.Optimizer):
    """Adam (no weight decay, no amsgrad) whose step updates the rows `visible` selects."""

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        super().__init__(params, {"lr": lr, "betas": betas, "eps": eps})

    @torch.no_grad()
    def step(self, visible: Tensor | None = None) -> None:  # visible: [N] bool (None: every row)
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                if not state:
                    state["step"] = torch.zeros((), dtype=torch.float32)
                    state["exp_avg"] = torch.zeros_like(p)
                    state["exp_avg_sq"] = torch.zeros_like(p)
                state["step"] += 1
                # torch's single-tensor Adam, term for term (so an every-step-visible row is its row exactly)
                t = float(state["step"])
                step_size = group["lr"] / (1 - beta1**t)
                correction2_sqrt = (1 - beta2**t) ** 0.5
                rows = slice(None) if visible is None else visible.nonzero()[:, 0]
                grad, m, v = p.grad[rows], state["exp_avg"][rows], state["exp_avg_sq"][rows]
                m.lerp_(grad, 1 - beta1)
                v.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
                denominator = (v.sqrt() / correction2_sqrt).add_(group["eps"])
                if visible is None:  # views of the state and the tensor: updated in place
                    p.addcdiv_(m, denominator, value=-step_size)
                else:  # copies of the visible rows, written back
                    state["exp_avg"][rows] = m
                    state["exp_avg_sq"][rows] = v
                    p[rows] = p[rows].addcdiv(m, denominator, value=-step_size)


def visible_rows(tensors: list[Tensor]) -> Tensor:
    """[N] bool: the rows where any of the tensors' gradients is not zero (each tensor [N, ...])."""
    seen = None
    for t in tensors:
        if t.grad is None:
            continue
        rows = t.grad.reshape(len(t.grad), -1).ne(0).any(1)
        seen = rows if seen is None else seen | rows
    if seen is None:
        raise ValueError("visible_rows: no tensor has a gradient")
    return seen
