"""Per-scene optimization: its loss terms against references (scikit-image's SSIM, a plane's exact
normal), the compiled CPU backend's position and rotation gradients of that loss against the torch
backend's, the loop shared with the refinement, held-out views never fitted, a saved reconstruction
optimized and read back, and the command-line wiring."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

import surfsplat
from surfsplat.capture import OptimizeConfig, RefineConfig, optimize_on_views, refine_on_views
from surfsplat.capture.fit import FitPlan, fit_on_views
from surfsplat.capture.losses import colour_loss, depth_normal_error
from surfsplat.capture.optimize import scene_extent
from surfsplat.capture.starts import StartConfig
from surfsplat.cli import main
from surfsplat.data.cameras import save_cameras
from surfsplat.data.synthetic import make_scene, make_trajectory, render_synthetic
from surfsplat.export.images import write_png
from surfsplat.model import SurfSplat, save_checkpoint
from surfsplat.render import render
from surfsplat.utils.checks import SurfSplatInputError

from .test_capture import SIZE, _two_views_of_a_textured_plane


def _noisy(plane: surfsplat.Gaussians, seed: int = 1) -> surfsplat.Gaussians:
    """The plane's surfels moved off it, tilted, resized and grey with degree-2 SH: what a fit must undo."""
    g = torch.Generator().manual_seed(seed)
    n = len(plane)
    quats = torch.nn.functional.normalize(plane.quats + 0.15 * torch.randn(n, 4, generator=g), dim=-1)
    return surfsplat.Gaussians(
        plane.means + 0.03 * torch.randn(n, 3, generator=g),
        quats,
        plane.scales * 1.3,
        plane.opacities * 0.7,
        torch.zeros(n, 3, 9),
    )


