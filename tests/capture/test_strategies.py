"""The densification strategies as plans of the one fit loop: 3DGS, AbsGS and 3DGS-MCMC.

MCMC's relocation against the paper's Eq. 9 in closed form, the count it conserves and the budget it
keeps, Adam's moments after every operation of every strategy, AbsGS's screen gradient, and seeded
fits of each strategy that repeat bit for bit."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

import surfsplat
from surfsplat.capture import OptimizeConfig
from surfsplat.capture import fit as fit_module
from surfsplat.capture.densify import Densify, DensifyConfig, screen_gradients
from surfsplat.capture.fit import FitPlan, fit_on_views
from surfsplat.capture.mcmc import MCMC, MCMCConfig, relocation, tangent_covariances
from surfsplat.capture.optimize import STRATEGIES
from surfsplat.utils.checks import SurfSplatInputError

from .test_capture import SIZE, _two_views_of_a_textured_plane
from .test_densify import _camera, _free_and_adam, _moments

CPU = torch.device("cpu")


def _gsplat_kernel_relocation(o: float, n: int) -> tuple[float, float]:
    """gsplat's `relocation_kernel` (RelocationCUDA.cu) line by line, in Python floats: the double sum."""
    new = 1.0 - (1.0 - o) ** (1.0 / n)
    denom = 0.0
    for i in range(1, n + 1):
        for k in range(i):
            denom += math.comb(i - 1, k) * ((-1.0) ** k / math.sqrt(k + 1)) * new ** (k + 1)
    return new, o / denom


def test_relocation_is_eq_9_in_closed_form_for_one_two_and_three_copies():
    o = torch.tensor([0.3, 0.8, 0.05], dtype=torch.float64)
    s = torch.tensor([[0.2, 0.1], [0.05, 0.3], [1.0, 2.0]], dtype=torch.float64)
    for n in (1, 2, 3):
        new_o, new_s = relocation(o, s, torch.full((3,), n))
        p = 1 - (1 - o) ** (1 / n)
        denominator = {
            1: p,  # N = 1: the surfel itself, coefficient 1
            2: 2 * p - p**2 / math.sqrt(2),
            3: 3 * p - 3 * p**2 / math.sqrt(2) + p**3 / math.sqrt(3),
        }[n]
        assert torch.allclose(new_o, p, rtol=1e-14, atol=0)
        assert torch.allclose(new_s, s * (o / denominator)[:, None], rtol=1e-12, atol=0)
    same_o, same_s = relocation(o, s, torch.ones(3, dtype=torch.long))
    assert torch.allclose(same_o, o, rtol=1e-14) and torch.allclose(same_s, s, rtol=1e-12)


def test_relocation_equals_gsplats_double_sum_up_to_its_table_and_clamps_past_it():
    o = torch.tensor([0.6, 0.2, 0.95, 0.01, 0.5], dtype=torch.float64)
    n = torch.tensor([4, 9, 17, 33, 51])
    new_o, new_s = relocation(o, torch.ones(5, 2, dtype=torch.float64), n)
    for j in range(5):
        ref_o, ref_coefficient = _gsplat_kernel_relocation(float(o[j]), int(n[j]))
        assert new_o[j].item() == pytest.approx(ref_o, rel=1e-12)
        assert new_s[j, 0].item() == pytest.approx(ref_coefficient, rel=1e-9)
    clamped = relocation(o[:1], torch.ones(1, 2, dtype=torch.float64), torch.tensor([80]))
    at_max = relocation(o[:1], torch.ones(1, 2, dtype=torch.float64), torch.tensor([51]))
    assert torch.equal(clamped[0], at_max[0]) and torch.equal(clamped[1], at_max[1])


def _state_aligned(free, adam) -> None:
    """Every fitted tensor is a parameter of Adam, and its moments have its shape."""
    params = {id(g["params"][0]): g["name"] for g in adam.param_groups}
    for name, tensor in free.tensors.items():
        assert params.get(id(tensor)) == name
        state = adam.state[tensor]
        assert state["exp_avg"].shape == tensor.shape and state["exp_avg_sq"].shape == tensor.shape, name


