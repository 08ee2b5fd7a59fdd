"""Every stage after the network runs on the device the network ran on, and computes there what it
computes on the CPU.

A `.to("cpu")` after the forward pass decides for every later stage; a CPU tensor made inside a
stage (`torch.arange(n)`, a host generator's draw) stops a CUDA run with "Expected all tensors to be
on the same device". These tests run the stages on the stand-in accelerator of
`surfsplat.testing.standin_device` (tensors that report another device, keep their values on the
CPU and refuse to meet a CPU tensor), so both fail here, on any machine:

- each stage function given device tensors returns device tensors holding exactly the values the
  CPU computes with the same (torch) renderer: fusion, compaction, refinement, the 3DGS bake, the
  closure figures and the TSDF volume and mesh;
- the refinement, the bake and the TSDF fusion wait for the device a fixed number of times, however
  many steps or views they run (a per-step `.item()` would make the host wait every step);
- `reconstruct(device=...)` with several views (two passes fused, a refinement, held-out views) and
  `Scene.save` with every output: while each stage runs, its work is on the device (an op counter
  by stage and device) and no tensor it makes on the host is larger than a few indices.
"""

from __future__ import annotations

import copy
import sys
from collections import Counter
from dataclasses import fields

import pytest
import torch
from torch.utils._pytree import tree_flatten

import surfsplat
from surfsplat.capture import FusionConfig, OptimizeConfig, RefineConfig, SurfelFusion, refine_on_views
from surfsplat.cli import main
from surfsplat.compaction import compact_surfels
from surfsplat.data.cameras import save_cameras
from surfsplat.data.synthetic import make_scene, make_trajectory, render_synthetic
from surfsplat.export.bake import BakeConfig, bake_for_viewers, fit_cameras
from surfsplat.export.flow import ExportOptions
from surfsplat.export.images import write_png
from surfsplat.export.mesh import TsdfConfig, mesh_from_renders, tsdf_fusion
from surfsplat.geometry.gaussians import Gaussians
from surfsplat.metrics.closure import closure_metrics
from surfsplat.model import SurfSplat
from surfsplat.reconstruction.pipeline import resolve_device
from surfsplat.testing.standin_device import STANDIN, StandinDevice, StandinTensor
from surfsplat.utils.checks import SurfSplatInputError

SIZE = 16  # network size of every pass: the tiny model's smallest, so the stand-in's slow ops stay few
NEAR, FAR = 0.5, 15.0


def _views(n: int, size: int):
    """(images [n, 3, size, size], Cameras) of a procedural room along a short path."""
    scene = make_scene(5)
    cams = make_trajectory(scene, torch.Generator().manual_seed(0)).cameras(torch.linspace(0, 1, n), size, size)
    return render_synthetic(scene, cams, size, size).image, cams.to(torch.float32)


@pytest.fixture(scope="module")
def model() -> SurfSplat:
    torch.manual_seed(0)
    return SurfSplat.from_preset("tiny").eval()


@pytest.fixture(scope="module")
def passes(model):
    """Two forward passes of the tiny model on the CPU, views (0, 1) and (1, 2) of three:
    [(gaussians [2 * SIZE^2], cameras [2], images [2, 3, SIZE, SIZE])]."""
    images, cams = _views(3, SIZE)
    out = []
    for members in ([0, 1], [1, 2]):
        with torch.no_grad():
            prediction = model(images[members][None], cams[torch.tensor(members)], NEAR, FAR)
        out.append((prediction.gaussians.select(0).clone(), cams[torch.tensor(members)], images[members]))
    return out


@pytest.fixture(scope="module")
def fused(passes):
    """The two passes fused on the CPU, with the three context cameras and photos."""
    fusion = SurfelFusion(FusionConfig(), backend="torch")
    for g, cams, _ in passes:
        fusion.add(g, cams, SIZE, SIZE)
    (_, cams_a, images_a), (_, cams_b, images_b) = passes
    cameras = surfsplat.Cameras(torch.cat([cams_a.c2w, cams_b.c2w[1:]]), torch.cat([cams_a.K, cams_b.K[1:]]))
    return fusion.gaussians(), cameras, torch.cat([images_a, images_b[1:]])


