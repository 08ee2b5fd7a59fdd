"""`surfsplat optimize FOLDER` continues the saved fit by default: its first step starts from the saved
surfels exactly, at the end of the fit's schedule; `--optimize-start` restarts it; the result is
compared with what was read, and a worse result says so on the terminal and in its JSON and never
replaces its input."""

from __future__ import annotations

import json

import pytest
import torch

from surfsplat.capture import optimize as optimize_module
from surfsplat.cli import main
from surfsplat.data.cameras import save_cameras
from surfsplat.data.synthetic import make_scene, make_trajectory, render_synthetic
from surfsplat.export.images import write_png
from surfsplat.export.ply import load_ply
from surfsplat.model import SurfSplat, save_checkpoint
from surfsplat.reconstruction import scene_fit

SIZE = 32


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    root = tmp_path_factory.mktemp("views")
    scene = make_scene(5)
    cams = make_trajectory(scene, torch.Generator().manual_seed(0)).cameras(torch.linspace(0, 1, 5), SIZE, SIZE)
    images = render_synthetic(scene, cams, SIZE, SIZE).image
    paths = [write_png(root / f"v{i}.png", image) for i, image in enumerate(images)]
    save_cameras(root / "cameras.json", cams, SIZE, SIZE, [p.name for p in paths], near=0.5, far=15.0)
    weights, _ = save_checkpoint(SurfSplat.from_preset("tiny"), root / "tiny")
    return paths, root / "cameras.json", weights


def _reconstruct(views, out, *flags: str) -> None:
    paths, cameras, weights = views
    argv = ["reconstruct", "--checkpoint", str(weights), "--cameras", str(cameras), "--views-per-pass", "2"]
    argv += ["--formats", "ply", "--raw-3dgs", "--no-progress", "--refine-steps", "0", *flags, "--out", str(out)]
    assert main([*argv, "--images", *map(str, paths)]) == 0


@pytest.fixture
def fits(monkeypatch):
    """The start and plan of every fit the optimizer runs."""
    seen = []
    real = optimize_module.fit_on_views

    def recorded(start, cameras, images, width, height, plan, **kwargs):
        seen.append((start, plan))
        return real(start, cameras, images, width, height, plan, **kwargs)

    monkeypatch.setattr(optimize_module, "fit_on_views", recorded)
    return seen


def test_an_optimized_folder_is_continued_from_its_saved_surfels(views, fits, tmp_path, capsys):
    # a fitted scene first (the network's start: SIFT finds no points in 32x32 views)
    _reconstruct(
        views, tmp_path / "fit", "--holdout-every", "4", "--optimize-steps", "6", "--optimize-start", "network"
    )
    capsys.readouterr()
    fits.clear()
    command = ["optimize", str(tmp_path / "fit"), "--optimize-steps", "3", "--formats", "ply", "--raw-3dgs"]
    assert main([*command, "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "optimized on the context views from the saved surfels (continued): 3 steps" in printed, printed
    ((start, plan),) = fits
    saved = load_ply(tmp_path / "fit" / "surfels.ply")
    assert len(start) == len(saved)  # nothing thinned, grown or dropped before the first step
    for name in ("means", "quats", "scales", "opacities"):
        assert torch.equal(getattr(start, name), getattr(saved, name)), name
    have = saved.sh.shape[-1]
    assert torch.equal(start.sh[..., :have], saved.sh) and not start.sh[..., have:].any()
    # where the fit's schedule ends: full size, the final position rate throughout, no growth
    assert plan.levels == () and plan.densify is None and plan.means_final_rate is None
    default = optimize_module.OptimizeConfig()
    assert plan.rates["means"] == pytest.approx(default.means_lr_final * plan.extent * default.lr_scale)
    summary = json.loads((tmp_path / "fit_optimized" / "reconstruction.json").read_text())
    versus = summary["optimize"]["versus_input"]
    held = summary["capture"]["held_out"]
    # compared on the held-out views: the input's figure is the score of the folder it read
    first = json.loads((tmp_path / "fit" / "reconstruction.json").read_text())["capture"]["held_out"]
    assert versus["measure"] == "held-out PSNR" and versus["input"] == str(tmp_path / "fit")
    assert versus["input_psnr"] == pytest.approx(first["mean_psnr"], abs=1e-4)
    assert versus["psnr"] == pytest.approx(held["mean_psnr"]) and versus["worse"] == (
        held["mean_psnr"] < first["mean_psnr"]
    )
    assert summary["worse_than_input"] == versus["worse"]
    assert "than its input (held-out PSNR" in printed or "as good as its input" in printed


def test_a_chosen_start_restarts_the_fit(views, fits, tmp_path, capsys):
    _reconstruct(views, tmp_path / "net", "--optimize-steps", "0")
    fits.clear()
    command = ["optimize", str(tmp_path / "net"), "--optimize-steps", "2", "--optimize-start", "network"]
    assert main([*command, "--formats", "ply", "--raw-3dgs", "--no-progress"]) == 0
    ((start, plan),) = fits
    saved = load_ply(tmp_path / "net" / "surfels.ply")
    assert len(start) == len(saved) < optimize_module.OptimizeConfig().start.budget  # all kept by the thinning
    # the whole schedule again: coarse to fine, the position rate's decay, growth
    default = optimize_module.OptimizeConfig()
    # growth: the default strategy "auto" is absgs on the CPU, 3DGS's densification with the absolute gradient
    assert plan.levels == default.levels and plan.densify == optimize_module.STRATEGIES["absgs"](default)
    assert plan.means_final_rate == pytest.approx(plan.rates["means"] / 100)
    assert "from the network's surfels" in capsys.readouterr().out


def test_a_result_worse_than_its_input_is_reported_and_kept_apart(views, monkeypatch, tmp_path, capsys):
    _reconstruct(views, tmp_path / "scene", "--optimize-steps", "0")  # no held-out views: compared on the context
    ply = (tmp_path / "scene" / "surfels.ply").read_bytes()
    scores = iter([30.0, 20.0])  # the input's context-view PSNR, then the result's
    monkeypatch.setattr(scene_fit, "_context_psnr", lambda scene, images: next(scores))
    capsys.readouterr()
    command = ["optimize", str(tmp_path / "scene"), "--optimize-steps", "2", "--formats", "ply", "--raw-3dgs"]
    assert main([*command, "--no-progress"]) == 0
    printed = capsys.readouterr().out
    line = f"WORSE than its input (context-view PSNR 30.00 dB read, 20.00 dB now): {tmp_path / 'scene'} stays the better scene"
    assert line in printed, printed
    summary = json.loads((tmp_path / "scene_optimized" / "reconstruction.json").read_text())
    assert summary["worse_than_input"] is True
    assert summary["optimize"]["versus_input"] == {
        "input": str(tmp_path / "scene"),
        "measure": "context-view PSNR",
        "input_psnr": 30.0,
        "psnr": 20.0,
        "worse": True,
    }
    assert (tmp_path / "scene" / "surfels.ply").read_bytes() == ply  # the input is never replaced
    assert "worse_than_input" not in json.loads((tmp_path / "scene" / "reconstruction.json").read_text())