def test_mcmc_relocation_moves_the_dead_conserves_the_count_and_restarts_the_moved_rows_moments():
    free, adam = _free_and_adam(n=8, seed=2)
    with torch.no_grad():
        free.tensors["logits"][[1, 4, 6]] = -8.0  # opacity 3e-4: dead
        free.tensors["logits"][[0, 2, 3, 5, 7]] = torch.tensor([0.5, -1.0, 2.0, 0.0, 1.0])
    before = {k: t.detach().clone() for k, t in free.tensors.items()}
    moments = {k: _moments(free, adam, k) for k in free.tensors}
    strategy = MCMC(MCMCConfig(), 1.0, 8, CPU)
    generator = torch.Generator().manual_seed(0)
    assert strategy.relocate(free, adam, generator) == 3
    _state_aligned(free, adam)
    t = free.tensors
    assert len(t["means"]) == 8  # relocation conserves the count
    # each dead row now holds a copy of a live source, which shares its opacity and scale by Eq. 9
    sources = [
        int((before["means"][[0, 2, 3, 5, 7]] - t["means"][d].detach()).norm(dim=-1).argmin()) for d in (1, 4, 6)
    ]
    sources = [[0, 2, 3, 5, 7][s] for s in sources]
    copies = {s: sources.count(s) + 1 for s in sources}
    for dead, source in zip((1, 4, 6), sources):
        for name in t:
            assert torch.equal(t[name][dead].detach(), t[name][source].detach()), name
        o = torch.sigmoid(before["logits"][source : source + 1]).double()
        new_o, new_s = relocation(
            o, before["log_scales"][source : source + 1].exp().double(), torch.tensor([copies[source]])
        )
        assert torch.sigmoid(t["logits"][source]).item() == pytest.approx(new_o.item(), rel=1e-5)
        assert torch.allclose(t["log_scales"][source].detach().exp().double(), new_s[0], rtol=1e-5)
    moved = sorted(set(sources) | {1, 4, 6})
    untouched = [r for r in range(8) if r not in moved]
    assert untouched  # some live rows were not drawn
    for name in t:
        m = _moments(free, adam, name)
        assert float(m[moved].abs().max()) == 0.0 and float(adam.state[t[name]]["exp_avg_sq"][moved].abs().max()) == 0.0
        assert torch.equal(m[untouched], moments[name][untouched]), name
        assert torch.equal(t[name][untouched].detach(), before[name][untouched]), name


def test_mcmc_growth_adds_copies_with_zero_moments_and_never_passes_cap_max():
    free, adam = _free_and_adam(n=6, seed=3)
    moments = {k: _moments(free, adam, k) for k in free.tensors}
    strategy = MCMC(MCMCConfig(cap_max=8, growth=0.25), 1.0, 6, CPU)
    generator = torch.Generator().manual_seed(1)
    assert strategy.add(free, adam, generator) == 1  # int(1.25 * 6) = 7 <= 8
    _state_aligned(free, adam)
    assert strategy.add(free, adam, generator) == 1  # min(8, int(1.25 * 7)) = 8
    assert strategy.add(free, adam, generator) == 0  # at cap_max
    _state_aligned(free, adam)
    t = free.tensors
    assert len(t["means"]) == 8
    for name in t:
        m = _moments(free, adam, name)
        assert float(m[6:].abs().max()) == 0.0  # new rows start at zero
        changed = (m[:6] != moments[name]).reshape(6, -1).any(-1)
        assert bool((m[:6][changed] == 0).all())  # only the drawn sources were reset
    # a grown surfel copies a source's position exactly
    assert all(bool((t["means"][:6] == t["means"][r]).all(-1).any()) for r in (6, 7))


