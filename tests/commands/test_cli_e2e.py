"""End to end (slow): the demo with a reduced budget, then its checkpoint on real DTU views through
reconstruct, eval over chunks built from the sample data (the full samples where present, else the
reduced copy in tests/data), render at x4, export and the viewer."""

from __future__ import annotations

import json
import re
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from plyfile import PlyData

from surfsplat.cli import main
from surfsplat.data.chunks import scene_to_example, write_chunks
from surfsplat.data.load import load_scene
from surfsplat.export.ply import SURFEL_FIELDS as PLY_SURFEL_FIELDS
from surfsplat.model.pretrained import describe

pytestmark = pytest.mark.slow

SURFEL_FIELDS = {*PLY_SURFEL_FIELDS}


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "--out", str(out), "--quick"]) == 0
    return out


def _nontrivial_image(path: Path) -> None:
    pixels = iio.imread(path).astype(np.float64)
    assert pixels.ndim == 3 and min(pixels.shape[:2]) >= 16, path
    assert pixels[..., :3].std() > 5, f"{path} is (nearly) constant"


def test_demo_writes_report_metrics_ply_videos_mesh(demo):
    metrics = json.loads((demo / "metrics.json").read_text())
    shipped, trained, untrained = (
        metrics["evaluation"][name] for name in ("tiny-synthetic (shipped)", "tiny, 6 steps here", "tiny, untrained")
    )
    for s in ("x1", "x2", "x4"):
        assert 5 < trained["vs_bicubic_upsampled_truth"]["mean"][s]["psnr"] < 60
        assert 5 < trained["vs_native_truth"][s]["psnr"] < 60
        assert trained["vs_bicubic_upsampled_truth"]["mean"][s]["lpips"] is None
    # Geometry against the exact truth: the shipped model's surface is far closer than the untrained one's.
    ship, raw = shipped["geometry"]["mean"], untrained["geometry"]["mean"]
    assert ship["abs_rel"] < 0.5 * raw["abs_rel"] and ship["median_deg"] < raw["median_deg"] - 10
    assert ship["surfels_chamfer"] < 0.5 * raw["surfels_chamfer"]
    assert metrics["lpips"].startswith("LPIPS unavailable: ")
    assert metrics["train"]["steps"] >= 1 and metrics["wall_seconds"]["total"] > 0

    html = (demo / "report.html").read_text()
    sources = re.findall(r'<(?:img|video) src="([^"]+)"', html)
    assert any(s.endswith("_grid.png") for s in sources) and any(s.endswith(".mp4") for s in sources)
    assert any(s.endswith("training_curve.svg") for s in sources)
    assert any(s.endswith("novel_view_grid.png") for s in sources)
    # The exported 3DGS PLY as standard viewers composite it, baked to our picture.
    assert any(s.endswith("viewer_export_grid.png") for s in sources)
    bake = json.loads((demo / "scene" / "surfels_3dgs.json").read_text())
    assert bake["after"]["context x1"]["alpha"] > max(0.95, bake["before"]["context x1"]["alpha"])
    assert f"{bake['after']['context x1']['psnr']:.1f} dB" in html
    assert any(s.endswith("_depth_error.png") for s in sources) and any(
        s.endswith("_normal_error.png") for s in sources
    )
    assert "What the numbers say" in html and f"median normal error {ship['median_deg']:.1f} deg" in html
    assert describe("tiny-synthetic")["summary"] in html  # how the shipped model was trained, from its metadata
    for src in sources:
        path = demo / src
        assert path.is_file(), src
        if src.endswith(".png"):
            _nontrivial_image(path)
        elif src.endswith(".svg"):
            assert "<polyline" in path.read_text()
        else:
            assert path.stat().st_size > 1000
    assert "LPIPS unavailable" in html

    ply = PlyData.read(str(demo / "scene" / "surfels.ply"))
    assert SURFEL_FIELDS <= {p.name for p in ply["vertex"].properties}
    assert len(ply["vertex"].data) == 2 * 32 * 32
    mesh = PlyData.read(str(demo / "scene" / "mesh.ply"))
    assert len(mesh["face"].data) > 10
    frames = iio.imread(demo / "scene" / "turntable.mp4", plugin="FFMPEG")
    assert frames.shape[0] == 8 and frames.std() > 5
    assert not list(demo.rglob(".*tmp*"))  # nothing half-written left behind