# ----------------------------------------------------------------------------------------- helpers
def _on(device, *values):
    """Gaussians, Cameras and tensors moved to `device`."""
    return tuple(v.to(device) for v in values)


def _host(value):
    """A device tensor (or Gaussians) read back to the CPU."""
    return value.to("cpu")


def _assert_on_device(*tensors: torch.Tensor) -> None:
    for t in tensors:
        assert isinstance(t, StandinTensor), f"a tensor of shape {tuple(t.shape)} is on {t.device}, not the device"


def _gaussian_tensors(g: Gaussians) -> dict[str, torch.Tensor]:
    return {f.name: getattr(g, f.name) for f in fields(g) if isinstance(getattr(g, f.name), torch.Tensor)}


def _assert_same_gaussians(on_device: Gaussians, on_cpu: Gaussians) -> None:
    """`on_device` lives on the device and holds exactly the CPU's values."""
    device, cpu = _gaussian_tensors(on_device), _gaussian_tensors(on_cpu)
    assert device.keys() == cpu.keys()
    _assert_on_device(*device.values())
    for name, t in device.items():
        assert torch.equal(_host(t), cpu[name]), name


def _syncs_in(dev: StandinDevice, path: str) -> int:
    """Host waits recorded at lines of one source file (e.g. "capture/fit.py")."""
    return sum(s.waits for s in dev.syncs if s.where.startswith(path))


