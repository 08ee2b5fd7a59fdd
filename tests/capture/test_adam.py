"""Selective Adam: the rows a step did not see keep their parameters and moments bit for bit, the rows
seen at every step follow torch's Adam exactly, and a step's visible rows are the surfels its view
composited."""

from __future__ import annotations

import pytest
import torch

import surfsplat
from surfsplat.capture import OptimizeConfig, optimize_on_views
from surfsplat.capture.adam import SelectiveAdam, visible_rows
from surfsplat.capture.starts import StartConfig
from surfsplat.render import render
from surfsplat.utils.checks import SurfSplatInputError

from .test_capture import SIZE, _two_views_of_a_textured_plane


def _tensors(seed: int):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(40, 3, generator=g), torch.randn(40, 3, 4, generator=g), torch.randn(40, generator=g)]


def test_unseen_rows_keep_parameters_and_moments_and_seen_rows_are_dense_adams():
    rates = [1e-2, 3e-3, 0.05]
    sparse = [t.clone().requires_grad_(True) for t in _tensors(0)]
    dense = [t.clone().requires_grad_(True) for t in _tensors(0)]
    selective = SelectiveAdam([{"params": [t], "lr": r} for t, r in zip(sparse, rates)])
    reference = torch.optim.Adam([{"params": [t], "lr": r} for t, r in zip(dense, rates)], foreach=False)
    always = torch.arange(40) < 10  # rows 0..9 are seen at every step
    g = torch.Generator().manual_seed(1)
    for step in range(6):
        seen = always | (torch.rand(40, generator=g) < 0.5)
        grads = [torch.randn(t.shape, generator=g) for t in sparse]
        for t, d, grad in zip(sparse, dense, grads):
            t.grad = grad * seen.reshape(-1, *[1] * (grad.dim() - 1))  # unseen rows: an exactly zero gradient
            d.grad = grad.clone()
        assert torch.equal(visible_rows(sparse), seen)
        before = [(t.detach().clone(), {k: v.clone() for k, v in selective.state[t].items()}) for t in sparse]
        selective.step(visible_rows(sparse))
        reference.step()
        for t, (value, state) in zip(sparse, before):
            hidden = ~seen
            assert torch.equal(t.detach()[hidden], value[hidden])
            for key in ("exp_avg", "exp_avg_sq"):
                if state:  # the first step creates the moments: zero rows stay zero
                    assert torch.equal(selective.state[t][key][hidden], state[key][hidden])
                else:
                    assert not selective.state[t][key][hidden].any()
            assert int(selective.state[t]["step"]) == step + 1
    for t, d in zip(sparse, dense):
        assert torch.equal(t.detach()[always], d.detach()[always])  # bit for bit
        for key in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(selective.state[t][key][always], reference.state[d][key][always])


def test_every_row_visible_is_torch_adam():
    sparse = [t.clone().requires_grad_(True) for t in _tensors(2)]
    dense = [t.clone().requires_grad_(True) for t in _tensors(2)]
    selective, reference = SelectiveAdam(sparse, lr=0.1), torch.optim.Adam(dense, lr=0.1, foreach=False)
    g = torch.Generator().manual_seed(3)
    for _ in range(4):
        for t, d in zip(sparse, dense):
            t.grad = torch.randn(t.shape, generator=g)
            d.grad = t.grad.clone()
        selective.step()
        reference.step()
    assert all(torch.equal(t, d) for t, d in zip(sparse, dense))


def test_a_step_sees_the_surfels_its_view_composited():
    plane, cameras, photos = _two_views_of_a_textured_plane()
    behind = plane.means[:5] - 10 * cameras.c2w[0, :3, 2]  # far behind the first camera: in no view
    far = surfsplat.Gaussians(
        torch.cat((plane.means, behind)),
        torch.cat((plane.quats, plane.quats[:5])),
        torch.cat((plane.scales, plane.scales[:5])),
        torch.cat((plane.opacities * 0.7, plane.opacities[:5])),  # fainter than the photos: a fit moves them
        torch.cat((plane.sh, plane.sh[:5])),
    )
    means = far.means.clone().requires_grad_(True)
    out = render(surfsplat.Gaussians(means, far.quats, far.scales, far.opacities, far.sh), cameras[:1], SIZE, SIZE)
    (out.color - photos[:1]).abs().mean().backward()
    seen = visible_rows([means])
    assert not seen[len(plane) :].any() and seen[: len(plane)].float().mean() > 0.5
    # in a fit with selective Adam the surfels no view saw keep their values exactly
    config = OptimizeConfig(
        steps=6, views_per_step=1, adam="selective", densify=None, levels=(), sh_degree=2,
        start=StartConfig(kind="network", budget=10**6),
    )  # fmt: skip
    fitted, stats = optimize_on_views(far, cameras, photos, SIZE, SIZE, config)
    assert stats["kept"] == 1.0 and stats["steps"] == 6
    assert torch.equal(fitted.means[len(plane) :], far.means[len(plane) :])
    assert (
        torch.equal(fitted.sh[len(plane) :, :, :1], far.sh[len(plane) :]) and not fitted.sh[len(plane) :, :, 1:].any()
    )
    assert not torch.equal(fitted.means[: len(plane)], far.means[: len(plane)])


def test_the_optimizer_choice_is_checked():
    with pytest.raises(SurfSplatInputError, match="optimize.adam"):
        OptimizeConfig(adam="sparse")
