"""The user-facing commands: one-line errors naming the bad file or field with exit 2, and a fast
reconstruct -> render -> export round trip with a small random network."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from plyfile import PlyData

from surfsplat.cli import main
from surfsplat.data.cameras import save_cameras
from surfsplat.data.synthetic import SyntheticDataset, SyntheticDatasetConfig
from surfsplat.export.images import write_png
from surfsplat.export.ply import SURFEL_FIELDS as PLY_SURFEL_FIELDS
from surfsplat.model import SurfSplat, save_checkpoint

SURFEL_FIELDS = {"nx", "ny", "nz", *PLY_SURFEL_FIELDS}


def _fails(argv: list[str], capsys, *needles: str) -> str:
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1, err  # one line, no traceback
    for needle in needles:
        assert needle in err, err
    return err


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """Two 32x32 views of a synthetic room, their camera file, and a random tiny checkpoint."""
    root = tmp_path_factory.mktemp("capture")
    dataset = SyntheticDataset(
        SyntheticDatasetConfig(length=1, seed=3, image_shape=(32, 32), num_target_views=1, supersample=1)
    )
    sample = dataset[0]
    names = []
    for i, image in enumerate(sample["context"]["image"]):
        write_png(root / f"view{i}.png", image)
        names.append(f"view{i}.png")
    from surfsplat import Cameras

    cams = Cameras(sample["context"]["c2w"].double(), sample["context"]["K"].double())
    save_cameras(root / "cameras.json", cams, 32, 32, names, near=0.5, far=15.0)
    torch.manual_seed(0)
    weights, _ = save_checkpoint(SurfSplat.from_preset("tiny"), root / "tiny")
    return root, weights


def test_reconstruct_render_export_round_trip(tmp_path, capture, capsys):
    root, weights = capture
    out = tmp_path / "rec"
    code = main(
        [
            "reconstruct",
            "--checkpoint",
            str(weights),
            "--images",
            str(root / "view0.png"),
            str(root / "view1.png"),
            "--cameras",
            str(root / "cameras.json"),
            "--out",
            str(out),
            "--formats",
            "ply",
            "renders",
            "mesh",
            "--frames",
            "4",
            "--mesh-resolution",
            "32",
            "--no-progress",
        ]
    )
    assert code == 0, capsys.readouterr().err
    ply = PlyData.read(str(out / "surfels.ply"))
    names = {p.name for p in ply["vertex"].properties}
    assert SURFEL_FIELDS <= names and "scale_2" not in names
    assert len(ply["vertex"].data) == 2 * 32 * 32  # one surfel per context pixel
    assert "scale_2" in {p.name for p in PlyData.read(str(out / "surfels_3dgs.ply"))["vertex"].properties}
    summary = json.loads((out / "reconstruction.json").read_text())
    assert summary["surfels"] == 2048 and summary["near"] == 0.5 and summary["far"] == 15.0
    assert (out / "renders" / "view00_color.png").is_file() and (out / "mesh.ply").is_file()
    assert not list(out.rglob(".*tmp*"))

    # The context render reproduces the input view closely (each pixel became a surfel there).
    import imageio.v3 as iio

    render = iio.imread(out / "renders" / "view00_color.png").astype(np.float64)
    source = iio.imread(root / "view0.png").astype(np.float64)
    assert np.abs(render - source).mean() < 40  # a random network: colours come from the image (SH DC init)

    code = main(
        [
            "render",
            str(out / "surfels.ply"),
            "--cameras",
            str(out / "cameras.json"),
            "--scale",
            "2",
            "--views",
            "0",
            "--out",
            str(tmp_path / "x2"),
        ]
    )
    assert code == 0
    assert iio.imread(tmp_path / "x2" / "view0_color.png").shape == (64, 64, 3)
    report = json.loads((tmp_path / "x2" / "render.json").read_text())
    assert report["width"] == 64 and report["views"][0]["coverage"] > 0.5

    # --antialiased: the filter's render, which at a quarter of the size differs from the plain one
    argv = ["render", str(out / "surfels.ply"), "--cameras", str(out / "cameras.json"), "--scale", "0.25"]
    assert main([*argv, "--views", "0", "--antialiased", "--out", str(tmp_path / "q"), "--alpha-threshold", "-1"]) == 0
    assert json.loads((tmp_path / "q" / "render.json").read_text())["antialiased"] is True
    from surfsplat.data.cameras import load_cameras
    from surfsplat.export.ply import load_ply
    from surfsplat.render import render as render_surfels

    cams = load_cameras(out / "cameras.json").cameras[:1].to(torch.float32).scaled(0.25)
    surfels = load_ply(out / "surfels.ply")
    written = iio.imread(tmp_path / "q" / "view0_color.png").astype(np.float64) / 255
    for antialiased, close in ((True, True), (False, False)):
        expected = render_surfels(surfels, cams, 8, 8, alpha_threshold=None, antialiased=antialiased).color[0]
        error = np.abs(written - expected.clamp(0, 1).permute(1, 2, 0).numpy()).max()
        assert (error <= 1 / 255 + 1e-6) == close, (antialiased, error)

    code = main(
        [
            "export",
            str(out / "surfels.ply"),
            "--cameras",
            str(out / "cameras.json"),
            "--formats",
            "mesh",
            "--out",
            str(tmp_path / "exp"),
            "--frames",
            "4",
            "--mesh-resolution",
            "24",
            "--no-progress",
        ]
    )
    assert code == 0
    mesh = PlyData.read(str(tmp_path / "exp" / "mesh.ply"))
    assert len(mesh["face"].data) > 0


def test_reconstruct_errors(tmp_path, capture, capsys):
    root, weights = capture
    base = ["reconstruct", "--checkpoint", str(weights), "--out", str(tmp_path / "o")]
    _fails(
        [*base, "--images", str(root / "view0.png"), str(root / "nope.png"), "--cameras", str(root / "cameras.json")],
        capsys,
        "nope.png",
        "image file not found",
    )
    _fails(
        [*base, "--images", str(root / "view0.png"), "--cameras", str(root / "cameras.json")],
        capsys,
        "--images",
        "at least 2",
    )
    bad = json.loads((root / "cameras.json").read_text())
    bad["frames"][1]["K"] = [[1, 2], [3, 4]]
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    _fails(
        [*base, "--images", str(root / "view0.png"), str(root / "view1.png"), "--cameras", str(tmp_path / "bad.json")],
        capsys,
        "bad.json",
        "frames[1].K",
    )
    _fails(
        [
            *base,
            "--images",
            str(root / "view0.png"),
            str(root / "view0.png"),
            "--cameras",
            str(root / "cameras.json"),
            "--size",
            "24",
            "24",
        ],
        capsys,
        "--size",
        "multiples of 16",
    )
    _fails(
        [
            "reconstruct",
            "--checkpoint",
            str(tmp_path / "missing.safetensors"),
            "--images",
            str(root / "view0.png"),
            str(root / "view1.png"),
            "--cameras",
            str(root / "cameras.json"),
        ],
        capsys,
        "missing",
        "not found",
    )
    (tmp_path / "truncated.safetensors").write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{")
    (tmp_path / "truncated.json").write_text((weights.with_suffix(".json")).read_text())
    _fails(
        [
            "reconstruct",
            "--checkpoint",
            str(tmp_path / "truncated.safetensors"),
            "--images",
            str(root / "view0.png"),
            str(root / "view1.png"),
            "--cameras",
            str(root / "cameras.json"),
            "--out",
            str(tmp_path / "o"),
        ],
        capsys,
        "truncated.safetensors",
    )
    assert not (tmp_path / "o").exists()  # nothing was written before the inputs were validated


def test_eval_errors(tmp_path, capture, capsys):
    root, weights = capture
    _fails(["eval", "--data", str(tmp_path), "--index", str(tmp_path / "i.json")], capsys, "--checkpoint or --compare")
    _fails(
        ["eval", "--checkpoint", str(weights), "--data", str(tmp_path / "none"), "--index", str(tmp_path / "i.json")],
        capsys,
        "none",
        "chunk folder not found",
    )
    (tmp_path / "i.json").write_text('{"scene": {"context": [0, 1]}}')
    _fails(
        ["eval", "--checkpoint", str(weights), "--data", str(tmp_path), "--index", str(tmp_path / "i.json")],
        capsys,
        "i.json",
        "missing key 'target'",
    )
    (tmp_path / "i.json").write_text('{"scene": {"context": [0, 1], "target": [2]}}')
    _fails(
        ["eval", "--checkpoint", str(weights), "--data", str(tmp_path), "--index", str(tmp_path / "i.json")],
        capsys,
        "no .torch chunks",
    )
    _fails(
        [
            "eval",
            "--compare",
            f"a={weights}",
            f"a={weights}",
            "--data",
            str(tmp_path),
            "--index",
            str(tmp_path / "i.json"),
        ],
        capsys,
        "names must differ",
    )


def test_render_export_view_demo_errors(tmp_path, capture, capsys):
    root, _ = capture
    _fails(
        ["render", str(tmp_path / "none.ply"), "--cameras", str(root / "cameras.json")],
        capsys,
        "none.ply",
        "no such PLY",
    )
    (tmp_path / "junk.ply").write_bytes(b"not a ply at all")
    _fails(
        ["render", str(tmp_path / "junk.ply"), "--cameras", str(root / "cameras.json")],
        capsys,
        "junk.ply",
        "not a readable PLY",
    )
    _fails(
        ["export", str(tmp_path / "junk.ply"), "--cameras", str(tmp_path / "none.json")],
        capsys,
        "none.json",
        "not found",
    )
    _fails(["view", str(tmp_path / "none.ply")], capsys, "none.ply")
    _fails(["demo", "--out", str(tmp_path / "d"), "--image-size", "40"], capsys, "--image-size", "multiple of 16")
    (tmp_path / "d" / "train").mkdir(parents=True)
    (tmp_path / "d" / "train" / "x").write_text("")
    _fails(["demo", "--out", str(tmp_path / "d")], capsys, "already holds a demo run")


def _python(code: str, **env: str) -> list[str]:
    import os
    import subprocess
    import sys

    environment = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"} | env
    run = subprocess.run([sys.executable, "-c", code], env=environment, capture_output=True, text=True, check=True)
    return run.stdout.split()


def test_the_command_line_lets_openmp_threads_sleep_unless_told_otherwise():
    import ast
    from pathlib import Path

    import surfsplat.cli

    show = "import os, sys, surfsplat.cli; print(os.environ['OMP_WAIT_POLICY'])"
    assert _python(show) == ["PASSIVE"]
    assert _python(show, OMP_WAIT_POLICY="ACTIVE") == ["ACTIVE"]  # the user's value wins
    # It is set before torch (and its OpenMP runtime) loads: the package's import loads no torch, and the
    # command line's first import from the package is `_openmp`.
    assert _python("import sys, surfsplat; print('torch' in sys.modules)") == ["False"]
    tree = ast.parse(Path(surfsplat.cli.__file__).read_text())
    first = next(n for n in tree.body if isinstance(n, ast.ImportFrom) and n.level)
    assert [a.name for a in first.names] == ["_openmp"]


def test_the_package_names_load_on_first_use():
    code = "import sys, surfsplat; n = surfsplat.Scene; print(n.__name__, 'torch' in sys.modules, len(dir(surfsplat)))"
    name, torch_loaded, _ = _python(code)
    assert (name, torch_loaded) == ("Scene", "True")
    import surfsplat

    for public in surfsplat.__all__:
        assert getattr(surfsplat, public) is not None
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        surfsplat.nothing  # noqa: B018