def test_mcmc_noise_stays_in_the_tangent_plane_and_spares_opaque_surfels():
    free, adam = _free_and_adam(n=6, seed=4)
    with torch.no_grad():
        free.tensors["logits"][:3] = -9.0  # nearly transparent: the gate is open
        free.tensors["logits"][3:] = 3.0  # opaque: sigmoid(-100 (0.95 - 0.005)) ~ 1e-41
    before = free.tensors["means"].detach().clone()
    strategy = MCMC(MCMCConfig(), 1.0, 6, CPU)
    strategy.inject_noise(free, adam, torch.Generator().manual_seed(5))
    moved = free.tensors["means"].detach() - before
    g = free.tensors
    normals = surfsplat.Gaussians(
        before, g["quats"].detach(), g["log_scales"].detach().exp(), torch.full((6,), 0.5), torch.zeros(6, 3, 1)
    ).normals
    assert float(moved[:3].norm(dim=-1).min()) > 0
    assert float((moved * normals).sum(-1).abs().max()) < 1e-6 * (1 + float(moved.norm(dim=-1).max()))
    assert float(moved[3:].abs().max()) == 0.0
    # exactly the formula: covariance @ (eps * gate * rate * noise_lr) with the same draws
    eps = torch.randn(6, 3, generator=torch.Generator().manual_seed(5))
    o = torch.sigmoid(g["logits"].detach())
    gate = torch.sigmoid(-100 * (o - 0.005))
    cov = tangent_covariances(g["quats"].detach(), g["log_scales"].detach().exp())
    expected = (cov @ (eps * (gate * 1e-2 * 5e5)[:, None])[..., None])[..., 0]
    assert torch.allclose(moved, expected, rtol=1e-5, atol=1e-7)


def test_absgs_reads_the_absolute_sums_in_ndc_and_grows_above_its_own_threshold():
    camera = _camera()
    width, height = 40, 30
    means = (
        torch.tensor([[0.1, 0.0, 2.0], [-0.2, 0.1, 1.5]], dtype=torch.float64) @ camera.c2w[0, :3, :3].T
    ) + camera.c2w[0, :3, 3]
    absolute = torch.tensor([[[3e-5, 4e-5], [1e-6, 0.0]]], dtype=torch.float64)  # [C = 1, N, 2] pixels
    norms, seen = screen_gradients(means, torch.zeros_like(means), camera, width, height, absolute)
    expected = (absolute[0] * torch.tensor([width / 2, height / 2], dtype=torch.float64)).norm(dim=-1)
    assert torch.allclose(norms, expected, rtol=1e-12) and torch.equal(seen, torch.ones(2, dtype=torch.float64))
    strategy = Densify(DensifyConfig(start=0.0, stop=1.0, absgrad=True), 1.0, 2, CPU)
    assert strategy.wants_absgrad(0.5)
    with pytest.raises(SurfSplatInputError, match="absgrad"):
        strategy.observe(means, torch.zeros_like(means), camera, width, height, 0.5)
    strategy.observe(means.float(), torch.zeros(2, 3), camera, width, height, 0.5, absolute.float())
    average = strategy.grad_sum / strategy.count
    assert float(average[0]) > 0.0008 > float(average[1])  # row 0 grows, row 1 does not
    assert not Densify(DensifyConfig(), 1.0, 2, CPU).wants_absgrad(0.3)


def test_the_registry_names_a_plan_of_the_one_loop_for_each_strategy():
    assert sorted(STRATEGIES) == ["3dgs", "absgs", "auto", "mcmc"]
    plans = {s: OptimizeConfig(strategy=s).plan(1.0, 5, 64 * 64).densify for s in STRATEGIES}
    assert plans["3dgs"] == DensifyConfig()
    assert plans["absgs"] == DensifyConfig(absgrad=True)
    assert plans["mcmc"] == MCMCConfig()
    assert OptimizeConfig(strategy="mcmc", densify=None).plan(1.0, 5, 64 * 64).densify is None
    with pytest.raises(SurfSplatInputError, match="--optimize-strategy"):
        OptimizeConfig(strategy="nope")


def _fit_plan(strategy: str) -> FitPlan:
    rates = {"means": 1e-3, "quats": 1e-3, "log_scales": 5e-3, "logits": 0.05, "sh_dc": 2.5e-3, "sh_rest": 1e-4}
    densify = {
        "3dgs": DensifyConfig(start=0.1, stop=0.8, every=10, grad_threshold=1e-4),
        "absgs": DensifyConfig(start=0.1, stop=0.8, every=10, absgrad=True, abs_grad_threshold=4e-4),
        "mcmc": MCMCConfig(start=0.1, stop=0.8, every=10, cap_max=400),
    }[strategy]
    return FitPlan(
        name="optimize", steps=50, rates=rates, views_per_step=1, loss="l1_dssim", densify=densify, extent=0.11
    )


