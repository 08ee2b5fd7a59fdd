"""No work for nothing: where the optimizer starts from COLMAP's points, `reconstruct` loads no model
and runs no forward pass, and it says so (the Scene, reconstruction.json, the printed summary); where
its start needs the network's surfels ("auto" finding too few points), the passes run and start it."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

import surfsplat
from surfsplat.capture import OptimizeConfig
from surfsplat.capture.starts import StartConfig, make_start
from surfsplat.cli import main
from surfsplat.data.cameras import save_cameras
from surfsplat.data.images import read_image
from surfsplat.data.synthetic import make_scene, make_trajectory, render_synthetic
from surfsplat.export.images import write_png
from surfsplat.reconstruction import pipeline
from surfsplat.reconstruction.scene import HeldOut

SIZE = 256  # SIFT finds some hundred points in the room's views at this size (tests/capture/test_starts.py)


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """Five views along a path in a procedural room, as PNG files with their camera file."""
    root = tmp_path_factory.mktemp("room")
    scene = make_scene(7)
    cameras = make_trajectory(scene, torch.Generator().manual_seed(3)).cameras(torch.linspace(0, 1, 5), SIZE, SIZE)
    images = render_synthetic(scene, cameras, SIZE, SIZE).image
    paths = [write_png(root / f"v{i}.png", image) for i, image in enumerate(images)]
    save_cameras(root / "cameras.json", cameras, SIZE, SIZE, [p.name for p in paths], near=0.5, far=15.0)
    return paths, root / "cameras.json"


@pytest.fixture
def no_network(monkeypatch):
    """Loading a model, or running one, fails the test."""

    def refuse(*args, **kwargs):
        raise AssertionError("the network was loaded although the optimizer starts from the SfM points")

    monkeypatch.setattr(pipeline, "_load", refuse)
    monkeypatch.setattr(pipeline, "_network_passes", refuse)


def test_auto_resolving_to_points_loads_no_model_and_fits_from_the_points(room, no_network):
    paths, cameras = room
    config = OptimizeConfig(steps=4, densify=None, start=StartConfig(kind="auto", min_points=20))
    options = surfsplat.CaptureOptions(holdout_every=4, optimize=config)
    scene = surfsplat.reconstruct(paths, cameras=cameras, capture=options, progress=False)
    stats = scene.optimize_stats
    assert stats["start"] == "points" and "start_reason" not in stats and stats["points"] >= 20
    assert scene.network == pipeline.NETWORK_SKIPPED and scene.passes == [] and scene.model == ""
    assert scene.precision == "none" and scene.mode == "surfel" and scene.scale_multipliers is None
    assert "forward" not in scene.seconds and "start" in scene.seconds and "optimize" in scene.seconds
    # the held-out views' figures before the fit are those of the start the fit began from: COLMAP's
    # points as surfels, rendered plain (the "auto" threshold from points)
    assert scene.alpha_threshold is None and stats["alpha_threshold"] is None
    context = [p for p in paths if p.name in scene.names]
    photos = torch.stack([read_image(p, background=(0.0, 0.0, 0.0))[0] for p in context])
    start, figures = make_start(config.start, None, photos, scene.cameras, config.sh_degree)
    assert figures["points"] == stats["points"] == len(start)
    held = HeldOut(scene.holdout.names, scene.holdout.cameras, scene.holdout.images)
    before = dataclasses.replace(scene, gaussians=start, alpha_threshold=None, holdout=held)
    before.score_holdout()
    assert before.holdout.psnr == pytest.approx(scene.holdout.before["psnr"], abs=1e-4)
    summary = scene.summary()
    assert summary["network"] == pipeline.NETWORK_SKIPPED and summary["capture"]["passes"] == []


def test_the_points_start_from_the_command_line_says_the_network_was_skipped(room, no_network, tmp_path, capsys):
    paths, cameras = room
    argv = ["reconstruct", "--images", *map(str, paths), "--cameras", str(cameras), "--holdout-every", "4"]
    argv += ["--optimize-steps", "3", "--optimize-start", "points", "--formats", "ply", "--raw-3dgs", "--no-progress"]
    assert main([*argv, "--out", str(tmp_path / "out")]) == 0, capsys.readouterr().err
    printed = capsys.readouterr().out
    assert "network: skipped (the optimizer starts from the SfM points)" in printed, printed
    assert "optimized on the context views from" in printed and "COLMAP points" in printed
    summary = json.loads((tmp_path / "out" / "reconstruction.json").read_text())
    assert summary["network"] == "skipped (the optimizer starts from the SfM points)"
    assert summary["optimize"]["start"] == "points" and summary["surfels"] == summary["optimize"]["surfels_after"]
    assert "network:" in (tmp_path / "out" / "capture.html").read_text()


def test_auto_with_too_few_points_runs_the_network_and_starts_from_its_surfels(room, monkeypatch):
    """COLMAP's points are found before the passes; too few, and the passes run and are the start."""
    paths, cameras = room
    loaded = []
    real_load = pipeline._load

    def counted(*args, **kwargs):
        loaded.append(args[0])
        return real_load(*args, **kwargs)

    monkeypatch.setattr(pipeline, "_load", counted)
    from surfsplat.model import SurfSplat

    model = SurfSplat.from_preset("tiny")
    config = OptimizeConfig(steps=2, densify=None, start=StartConfig(kind="auto", min_points=10**6, budget=500))
    options = surfsplat.CaptureOptions(holdout_every=4, optimize=config)
    scene = surfsplat.reconstruct(paths[:4], model, cameras=cameras, capture=options, progress=False)
    stats = scene.optimize_stats
    assert len(loaded) == 1 and scene.network == "ran" and scene.passes and "forward" in scene.seconds
    assert stats["start"] == "network" and "fewer than 1000000" in stats["start_reason"]
    assert stats["start_surfels"] == 500 and stats["surfels_before"] == 3 * SIZE * SIZE  # one pass of 3 views