# ----------------------------------------------------------------------------------------- the device choice
def test_resolve_device_takes_a_torch_device_and_names_bad_choices():
    assert resolve_device(torch.device("meta")) == STANDIN  # a test's stand-in accelerator
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(SurfSplatInputError, match="expected auto, cpu, cuda or a torch.device, got 'tpu'"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(SurfSplatInputError, match="no CUDA device"):
            resolve_device(torch.device("cuda", 0))


# ----------------------------------------------------------------------------------------- each stage
def test_fusion_on_the_device_keeps_what_the_cpu_keeps(passes, fused):
    on_cpu = fused[0]
    fusion = SurfelFusion(FusionConfig(), backend="torch")
    for g, cams, _ in passes:
        fusion.add(g, cams, SIZE, SIZE)
    assert fusion.stats["duplicates"] > 0  # the second pass repeats view 1: fusion decided something
    with StandinDevice() as dev:
        fusion_d = SurfelFusion(FusionConfig())  # "auto": the torch renderer off the CPU
        for g, cams, _ in passes:
            fusion_d.add(*_on(dev.device, g, cams), SIZE, SIZE)
        _assert_same_gaussians(fusion_d.gaussians(), on_cpu)
    assert fusion_d.stats == fusion.stats


def test_compaction_on_the_device_matches_the_cpu(passes):
    g, cams, _ = passes[0]
    cpu = compact_surfels(g, cams, SIZE, SIZE, 1, backend="torch")
    assert cpu.stats["output"] < cpu.stats["input"]
    with StandinDevice() as dev:
        out = compact_surfels(*_on(dev.device, g, cams), SIZE, SIZE, 1)
        _assert_same_gaussians(out.gaussians, cpu.gaussians)
        _assert_on_device(out.cells)
        assert torch.equal(_host(out.cells), cpu.cells)
    assert out.stats == cpu.stats


@pytest.fixture
def foreach_adam(monkeypatch):
    """The CPU reference steps with the for-each Adam a device runs: the CPU's fused Adam (`fit.adam`) rounds
    differently, and the device flow is checked bit for bit against the same algorithm."""
    from surfsplat.capture import fit

    monkeypatch.setattr(fit, "adam", lambda groups, device: torch.optim.Adam(groups))


def test_refinement_on_the_device_matches_the_cpu_and_reads_no_loss_per_step(fused, foreach_adam):
    g, cams, images = fused
    config = RefineConfig(steps=3, views_per_step=2)
    cpu, cpu_stats = refine_on_views(g, cams, images, SIZE, SIZE, config, backend="torch")
    assert cpu_stats["steps"] == 3 and cpu_stats["kept"] == 1.0 and cpu_stats["mse_after"] < cpu_stats["mse_before"]
    waits = {}
    for steps in (1, 3):
        with StandinDevice() as dev:
            on_device = _on(dev.device, g, cams, images)
            out, stats = refine_on_views(*on_device, SIZE, SIZE, RefineConfig(steps=steps, views_per_step=2))
            waits[steps] = Counter(s.where for s in dev.syncs if s.where.startswith("capture/fit.py"))
            if steps == 3:
                _assert_same_gaussians(out, cpu)
    assert {k: v for k, v in stats.items() if k != "seconds"} == {k: v for k, v in cpu_stats.items() if k != "seconds"}
    # the same waits at any step count (the shared fit loop's): the render size and the views' draws sent once, the colour
    # error before and after read once each
    assert waits[1] == waits[3] and sum(waits[3].values()) == 4, waits


def test_refinement_reads_its_losses_once_a_window_with_the_early_stop(fused, foreach_adam):
    g, cams, images = fused
    config = RefineConfig(steps=4, views_per_step=2, patience=2, min_improvement=0.0)
    cpu, cpu_stats = refine_on_views(g, cams, images, SIZE, SIZE, config, backend="torch")
    with StandinDevice() as dev:
        out, stats = refine_on_views(*_on(dev.device, g, cams, images), SIZE, SIZE, config)
        _assert_same_gaussians(out, cpu)
        assert _syncs_in(dev, "capture/fit.py") == 4 + 2  # and one read per window of 2 steps
    assert stats["steps"] == cpu_stats["steps"] == 4


def test_the_bake_on_the_device_matches_the_cpu_and_reads_its_losses_once_a_cycle(passes):
    g, cams, _ = passes[0]
    config = BakeConfig(steps=2, jittered_views=1, report_factors=(1,), report_views=1)
    cpu, cpu_report = bake_for_viewers(g, cams, SIZE, SIZE, config, backend="torch")
    assert cpu_report.after["context x1"].alpha > cpu_report.before["context x1"].alpha  # the bake did its work
    with StandinDevice() as dev:
        out, report = bake_for_viewers(*_on(dev.device, g, cams), SIZE, SIZE, config)
        _assert_same_gaussians(out, cpu)
        # reads in the step loop itself (its losses' .tolist() or a float() per step)
        reads = ("copy to the CPU", "scalar read (.item/bool/float/int)")
        losses_read = [s.kind for s in dev.syncs if s.where.endswith("(bake_for_viewers)") and s.kind in reads]
    assert report.losses == cpu_report.losses and report.best_step == cpu_report.best_step
    assert report.before == cpu_report.before and report.after == cpu_report.after
    assert losses_read == ["copy to the CPU"]  # two steps within a cycle of four probe views: read once


def test_the_bake_jitters_the_probe_cameras_on_the_device_as_on_the_cpu(passes):
    _, cams, _ = passes[0]
    config = BakeConfig(nearby_views=1, jittered_views=2)
    cpu = fit_cameras(cams, config, 3.0)
    assert len(cpu) == 2 + 1 + 4
    with StandinDevice() as dev:
        probes = fit_cameras(cams.to(dev.device), config, 3.0)
        _assert_on_device(probes.c2w, probes.K)
        assert torch.equal(_host(probes.c2w), cpu.c2w) and torch.equal(_host(probes.K), cpu.K)


def test_closure_figures_on_the_device_match_the_cpu(fused):
    g, cams, _ = fused
    cpu = closure_metrics(g, cams, SIZE, SIZE, (1, 2), backend="torch")
    with StageOps() as dev:
        out = closure_metrics(*_on(dev.device, g, cams), SIZE, SIZE, (1, 2))
        _assert_stages_on_device(dev, ["closure"])  # the per-surfel figures too, not only the renders
    assert out == cpu and 0 < cpu.mean_alpha[1] <= 1


def test_tsdf_fusion_runs_on_the_device_without_a_host_wait_per_view():
    images, cams = _views(4, 24)
    scene = make_scene(5)
    depth = render_synthetic(scene, cams.to(torch.float64), 24, 24).depth.float()
    depth = depth if depth.dim() == 4 else depth[:, None]
    valid = depth > 0
    config = TsdfConfig(resolution=24)
    cpu = tsdf_fusion(depth, cams, colors=images, valid=valid, config=config)
    cpu_mesh = mesh_from_renders(depth, valid.float(), images, cams, config)
    assert float(cpu.weight.max()) == 4 and len(cpu_mesh.faces) > 100
    waits = {}
    for views in (2, 4):
        with StandinDevice() as dev:
            d, c, v = _on(dev.device, depth[:views], images[:views], valid[:views])
            volume = tsdf_fusion(d, cams[:views].to(dev.device), colors=c, valid=v, config=config)
            waits[views] = _syncs_in(dev, "export/mesh.py")
            if views == 4:
                _assert_on_device(volume.tsdf, volume.weight, volume.color, volume.origin)
                for name in ("tsdf", "weight", "color", "origin"):
                    assert torch.equal(_host(getattr(volume, name)), getattr(cpu, name)), name
                mesh = mesh_from_renders(d, v.float(), c, cams.to(dev.device), config)
                _assert_on_device(mesh.vertices, mesh.faces, mesh.normals, mesh.colors)
                for name in ("vertices", "faces", "normals", "colors"):
                    assert torch.equal(_host(getattr(mesh, name)), getattr(cpu_mesh, name)), name
    assert waits[2] == waits[4]  # the bounds and the grid size are read; the views add no wait


# ----------------------------------------------------------------------------------------- the whole flow
# (source file, function or None for any): the stage whose work an op is; the outermost one counts,
# so a stage's own renders are its work
STAGES = {
    ("capture/fusion.py", None): "fusion",
    ("capture/refine.py", "refine_on_views"): "refine",
    ("reconstruction/scene_fit.py", "optimize_scene"): "optimize",
    ("compaction/", None): "compaction",
    ("reconstruction/scene.py", "score_holdout"): "held-out scores",
    ("metrics/closure.py", "closure_metrics"): "closure",
    ("export/bake.py", "bake_for_viewers"): "bake",
    ("export/flow.py", "render_frames"): "renders",
    ("export/mesh.py", "tsdf_fusion"): "mesh",
}
HOST_READS = {"aten.resolve_conj.default", "aten.resolve_neg.default", "aten.lift_fresh.default"}
SMALL = 32  # the largest tensor a stage may make on the host: a few indices of views, a seeded draw


class StageOps(StandinDevice):
    """The stand-in device, counting the tensors each stage's ops make, by device, and keeping the
    largest each stage makes on the host."""

    def __init__(self) -> None:
        super().__init__()
        self.made: Counter = Counter()  # (stage, "device" | "host") -> tensors made
        self.largest_on_host: dict[str, tuple[int, str]] = {}  # stage -> (elements, op)

    def dispatch(self, func, args, kwargs):
        out = super().dispatch(func, args, kwargs)
        stage = _stage()
        if stage is not None:
            for t in tree_flatten(out)[0]:
                if not isinstance(t, torch.Tensor):
                    continue
                on_device = isinstance(t, StandinTensor)
                self.made[(stage, "device" if on_device else "host")] += 1
                if not on_device and str(func) not in HOST_READS:  # reading a device tensor is not host work
                    self.largest_on_host[stage] = max(self.largest_on_host.get(stage, (0, "")), (t.numel(), str(func)))
        return out


def _stage() -> str | None:
    frame, found = sys._getframe(2), None
    while frame is not None:
        path = frame.f_code.co_filename.replace("\\", "/")
        if "/surfsplat/" in path:
            for (file, function), stage in STAGES.items():
                if file in path and function in (None, frame.f_code.co_name):
                    found = stage
        frame = frame.f_back
    return found


def _assert_stages_on_device(dev: StageOps, stages: list[str]) -> None:
    for stage in stages:
        assert dev.made[(stage, "device")] > 100, f"{stage}: {dev.made[(stage, 'device')]} tensors on the device"
        size, op = dev.largest_on_host.get(stage, (0, ""))
        assert size <= SMALL, f"{stage} made a tensor of {size} elements on the host ({op})"


@pytest.fixture(scope="module")
def five_views(tmp_path_factory):
    root = tmp_path_factory.mktemp("views")
    images, cams = _views(5, 32)
    paths = [write_png(root / f"v{i}.png", image) for i, image in enumerate(images)]
    save_cameras(root / "cameras.json", cams, 32, 32, [p.name for p in paths], near=NEAR, far=FAR)
    return paths, root / "cameras.json"


CAPTURE = surfsplat.CaptureOptions(
    views_per_pass=2, holdout_every=4, refine=RefineConfig(steps=2), optimize=OptimizeConfig(steps=0)
)


def test_reconstruct_runs_fusion_refinement_and_held_out_scores_on_its_device(five_views, model):
    paths, cameras = five_views
    with StageOps() as dev:
        scene = surfsplat.reconstruct(
            paths,
            copy.deepcopy(model),  # reconstruct moves a model it is given to the device
            cameras=cameras,
            device=dev.device,
            size=(SIZE, SIZE),
            capture=CAPTURE,
            progress=False,
        )
        assert scene.device == STANDIN
        _assert_on_device(*_gaussian_tensors(scene.gaussians).values(), scene.cameras.c2w, scene.cameras.K)
        _assert_on_device(scene.holdout.cameras.c2w, scene.holdout.images)
        _assert_stages_on_device(dev, ["fusion", "refine", "held-out scores"])
    assert scene.fusion_stats["passes"] == 2 and scene.fusion_stats["duplicates"] > 0
    assert scene.refine_stats["steps"] == 2 and scene.holdout.names == ["v0.png", "v4.png"]
    assert all(0 < p < 60 for p in scene.holdout.psnr) and all(0 <= c <= 1 for c in scene.holdout.coverage)


def _from_the_network(**fields) -> OptimizeConfig:
    """The optimizer from the network's surfels: COLMAP's start reads the photos on the host (it writes
    them for SIFT), which the stage checks below would count."""
    from surfsplat.capture.starts import StartConfig

    return OptimizeConfig(start=StartConfig(kind="network"), **fields)


def test_reconstruct_optimizes_every_surfel_on_its_device(five_views, model):
    paths, cameras = five_views
    options = surfsplat.CaptureOptions(
        views_per_pass=2, holdout_every=4, optimize=_from_the_network(steps=3, prunings=1)
    )
    with StageOps() as dev:
        scene = surfsplat.reconstruct(
            paths, copy.deepcopy(model), cameras=cameras, device=dev.device, size=(SIZE, SIZE), capture=options,
            progress=False,
        )  # fmt: skip
        _assert_on_device(*_gaussian_tensors(scene.gaussians).values())
        _assert_stages_on_device(dev, ["fusion", "optimize"])  # it scores the held-out views before and after
    assert scene.optimize_stats["steps"] == 3 and not scene.refine_stats
    assert scene.holdout.before is not None and all(0 < p < 60 for p in scene.holdout.psnr)


def test_reconstruct_compacts_each_pass_on_its_device(five_views, model):
    paths, cameras = five_views
    no_refine = surfsplat.CaptureOptions(
        views_per_pass=2, refine=RefineConfig(steps=0), optimize=OptimizeConfig(steps=0)
    )
    with StageOps() as dev:
        scene = surfsplat.reconstruct(
            paths[:3], copy.deepcopy(model), cameras=cameras, device=dev.device, size=(SIZE, SIZE), compact=1,
            capture=no_refine, progress=False,
        )  # fmt: skip
        _assert_on_device(scene.gaussians.means)
        _assert_stages_on_device(dev, ["compaction", "fusion"])
    assert scene.compact_stats["output"] < scene.compact_stats["input"] == 2 * 2 * SIZE * SIZE


def test_a_scene_moved_to_the_device_saves_every_output_from_there(five_views, model, tmp_path):
    paths, cameras = five_views
    scene = surfsplat.reconstruct(paths, model, cameras=cameras, size=(SIZE, SIZE), capture=CAPTURE, progress=False)
    options = ExportOptions(
        path_frames=3,
        turntable_frames=2,
        mesh_resolution=16,
        progress=False,
        bake=BakeConfig(steps=2, report_factors=(1,), report_views=2),
    )
    with StageOps() as dev:
        moved = scene.to(dev.device)
        assert moved.device == STANDIN and scene.device == torch.device("cpu")  # a new scene; this one stays
        _assert_on_device(moved.holdout.images, moved.cameras.K)
        written = moved.save(tmp_path / "out", options=options)
        _assert_stages_on_device(dev, ["closure", "bake", "renders", "mesh"])
    for name in ("surfels.ply", "surfels_3dgs.ply", "mesh.ply", "path.mp4", "turntable.mp4", "reconstruction.json"):
        assert (tmp_path / "out" / name).stat().st_size > 0, name
    assert written["context renders"] == tmp_path / "out" / "renders"
    # the surfels written from the device are the CPU scene's, byte for byte
    scene.save(tmp_path / "cpu", options=ExportOptions(formats=("ply",), bake=None, progress=False))
    assert (tmp_path / "out" / "surfels.ply").read_bytes() == (tmp_path / "cpu" / "surfels.ply").read_bytes()


def test_a_saved_scene_is_optimized_on_the_device(five_views, model, tmp_path):
    from surfsplat.reconstruction.scene_fit import optimize_saved

    paths, cameras = five_views
    no_fit = surfsplat.CaptureOptions(optimize=OptimizeConfig(steps=0))
    scene = surfsplat.reconstruct(paths[:3], model, cameras=cameras, size=(SIZE, SIZE), capture=no_fit, progress=False)
    scene.save(tmp_path / "scene", options=ExportOptions(formats=("ply",), bake=None, progress=False))
    config = _from_the_network(steps=2)
    with StageOps() as dev:
        optimized, _ = optimize_saved(
            tmp_path / "scene", tmp_path / "out", config, formats=("ply",), bake=False, device=dev.device
        )
        assert optimized.device == STANDIN
        _assert_stages_on_device(dev, ["optimize"])
    assert optimized.optimize_stats["steps"] == 2 and (tmp_path / "out" / "surfels.ply").is_file()


def test_export_and_render_commands_take_a_device(five_views, model, tmp_path, capsys):
    paths, cameras = five_views
    scene = surfsplat.reconstruct(paths[:2], model, cameras=cameras, size=(SIZE, SIZE), progress=False)
    scene.save(tmp_path / "scene", options=ExportOptions(formats=("ply",), bake=None, progress=False))
    ply, cams = tmp_path / "scene" / "surfels.ply", tmp_path / "scene" / "cameras.json"
    export = ["export", str(ply), "--cameras", str(cams), "--formats", "ply", "--raw-3dgs", "--no-progress"]
    render = ["render", str(ply), "--cameras", str(cams), "--views", "0"]
    optimize = ["optimize", str(tmp_path / "scene"), "--optimize-steps", "1", "--formats", "ply", "--raw-3dgs"]
    optimize += ["--no-progress"]
    assert main([*export, "--device", "cpu", "--out", str(tmp_path / "e")]) == 0, capsys.readouterr().err
    assert main([*render, "--device", "cpu", "--out", str(tmp_path / "r")]) == 0, capsys.readouterr().err
    assert main([*optimize, "--device", "cpu", "--out", str(tmp_path / "o")]) == 0, capsys.readouterr().err
    assert (tmp_path / "e" / "surfels_3dgs.ply").is_file() and (tmp_path / "r" / "v0_color.png").is_file()
    assert (tmp_path / "o" / "surfels.ply").is_file()
    if not torch.cuda.is_available():  # the choice reaches the library, which names what is missing
        for argv in (export, render, optimize):
            assert main([*argv, "--device", "cuda", "--out", str(tmp_path / "x")]) != 0
            assert "no CUDA device" in capsys.readouterr().err


def test_the_optimizer_grows_and_prunes_on_its_device(five_views, model):
    """Densification (the screen-space gradient, clones, splits, Adam's rows) runs where the surfels are
    (the splits' seeded samples are drawn on the host, a few values a surfel every hundred steps)."""
    from surfsplat.capture.densify import DensifyConfig

    paths, cameras = five_views
    grow = DensifyConfig(start=0.0, stop=1.0, every=2, grad_threshold=1e-12, budget=10**6)
    config = _from_the_network(steps=4, densify=grow, levels=())
    options = surfsplat.CaptureOptions(views_per_pass=2, holdout_every=4, optimize=config)
    with StageOps() as dev:
        scene = surfsplat.reconstruct(
            paths, copy.deepcopy(model), cameras=cameras, device=dev.device, size=(SIZE, SIZE), capture=options,
            progress=False,
        )  # fmt: skip
        _assert_on_device(*_gaussian_tensors(scene.gaussians).values())
    grown = sum(h.get("cloned", 0) + h.get("split", 0) for h in scene.optimize_stats["densify"])
    assert grown > 0 and scene.optimize_stats["surfels_after"] > scene.optimize_stats["start_surfels"] - 1