@pytest.mark.parametrize("strategy", ["3dgs", "absgs", "mcmc"])
def test_a_seeded_fit_of_each_strategy_keeps_adams_rows_aligned_and_repeats_bit_for_bit(strategy, monkeypatch):
    plane, cameras, photos = _two_views_of_a_textured_plane()
    sparse = plane.subset(torch.arange(0, len(plane), 16))
    sparse = surfsplat.Gaussians(sparse.means, sparse.quats, sparse.scales * 2, sparse.opacities, sparse.sh)
    with torch.no_grad():
        sparse.opacities[::5] = 0.002  # dead from the start: MCMC relocates them
    plan = _fit_plan(strategy)
    checks = []
    original = fit_module.make_strategy

    def checked(*args):
        made = original(*args)
        step = made.step

        def step_and_check(free, optimizer, *rest):
            step(free, optimizer, *rest)
            _state_aligned(free, optimizer)
            checks.append(len(free.tensors["means"]))

        made.step = step_and_check
        return made

    monkeypatch.setattr(fit_module, "make_strategy", checked)
    fitted, stats = fit_on_views(sparse, cameras, photos, SIZE, SIZE, plan, alpha_threshold=None)
    assert len(checks) == stats["steps"] == 50
    history = stats["densify"]
    if strategy == "mcmc":
        assert sum(h["relocated"] for h in history) > 0 and sum(h["added"] for h in history) > 0
        assert max(checks) <= 400 and len(fitted) == history[-1]["after"]
    else:
        assert sum(h.get("cloned", 0) + h.get("split", 0) for h in history) > 0
    assert stats["mse_after"] < stats["mse_before"]
    again, _ = fit_on_views(sparse, cameras, photos, SIZE, SIZE, plan, alpha_threshold=None)
    for name in ("means", "quats", "scales", "opacities", "sh"):
        assert torch.equal(getattr(again, name), getattr(fitted, name)), name


def test_the_strategy_flag_reaches_the_library():
    from surfsplat.cli import build_parser
    from surfsplat.commands.reconstruct import optimize_from_args

    parse = build_parser().parse_args
    assert optimize_from_args(parse(["reconstruct", "--images", "a.png"])).strategy == "auto"
    for name in ("absgs", "mcmc"):
        args = parse(["reconstruct", "--images", "a.png", "--optimize-strategy", name])
        assert optimize_from_args(args).strategy == name
        args = parse(["optimize", "out", "--optimize-strategy", name])
        assert optimize_from_args(args).strategy == name
    with pytest.raises(SystemExit):
        parse(["reconstruct", "--images", "a.png", "--optimize-strategy", "nope"])
    # the fit's seed: 0 by default, any integer by --optimize-seed, in both commands
    assert optimize_from_args(parse(["reconstruct", "--images", "a.png"])).seed == 0
    assert optimize_from_args(parse(["reconstruct", "--images", "a.png", "--optimize-seed", "3"])).seed == 3
    assert optimize_from_args(parse(["optimize", "out", "--optimize-seed", "7"])).seed == 7


@pytest.mark.parametrize(("backend", "expected"), [("torch", "absgs"), ("cpu", "absgs"), ("gsplat", "3dgs")])
def test_auto_strategy_is_absgs_where_the_backend_gives_the_absolute_gradient(monkeypatch, backend, expected):
    """The shipped "auto": AbsGS on the torch and compiled CPU backends, 3DGS's on gsplat, whose 2DGS kernel
    cannot give surfels' absolute screen gradient."""
    from surfsplat.capture import optimize as optimize_module

    plane, cameras, _ = _two_views_of_a_textured_plane()
    from surfsplat.render import render

    photos = render(plane, cameras, SIZE, SIZE).color
    seen = {}

    def fake_fit(start, cams, images, width, height, plan, **kwargs):
        seen["densify"] = plan.densify
        return start, {"kept": 1.0, "steps": 0}

    monkeypatch.setattr(optimize_module, "fit_on_views", fake_fit)
    monkeypatch.setattr("surfsplat.render.resolve_backend", lambda *args, **kwargs: backend)
    config = OptimizeConfig(steps=10, start=dataclasses.replace(OptimizeConfig().start, kind="network"))
    _, stats = optimize_module.optimize_on_views(plane, cameras, photos, SIZE, SIZE, config, backend=backend)
    assert stats["strategy"] == expected
    assert seen["densify"] == (DensifyConfig(absgrad=True) if expected == "absgs" else DensifyConfig())