# ----------------------------------------------------------------------------------------- loss terms
def test_dssim_term_is_one_minus_the_published_ssim_and_differentiable():
    g = torch.Generator().manual_seed(0)
    target = torch.rand(2, 3, 24, 31, generator=g, dtype=torch.float64)
    prediction = (target + 0.1 * torch.randn(target.shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    prediction.requires_grad_(True)
    loss = colour_loss(prediction, target, "l1_dssim", ssim_weight=1.0)
    reference = np.mean(
        [
            structural_similarity(
                t.numpy(), p.detach().numpy(), win_size=11, gaussian_weights=True, channel_axis=0, data_range=1.0
            )
            for t, p in zip(target, prediction)
        ]
    )
    assert float(loss.detach()) == pytest.approx(1 - reference, abs=1e-10)
    loss.backward()
    assert prediction.grad is not None and float(prediction.grad.abs().sum()) > 0
    # the mix: (1 - 0.2) L1 + 0.2 D-SSIM
    mixed = colour_loss(prediction.detach(), target, "l1_dssim", ssim_weight=0.2)
    l1 = float((prediction.detach() - target).abs().mean())
    assert float(mixed) == pytest.approx(0.8 * l1 + 0.2 * (1 - reference), abs=1e-10)


def test_depth_normal_term_vanishes_on_a_flat_plane_and_not_on_tilted_surfels():
    plane, cameras, _ = _two_views_of_a_textured_plane()
    plane = surfsplat.Gaussians(
        plane.means, plane.quats, plane.scales * 2, torch.full_like(plane.opacities, 0.99), plane.sh
    )
    out = render(plane, cameras, SIZE, SIZE)
    inner = out.alpha[..., 6:-6, 6:-6]
    assert float(inner.min()) > 0.9  # the plane covers the middle of both views
    # facing the camera: the rendered normal is (0, 0, -1), the depth's normal too
    assert float(out.normal[:, 2, 6:-6, 6:-6].mean()) == pytest.approx(-1.0, abs=1e-3)
    flat = depth_normal_error(
        out.depth[..., 5:-5, 5:-5], out.normal[..., 5:-5, 5:-5], out.alpha[..., 5:-5, 5:-5], _crop(cameras, 5)
    )
    assert float(flat) < 1e-4
    tilted = _noisy(plane)
    tilted = surfsplat.Gaussians(plane.means, tilted.quats, plane.scales, plane.opacities, plane.sh)
    out = render(tilted, cameras, SIZE, SIZE)
    crop = (out.depth[..., 5:-5, 5:-5], out.normal[..., 5:-5, 5:-5], out.alpha[..., 5:-5, 5:-5])
    assert float(depth_normal_error(*crop, _crop(cameras, 5))) > 100 * float(flat) + 1e-3


def _crop(cameras: surfsplat.Cameras, border: int) -> surfsplat.Cameras:
    """The cameras of images with `border` pixels cut off every side."""
    K = cameras.K.clone()
    K[:, :2, 2] -= border
    return surfsplat.Cameras(cameras.c2w, K)


# ----------------------------------------------------------------------------------------- backends
def test_cpu_backend_position_and_rotation_gradients_of_the_loss_match_torch():
    plane, cameras, photos = _two_views_of_a_textured_plane()
    start = _noisy(plane).subset(torch.arange(0, len(plane), 3)).to(torch.float64)  # a third: a quicker reference
    start = surfsplat.Gaussians(start.means, start.quats, start.scales * 1.7, start.opacities, start.sh)
    grads = {}
    for backend in ("cpu", "torch"):
        means = start.means.clone().requires_grad_(True)
        quats = start.quats.clone().requires_grad_(True)
        g = surfsplat.Gaussians(means, quats, start.scales, start.opacities, start.sh + 0.3, validate=False)
        out = render(g, cameras.to(dtype=torch.float64), SIZE, SIZE, backend=backend)
        loss = colour_loss(out.color, photos.double(), "l1_dssim") + 0.05 * depth_normal_error(
            out.depth, out.normal, out.alpha, cameras.to(dtype=torch.float64)
        )
        loss.backward()
        grads[backend] = (means.grad, quats.grad)
    for name, ours, reference in zip(("means", "quats"), grads["cpu"], grads["torch"]):
        scale = float(reference.abs().max())
        assert scale > 0, name
        assert float((ours - reference).abs().max()) <= 1e-6 * scale, name


# ----------------------------------------------------------------------------------------- the fit
def _from_network(**fields) -> OptimizeConfig:
    """The fit of the given surfels as they are: the network's start, every one kept, no growth, full size."""
    defaults = {"start": StartConfig(kind="network", budget=10**6), "densify": None, "levels": (), "sh_degree": 2}
    return OptimizeConfig(**{**defaults, **fields})


def test_optimization_moves_every_attribute_and_matches_the_photos():
    plane, cameras, photos = _two_views_of_a_textured_plane()
    start = _noisy(plane)
    config = _from_network(steps=60, lr_scale=5.0, views_per_step=2, sh_degree_share=None)
    fitted, stats = optimize_on_views(start, cameras, photos, SIZE, SIZE, config)
    assert stats["kept"] == 1.0 and stats["steps"] == 60
    assert stats["mse_after"] < 0.05 * stats["mse_before"], stats
    for name in ("means", "quats", "scales", "sh"):
        kept = fitted.subset(torch.arange(len(fitted)))  # same order as the survivors of the start
        assert not torch.equal(getattr(kept, name), getattr(start, name)[: len(kept)]) or len(kept) < len(start), name
    assert torch.allclose(fitted.quats.norm(dim=-1), torch.ones(len(fitted)), atol=1e-5)
    assert stats["surfels_before"] == len(start) and stats["surfels_after"] == len(fitted)
    again, _ = optimize_on_views(start, cameras, photos, SIZE, SIZE, config)
    assert torch.equal(again.means, fitted.means)  # seeded: the same views in the same order every run


def test_pruning_removes_the_faint_surfels_and_their_adam_moments():
    plane, cameras, photos = _two_views_of_a_textured_plane()
    start = _noisy(plane)
    opacities = start.opacities.clone()
    opacities[::3] = 1e-3  # a third start below the pruning threshold and the photos do not need them
    start = surfsplat.Gaussians(start.means, start.quats, start.scales, opacities, start.sh)
    fitted, stats = optimize_on_views(start, cameras, photos, SIZE, SIZE, _from_network(steps=8, prunings=1))
    assert len(fitted) < len(start) - len(start) // 4 and stats["surfels_after"] == len(fitted)
    never, _ = optimize_on_views(start, cameras, photos, SIZE, SIZE, _from_network(steps=8, prunings=0))
    assert len(never) == len(start)


def test_only_the_chosen_parameters_move_and_the_sh_degree_rises_during_the_fit():
    plane, cameras, photos = _two_views_of_a_textured_plane()
    start = _noisy(plane)
    fitted, _ = optimize_on_views(
        start, cameras, photos, SIZE, SIZE, _from_network(steps=6, parameters=("sh", "opacities"), prunings=0)
    )
    assert torch.equal(fitted.means, start.means) and torch.equal(fitted.quats, start.quats)
    assert torch.equal(fitted.scales, start.scales) and not torch.equal(fitted.sh, start.sh)
    plan = OptimizeConfig(steps=90, sh_degree_share=1 / 30).plan(1.0, views=3, pixels=SIZE * SIZE)
    assert plan.sh_degree_share == pytest.approx(1 / 30)  # as 3DGS's 1,000 of 30,000 steps
    assert plan.rates["sh_rest"] == pytest.approx(plan.rates["sh_dc"] / 20)
    assert plan.means_final_rate == pytest.approx(plan.rates["means"] / 100)


def test_the_scene_extent_is_3dgs_camera_radius():
    _, cameras, _ = _two_views_of_a_textured_plane()  # centres 0.2 apart
    assert scene_extent(cameras) == pytest.approx(1.1 * 0.1)
    assert scene_extent(cameras[:1]) == 1.0


def test_the_refinement_is_the_shared_loop_with_its_own_plan_and_unchanged_results():
    plane, cameras, photos = _two_views_of_a_textured_plane()
    g = torch.Generator().manual_seed(1)
    start = surfsplat.Gaussians(
        plane.means, plane.quats, plane.scales, plane.opacities * 0.7, torch.randn(len(plane), 3, 9, generator=g) * 0.3
    )
    config = RefineConfig(steps=20, lr=0.05)
    refined, stats = refine_on_views(start, cameras, photos, SIZE, SIZE, config)
    plan = config.plan(len(cameras))
    assert set(plan.rates) == {"sh_dc", "sh_rest", "log_scales", "logits"} and plan.loss == "mse"
    looped, loop_stats = fit_on_views(start, cameras, photos, SIZE, SIZE, plan)
    assert torch.equal(looped.sh, refined.sh) and torch.equal(looped.scales, refined.scales)
    assert torch.equal(looped.opacities, refined.opacities)
    # the figure the refinement gave before its loop became the optimization's (same scene, same config)
    assert stats["mse_after"] == pytest.approx(0.0014477064833045006, rel=1e-5)
    assert loop_stats["mse_after"] == stats["mse_after"]


@pytest.mark.parametrize(
    ("options", "needle"),
    [
        ({"steps": -1}, "optimize.steps"),
        ({"views_per_step": 0}, "optimize.views_per_step"),
        ({"scale": 0.0}, "optimize.scale"),
        ({"parameters": ("colours",)}, "optimize.parameters"),
        ({"means_lr": 0.0}, "optimize.means_lr"),
        ({"ssim_weight": 1.5}, "optimize.ssim_weight"),
        ({"sh_degree_share": 0.0}, "optimize.sh_degree_share"),
        ({"prunings": -1}, "optimize.prunings"),
        ({"seconds": 0.0}, "optimize.seconds"),
        ({"levels": ((0.5, 0.5), (0.2, 0.25))}, "optimize.levels"),
        ({"parameters": ("sh",)}, "optimize.densify"),
        ({"sh_degree": 4}, "optimize.sh_degree"),
        ({"antialiased": 1}, "optimize.antialiased"),
    ],
)
def test_optimize_config_refuses_bad_values(options, needle):
    with pytest.raises(SurfSplatInputError, match=needle):
        OptimizeConfig(**options)


def test_a_plan_with_unknown_tensors_is_refused():
    with pytest.raises(SurfSplatInputError, match="unknown fitted tensors"):
        FitPlan(name="x", steps=1, rates={"colour": 1.0})


# ----------------------------------------------------------------------------------------- in reconstruct
@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    torch.manual_seed(0)
    weights, _ = save_checkpoint(SurfSplat.from_preset("tiny"), tmp_path_factory.mktemp("tiny") / "tiny")
    return weights


@pytest.fixture(scope="module")
def five_views(tmp_path_factory):
    root = tmp_path_factory.mktemp("views")
    scene = make_scene(5)
    cams = make_trajectory(scene, torch.Generator().manual_seed(0)).cameras(torch.linspace(0, 1, 5), 32, 32)
    images = render_synthetic(scene, cams, 32, 32).image
    paths = [write_png(root / f"v{i}.png", image) for i, image in enumerate(images)]
    save_cameras(root / "cameras.json", cams, 32, 32, [p.name for p in paths], near=0.5, far=15.0)
    return paths, root / "cameras.json"


def test_held_out_views_are_scored_before_and_after_and_never_fitted(five_views, tiny_checkpoint, tmp_path):
    paths, cameras = five_views
    options = surfsplat.CaptureOptions(views_per_pass=2, holdout_every=4, optimize=_from_network(steps=3))
    scene = surfsplat.reconstruct(paths, tiny_checkpoint, cameras=cameras, capture=options, progress=False)
    h = scene.holdout
    assert h.names == ["v0.png", "v4.png"] and scene.names == ["v1.png", "v2.png", "v3.png"]
    assert h.before is not None and len(h.before["psnr"]) == 2 and h.before_renders.shape == (2, 3, 32, 32)
    assert len(h.ssim) == 2 and (h.lpips is not None or h.lpips_note.startswith("LPIPS unavailable: "))
    assert scene.optimize_stats["steps"] == 3 and "optimize" in scene.seconds and "refine" not in scene.seconds
    # a held-out photo changed beyond recognition changes nothing the fit produced
    changed = tmp_path / "v0.png"
    write_png(changed, torch.rand(3, 32, 32, generator=torch.Generator().manual_seed(3)))
    other = surfsplat.reconstruct(
        [changed, *paths[1:]], tiny_checkpoint, cameras=_renamed(cameras, tmp_path), capture=options, progress=False
    )
    assert torch.equal(other.gaussians.means, scene.gaussians.means)
    assert torch.equal(other.gaussians.sh, scene.gaussians.sh)
    assert other.holdout.psnr[0] != h.psnr[0]  # the changed photo is scored, not fitted
    written = scene.save(tmp_path / "out", formats=("ply", "renders"))
    summary = json.loads(written["summary"].read_text())
    held = summary["capture"]["held_out"]
    assert held["before_optimization"]["mean_psnr"] == pytest.approx(h.before["mean_psnr"])
    assert summary["optimize"]["steps"] == 3 and "optimize" in summary["seconds"]
    assert (tmp_path / "out" / "capture" / "v0_render_before.png").is_file()
    assert "before the optimization" in (tmp_path / "out" / "capture.html").read_text()


def _renamed(cameras, folder):
    """The camera file beside the changed photo (cameras are matched by file name)."""
    target = folder / "cameras.json"
    target.write_text(cameras.read_text())
    return target


def test_a_saved_reconstruction_is_optimized_and_reads_back(five_views, tiny_checkpoint, tmp_path, capsys):
    paths, cameras = five_views
    argv = ["reconstruct", "--checkpoint", str(tiny_checkpoint), "--cameras", str(cameras), "--views-per-pass", "2"]
    argv += ["--formats", "ply", "--raw-3dgs", "--no-progress", "--refine-steps", "0", "--optimize-steps", "0"]
    argv += ["--out", str(tmp_path / "first")]
    assert main([*argv, "--images", *map(str, paths[:3])]) == 0, capsys.readouterr().err
    capsys.readouterr()
    out = tmp_path / "first_optimized"
    command = ["optimize", str(tmp_path / "first"), "--optimize-steps", "30", "--optimize-start", "network"]
    assert main([*command, "--raw-3dgs", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "optimized on the context views from the network's surfels: 30 steps at 32x32" in printed, printed
    from surfsplat.reconstruction import load_reconstruction

    before, photos = load_reconstruction(tmp_path / "first")
    after, _ = load_reconstruction(out)
    assert photos.shape == (3, 3, 32, 32) and after.names == before.names
    assert not torch.equal(after.gaussians.means, before.gaussians.means[: len(after.gaussians)])
    summary = json.loads((out / "reconstruction.json").read_text())
    assert summary["optimize"]["steps"] == 30 and summary["optimize"]["kept"] == 1.0
    # read back, the optimized scene renders its photos as it did in memory
    again = after.render()
    assert float((again.color - photos).square().mean()) == pytest.approx(summary["optimize"]["mse_after"], rel=1e-3)


def test_reconstruct_flags_reach_the_library(monkeypatch, tmp_path):
    from surfsplat.cli import build_parser

    args = build_parser().parse_args(["reconstruct", "--images", "a.png", "b.png", "--optimize-steps", "7"])
    assert args.checkpoint == "tiny-synthetic"  # the shipped model, as surfsplat.reconstruct
    from surfsplat.commands.reconstruct import optimize_from_args

    config = optimize_from_args(args)
    assert config.steps == 7 and config.scale == OptimizeConfig().scale
    assert not config.antialiased and not config.plan(1.0, 3, 64 * 64).antialiased
    flagged = build_parser().parse_args(["reconstruct", "--images", "a.png", "b.png", "--optimize-antialiased"])
    assert optimize_from_args(flagged).plan(1.0, 3, 64 * 64).antialiased
    with pytest.raises(SurfSplatInputError, match="--optimize-steps"):
        optimize_from_args(build_parser().parse_args(["reconstruct", "--images", "a.png", "--optimize-steps", "-2"]))


def test_a_resolution_warning_has_one_prefix(capsys):
    from surfsplat.model.pretrained import check_resolution
    from surfsplat.utils import log

    model = SurfSplat.from_preset("tiny")
    model.pretrained_info = type("Info", (), {"name": "tiny-synthetic", "resolution": (64, 64)})()
    log.configure(logging.INFO)
    try:
        message = check_resolution(model, 128, 128)
    finally:
        logging.getLogger(log.ROOT).handlers.clear()
    err = capsys.readouterr().err
    assert err.strip() == f"warning: {message}" and "warning: warning" not in err


def test_the_distortion_term_gathers_the_surfels_a_ray_meets_into_one_layer():
    plane, cameras, photos = _two_views_of_a_textured_plane()
    start = _noisy(plane)  # surfels 0.03 off the plane: each ray meets several depths

    def spread(g) -> float:
        return float(render(g, cameras, SIZE, SIZE, distortion=True).distortion.mean())

    plain, _ = optimize_on_views(start, cameras, photos, SIZE, SIZE, _from_network(steps=40, views_per_step=2))
    config = _from_network(steps=40, views_per_step=2, distortion_weight=10.0, distortion_from=0.0)
    gathered, stats = optimize_on_views(start, cameras, photos, SIZE, SIZE, config)
    assert stats["kept"] == 1.0 and config.plan(1.0, 2, SIZE * SIZE).distortion_weight == 10.0
    assert spread(gathered) < 0.7 * spread(plain), (spread(gathered), spread(plain), spread(start))


def test_optimizing_a_saved_reconstruction_scores_its_held_out_views_again(five_views, tiny_checkpoint, tmp_path):
    paths, cameras = five_views
    argv = ["reconstruct", "--checkpoint", str(tiny_checkpoint), "--cameras", str(cameras), "--views-per-pass", "2"]
    argv += ["--holdout-every", "4", "--optimize-steps", "0", "--refine-steps", "0", "--formats", "ply", "--raw-3dgs"]
    argv += ["--no-progress"]
    assert main([*argv, "--out", str(tmp_path / "first"), "--images", *map(str, paths)]) == 0
    first = json.loads((tmp_path / "first" / "reconstruction.json").read_text())["capture"]["held_out"]
    assert first["names"] == ["v0.png", "v4.png"] and len(first["sources"]) == 2
    command = ["optimize", str(tmp_path / "first"), "--optimize-steps", "60", "--optimize-start", "network"]
    assert main([*command, "--raw-3dgs", "--no-progress", "--formats", "ply"]) == 0
    again = json.loads((tmp_path / "first_optimized" / "reconstruction.json").read_text())["capture"]["held_out"]
    assert again["names"] == first["names"]
    # scored before the fit as the first reconstruction scored them, and again after it
    assert again["before_optimization"]["psnr"] == pytest.approx(first["psnr"], abs=1e-4)
    assert again["psnr"] != again["before_optimization"]["psnr"]
    from surfsplat.reconstruction import load_reconstruction

    scene, photos = load_reconstruction(tmp_path / "first")
    assert scene.holdout.names == ["v0.png", "v4.png"] and len(photos) == len(scene.names) == 3
    assert not set(scene.names) & set(scene.holdout.names)  # the fit is given the context photos only


def test_the_default_budget_scales_with_the_views_and_their_pixels():
    config = OptimizeConfig()
    fern, dtu, clip = config.steps_for(17, 368 * 496), config.steps_for(10, 288 * 400), config.steps_for(7, 288 * 400)
    assert (fern, dtu, clip) == (3000, 1500, 1050)  # docs/optimize.md, "The budget"
    # proportional to views x pixels between the floor and the ceiling
    assert config.steps_for(14, 288 * 400) == 2 * clip and config.steps_for(7, 2 * 288 * 400) == 2 * clip
    assert config.steps_for(3, 64 * 64) == 1000 and config.steps_for(100, 1920 * 1080) == 3000
    assert config.steps_for(2, 288 * 400) == 0 and not config.runs_for(2) and config.runs_for(3)
    assert OptimizeConfig(steps=7).steps_for(2, 1) == 7 and OptimizeConfig(steps=0).steps_for(9, 10**6) == 0
    assert not OptimizeConfig(steps=0).runs_for(9) and OptimizeConfig(steps=4).runs_for(2)
    assert OptimizeConfig(seconds=20.0).steps_for(9, 1) == 1_000_000  # the time budget ends the fit
    assert config.plan(1.0, 10, 288 * 400).steps == 1500


def test_an_antialiased_fit_is_saved_as_one_and_every_later_render_uses_the_filter(
    five_views, tiny_checkpoint, tmp_path
):
    """`--optimize-antialiased`: the fit's renders (its recorded colour error is the antialiased render's),
    reconstruction.json, the scene read back and its held-out zoom scores all carry the filter."""
    paths, cameras = five_views
    argv = ["reconstruct", "--checkpoint", str(tiny_checkpoint), "--cameras", str(cameras), "--views-per-pass", "2"]
    argv += ["--holdout-every", "4", "--optimize-steps", "0", "--refine-steps", "0", "--formats", "ply", "--raw-3dgs"]
    assert main([*argv, "--no-progress", "--out", str(tmp_path / "first"), "--images", *map(str, paths)]) == 0
    command = ["optimize", str(tmp_path / "first"), "--optimize-steps", "20", "--optimize-start", "network"]
    assert main([*command, "--optimize-antialiased", "--raw-3dgs", "--no-progress", "--formats", "ply"]) == 0
    summary = json.loads((tmp_path / "first_optimized" / "reconstruction.json").read_text())
    assert summary["antialiased"] is True and summary["optimize"]["antialiased"] is True
    zoom = summary["capture"]["held_out"]["zoom"]
    assert zoom["antialiased"] is True and zoom["x1"] == pytest.approx(summary["capture"]["held_out"]["mean_psnr"])
    assert {"x1/2", "x1/4", "x1/2_vs_render", "x1/4_vs_render", "x2", "x4", "coverage_x4_over_x1"} <= set(zoom)
    from surfsplat.reconstruction import load_reconstruction

    scene, photos = load_reconstruction(tmp_path / "first_optimized")
    assert scene.antialiased
    again = scene.render()
    filtered = render(scene.gaussians, scene.cameras, 32, 32, alpha_threshold=scene.alpha_threshold, antialiased=True)
    plain = render(scene.gaussians, scene.cameras, 32, 32, alpha_threshold=scene.alpha_threshold)
    assert torch.equal(again.color, filtered.color) and not torch.equal(again.color, plain.color)
    error = float((again.color - photos).square().mean())
    assert error == pytest.approx(summary["optimize"]["mse_after"], rel=1e-3)
