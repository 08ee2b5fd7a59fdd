"""Densification: the screen-space gradient against its closed form, clone and split by 3DGS's rules,
Adam's moments following every row, the budget, the opacity reset, and a fit that grows."""

from __future__ import annotations

import math

import pytest
import torch

import surfsplat
from surfsplat.capture.densify import Densify, DensifyConfig, screen_gradients
from surfsplat.capture.fit import FitPlan, _Free, fit_on_views
from surfsplat.geometry.cameras import Cameras
from surfsplat.utils.checks import SurfSplatInputError

from .test_capture import SIZE, _two_views_of_a_textured_plane


def _camera(width: int = 40, height: int = 30) -> Cameras:
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]], dtype=torch.float64)  # a turn
    c2w[:3, 3] = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    K = torch.tensor([[50.0, 0.0, width / 2], [0.0, 45.0, height / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Cameras(c2w[None], K[None])


def test_screen_gradient_is_the_gradient_of_the_projected_centre_in_ndc():
    """For L = a . c_px of a pinhole projection c_px = (f x / z + c), whatever the depth's part in
    dL/dmu, the screen-space gradient is a exactly, times (W / 2, H / 2) in NDC."""
    camera = _camera()
    width, height = 40, 30
    g = torch.Generator().manual_seed(0)
    local = (torch.rand(6, 2, generator=g, dtype=torch.float64) - 0.5) * 0.6  # x / z, y / z: inside the view
    depth = 1 + torch.rand(6, generator=g, dtype=torch.float64)
    points = torch.cat((local * depth[:, None], depth[:, None]), -1)  # camera frame, inside the view
    means = (points @ camera.c2w[0, :3, :3].T + camera.c2w[0, :3, 3]).requires_grad_(True)
    a = torch.randn(6, 2, generator=g, dtype=torch.float64)
    R_cw = camera.c2w[0, :3, :3].T
    cam = (means - camera.c2w[0, :3, 3]) @ R_cw.T
    K = camera.K[0]
    px = K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2]
    py = K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]
    (a[:, 0] * px + a[:, 1] * py).sum().backward()
    norms, seen = screen_gradients(means.detach(), means.grad, camera, width, height)
    expected = torch.stack((a[:, 0] * width / 2, a[:, 1] * height / 2), -1).norm(dim=-1)
    assert torch.allclose(norms, expected, rtol=1e-10, atol=0)
    assert torch.equal(seen, torch.ones(6, dtype=torch.float64))
    # behind the camera or outside the image: not seen, no gradient counted
    away = means.detach().clone()
    away[0] = camera.c2w[0, :3, 3] - 2 * camera.c2w[0, :3, 2]  # 2 units behind
    away[1] = camera.c2w[0, :3, 3] + 1.0 * camera.c2w[0, :3, 2] + 5.0 * camera.c2w[0, :3, 0]  # far to the right
    norms, seen = screen_gradients(away, means.grad, camera, width, height)
    assert seen[:2].tolist() == [0.0, 0.0] and norms[:2].tolist() == [0.0, 0.0]


def _free_and_adam(n: int = 6, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    surfels = surfsplat.Gaussians(
        torch.randn(n, 3, generator=g),
        torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1),
        torch.tensor([[0.001, 0.002]] * (n // 2) + [[0.5, 0.2]] * (n - n // 2)),  # small ones first, then large
        torch.full((n,), 0.5),
        torch.randn(n, 3, 4, generator=g),
    )
    rates = dict.fromkeys(("means", "quats", "log_scales", "logits", "sh_dc", "sh_rest"), 1e-2)
    free = _Free(surfels, FitPlan(name="optimize", steps=10, rates=rates))
    adam = torch.optim.Adam(free.groups())
    for _ in range(3):  # moments that differ row by row
        adam.zero_grad()
        loss = sum((t * torch.randn(t.shape, generator=g)).sum() for t in free.tensors.values())
        loss.backward()
        adam.step()
    return free, adam


def _moments(free, adam, name):
    return adam.state[free.tensors[name]]["exp_avg"].clone()


def test_clone_small_split_large_and_adam_moments_follow_every_row():
    free, adam = _free_and_adam()
    config = DensifyConfig(start=0.0, stop=1.0, every=1, percent_dense=0.01, prune_opacity=0.0)
    strategy = Densify(config, extent=1.0, n=6, device=torch.device("cpu"))
    strategy.grad_sum = torch.tensor([1.0, 0.0, 1.0, 1.0, 0.0, 1.0])  # rows 0, 2 (small), 3, 5 (large) grow
    strategy.count = torch.ones(6)
    before = {k: t.detach().clone() for k, t in free.tensors.items()}
    moments = {k: _moments(free, adam, k) for k in free.tensors}
    strategy.step(free, adam, step=0, done=0.5, generator=torch.Generator().manual_seed(0))
    t = free.tensors
    assert len(t["means"]) == 6 + 2 + 2  # two clones, two splits' second halves
    for name in t:
        assert len(adam.state[t[name]]["exp_avg"]) == 10 and len(adam.state[t[name]]["exp_avg_sq"]) == 10
    # untouched rows (1, 4) keep their values and moments; the clones (6, 7) copy rows 0, 2 with zero moments
    for name in t:
        assert torch.equal(t[name][[1, 4]].detach(), before[name][[1, 4]])
        assert torch.equal(_moments(free, adam, name)[[1, 4]], moments[name][[1, 4]])
        assert torch.equal(t[name][[6, 7]].detach(), before[name][[0, 2]])
        assert torch.equal(_moments(free, adam, name)[6:], torch.zeros_like(_moments(free, adam, name)[6:]))
    # a split replaces the large surfel by two samples of it at 1/1.6 the scale, in its tangent plane
    shrink = math.log(1.6)
    for row, twin in ((3, 8), (5, 9)):
        assert torch.allclose(t["log_scales"][row].detach(), before["log_scales"][row] - shrink)
        assert torch.allclose(t["log_scales"][twin].detach(), before["log_scales"][row] - shrink)
        normal = surfsplat.Gaussians(
            before["means"][row : row + 1], before["quats"][row : row + 1],
            before["log_scales"][row : row + 1].exp(), torch.ones(1), torch.zeros(1, 3, 1),
        ).normals[0]  # fmt: skip
        for moved in (t["means"][row].detach(), t["means"][twin].detach()):
            offset = moved - before["means"][row]
            assert 0 < offset.norm() < 4 * float(before["log_scales"][row].exp().max())
            assert abs(float(offset @ normal)) < 1e-5  # in the plane
        assert torch.equal(_moments(free, adam, "means")[row], torch.zeros(3))
    assert strategy.history[-1] == {"step": 1, "cloned": 2, "split": 2, "pruned": 0, "before": 6, "after": 10}


def test_pruning_removes_faint_rows_with_their_moments_and_the_budget_keeps_the_strongest():
    free, adam = _free_and_adam()
    with torch.no_grad():
        free.tensors["logits"][[1, 4]] = -10.0  # opacity 4.5e-5: pruned
    moments = _moments(free, adam, "sh_dc")
    config = DensifyConfig(start=0.0, stop=1.0, every=1, budget=7)
    strategy = Densify(config, extent=1.0, n=6, device=torch.device("cpu"))
    strategy.grad_sum = torch.tensor([0.0, 0.0, 1.0, 3.0, 0.0, 2.0])
    strategy.count = torch.ones(6)
    strategy.step(free, adam, step=0, done=0.5, generator=torch.Generator().manual_seed(0))
    # room for one: only row 3 (the highest gradient) grows (a split), then rows 1 and 4 go
    assert strategy.history[-1]["split"] == 1 and strategy.history[-1]["cloned"] == 0
    assert strategy.history[-1]["pruned"] == 2 and len(free.tensors["means"]) == 5
    assert torch.equal(_moments(free, adam, "sh_dc")[[0, 1, 3]], moments[[0, 2, 5]])
    assert len(strategy.grad_sum) == 5 and float(strategy.grad_sum.abs().sum()) == 0.0


def test_opacity_reset_caps_opacities_and_restarts_their_moments():
    free, adam = _free_and_adam()
    strategy = Densify(DensifyConfig(start=0.9, stop=1.0, reset_every=0.25), 1.0, 6, torch.device("cpu"))
    strategy.step(free, adam, step=10, done=0.2, generator=torch.Generator())
    assert strategy.resets == 0
    strategy.step(free, adam, step=11, done=0.26, generator=torch.Generator())
    assert strategy.resets == 1 and strategy.history[-1] == {"step": 12, "reset": 1}
    assert float(torch.sigmoid(free.tensors["logits"].detach()).max()) <= 0.01 + 1e-6
    assert float(adam.state[free.tensors["logits"]]["exp_avg"].abs().max()) == 0.0


@pytest.mark.parametrize(
    ("fields", "needle"),
    [({"start": 0.6, "stop": 0.5}, "start <= stop"), ({"every": 0}, "every"), ({"budget": 0}, "budget")],
)
def test_densify_config_refuses_bad_values(fields, needle):
    with pytest.raises(SurfSplatInputError, match=needle):
        DensifyConfig(**fields)


def test_a_fit_with_densification_grows_where_the_photos_need_it_and_repeats_bit_for_bit():
    plane, cameras, photos = _two_views_of_a_textured_plane()
    sparse = plane.subset(torch.arange(0, len(plane), 16))  # every 16th surfel: holes the fit must fill
    sparse = surfsplat.Gaussians(sparse.means, sparse.quats, sparse.scales * 2, sparse.opacities, sparse.sh)
    rates = {"means": 1e-3, "quats": 1e-3, "log_scales": 5e-3, "logits": 0.05, "sh_dc": 2.5e-3, "sh_rest": 1e-4}
    plan = FitPlan(
        name="optimize", steps=60, rates=rates, views_per_step=1, loss="l1_dssim",
        densify=DensifyConfig(start=0.1, stop=0.8, every=10, grad_threshold=1e-4), extent=0.11,
    )  # fmt: skip
    fitted, stats = fit_on_views(sparse, cameras, photos, SIZE, SIZE, plan, alpha_threshold=None)
    grown = sum(h.get("cloned", 0) + h.get("split", 0) for h in stats["densify"])
    assert grown > 0 and len(fitted) > len(sparse)
    assert stats["mse_after"] < stats["mse_before"]
    again, _ = fit_on_views(sparse, cameras, photos, SIZE, SIZE, plan, alpha_threshold=None)
    assert torch.equal(again.means, fitted.means) and torch.equal(again.sh, fitted.sh)


def test_a_fit_with_its_progress_bar_shows_the_psnr_and_gives_the_same_surfels(caplog):
    plane, cameras, photos = _two_views_of_a_textured_plane()
    rates = {"sh_dc": 0.01, "logits": 0.05}
    plan = FitPlan(name="optimize", steps=60, rates=rates, views_per_step=1, loss="l1_dssim")
    quiet, _ = fit_on_views(plane, cameras, photos, SIZE, SIZE, plan)
    shown, stats = fit_on_views(plane, cameras, photos, SIZE, SIZE, plan, progress=True)
    assert torch.equal(shown.sh, quiet.sh) and stats["steps"] == 60