def test_reconstruct_two_dtu_views_with_the_demo_checkpoint(demo, preferred_samples, tmp_path):
    scan, folder = preferred_samples.root / "dtu_scan24", preferred_samples.dtu_images
    out = tmp_path / "dtu"
    images = [str(scan / folder / "000000.png"), str(scan / folder / "000001.png")]
    code = main(
        [
            "reconstruct",
            "--checkpoint",
            str(demo / "train"),
            "--images",
            *images,
            "--cameras",
            str(scan),
            "--images-folder",
            folder,
            "--size",
            "96",
            "128",
            "--out",
            str(out),
            "--frames",
            "8",
            "--mesh-resolution",
            "48",
            "--no-progress",
        ]
    )
    assert code == 0
    ply = PlyData.read(str(out / "surfels.ply"))
    assert SURFEL_FIELDS <= {p.name for p in ply["vertex"].properties}
    assert len(ply["vertex"].data) == 2 * 96 * 128
    summary = json.loads((out / "reconstruction.json").read_text())
    assert summary["size"] == [96, 128]
    assert 1.5 < summary["near"] < summary["far"] < 5  # DTU's bounds in the normalized sphere frame
    for name in ("view00_color.png", "view00_depth.png", "view00_normal.png"):
        _nontrivial_image(out / "renders" / name)
    assert iio.imread(out / "path.mp4", plugin="FFMPEG").shape[0] == 8
    assert len(PlyData.read(str(out / "mesh.ply"))["face"].data) > 0

    # render at x4 from the saved reconstruction
    code = main(
        [
            "render",
            str(out / "surfels.ply"),
            "--cameras",
            str(out / "cameras.json"),
            "--scale",
            "4",
            "--views",
            "1",
            "--out",
            str(tmp_path / "x4"),
        ]
    )
    assert code == 0
    assert iio.imread(tmp_path / "x4" / "000001_color.png").shape == (384, 512, 3)

    # the viewer on the reconstruction folder, as a person opens it
    from surfsplat.viewer import SurfelViewer, load_viewer_scene
    from tests.helpers.browser import Browser, chromium

    def covered(image: np.ndarray) -> float:  # left of the panel, below the software-WebGL notice
        return float((np.abs(image[170:, :450].astype(int) - image[-5, 5].astype(int)).sum(-1) > 30).mean())

    exe = chromium()
    viewer = SurfelViewer(port=0)
    try:
        viewer.show(load_viewer_scene(out, viewer.progress))
        assert len(viewer.splats.centers) == 2 * 96 * 128 and len(viewer.frustums) == 2 and viewer.mesh is not None
        with Browser(exe, viewer.url, 800, 600) as browser:
            shot = browser.wait_for(lambda image: covered(image) > 0.25)
    finally:
        viewer.stop()
    iio.imwrite(tmp_path / "viewer.png", shot)
    assert covered(shot) > 0.25


def test_eval_over_chunks_built_from_dtu(demo, preferred_samples, tmp_path):
    scene = load_scene(preferred_samples.root / "dtu_scan24", images=preferred_samples.dtu_images)
    scene = scene.select([0, 1, 2, 3, 4])
    write_chunks([scene_to_example(scene, key="scan24", image_format="png")], tmp_path / "chunks")
    # MVSplat's DTU index style: several entries per scene as key_NN (one of them excluded with null).
    index = {
        "scan24_00": {"context": [0, 2], "target": [1, 3]},
        "scan24_01": None,
        "scan99": {"context": [0, 1], "target": [2]},
    }
    (tmp_path / "index.json").write_text(json.dumps(index))
    near, far = float(scene.near.min()), float(scene.far.max())
    code = main(
        [
            "eval",
            "--compare",
            f"demo={demo / 'train'}",
            f"demo w/o FAB={demo / 'train'}:opacity_max=1.0",
            "--data",
            str(tmp_path / "chunks"),
            "--index",
            str(tmp_path / "index.json"),
            "--size",
            "96",
            "128",
            "--near",
            str(near),
            "--far",
            str(far),
            "--out",
            str(tmp_path / "eval"),
            "--no-progress",
        ]
    )
    assert code == 0
    document = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert document["entries"] == {
        "evaluated_per_model": 1,
        "excluded_null": 1,
        "scenes_not_in_index": 0,
        "missing_from_data": 1,
    }
    full, ablated = document["models"]["demo"], document["models"]["demo w/o FAB"]
    assert full["num_images"] == 2 and set(full["mean"]) == {"x1", "x2", "x4"}
    assert full["mean"]["x1"]["psnr"] != ablated["mean"]["x1"]["psnr"]  # alpha normalization changes the render
    table = (tmp_path / "eval" / "table.txt").read_text()
    assert "96x128 (Standard)" in table and "192x256 (HRRC)" in table and "384x512 (HRRC)" in table
    assert "LPIPS unavailable" in table
    rows = (tmp_path / "eval" / "per_scene.csv").read_text().splitlines()
    assert len(rows) == 1 + 2 * 3  # header + models x factors (one entry)
