"""PLY export/import in the layouts 2DGS/3DGS viewers read."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData

from surfsplat import Cameras, Gaussians
from surfsplat.export import load_ply, save_ply
from surfsplat.render import render
from surfsplat.utils.checks import SurfSplatInputError


def scene(n: int = 200, degree: int = 2, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g)
    return Gaussians(
        means=torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 2.0]),
        quats=q / q.norm(dim=-1, keepdim=True),
        scales=torch.rand(n, 2, generator=g) * 0.05 + 0.01,
        opacities=torch.rand(n, generator=g) * 0.98 + 0.01,
        sh=torch.randn(n, 3, (degree + 1) ** 2, generator=g) * 0.5,
    )


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_float64_round_trip_is_bit_exact(tmp_path, degree):
    g = scene(degree=degree)
    path = save_ply(g, tmp_path / "s.ply", precision="float64")
    back = load_ply(path)
    for name in ("means", "quats", "scales", "opacities", "sh"):
        assert torch.equal(getattr(back, name), getattr(g, name)), name


def test_float32_layout_is_what_viewers_read(tmp_path):
    g = scene(degree=2)
    path = save_ply(g, tmp_path / "s.ply")
    v = PlyData.read(str(path))["vertex"]
    names = list(v.data.dtype.names)
    expected = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    expected += [f"f_rest_{i}" for i in range(24)] + ["opacity", "scale_0", "scale_1"] + [f"rot_{i}" for i in range(4)]
    assert names == expected
    assert all(v.data.dtype[n] == np.float32 for n in names)
    # Encodings: opacity as logit, scales as log, quaternion w first, f_rest channel-major.
    i = 7
    o = float(g.opacities[i])
    assert v["opacity"][i] == pytest.approx(np.log(o / (1 - o)), rel=1e-6)
    assert v["scale_1"][i] == pytest.approx(np.log(float(g.scales[i, 1])), rel=1e-6)
    assert v["rot_0"][i] == pytest.approx(float(g.quats[i, 0]), rel=1e-6)
    assert v["f_rest_9"][i] == pytest.approx(float(g.sh[i, 1, 2]), rel=1e-6)  # colour 1, coefficient 2
    assert np.allclose(np.stack([v["nx"], v["ny"], v["nz"]], -1), g.normals.numpy(), atol=1e-6)
    back = load_ply(path)
    for name in ("means", "quats", "scales", "opacities", "sh"):
        assert torch.allclose(getattr(back, name), getattr(g, name), rtol=2e-6, atol=1e-7), name


def test_explicit_covariances_use_the_3dgs_layout_and_render_identically(tmp_path):
    g = scene(60)
    A = torch.randn(60, 3, 3, generator=torch.Generator().manual_seed(3)) * 0.03
    cov = A @ A.transpose(1, 2) + 1e-5 * torch.eye(3)
    g = g.with_explicit_covariances(cov)
    path = save_ply(g, tmp_path / "c.ply", precision="float64")
    assert "scale_2" in PlyData.read(str(path))["vertex"].data.dtype.names
    back = load_ply(path)
    assert back.explicit_covariances is not None
    assert torch.allclose(back.explicit_covariances, cov, atol=1e-7)
    K = torch.tensor([[[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]]])
    cam = Cameras(torch.eye(4)[None], K)
    a = render(g, cam, 32, 32, mode="ewa")
    b = render(back, cam, 32, 32, mode="ewa")
    assert a.alpha.max() > 0.2
    assert torch.allclose(a.color, b.color, atol=1e-5)


def test_bad_files_get_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such PLY"):
        load_ply(tmp_path / "missing.ply")
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"not a ply at all")
    with pytest.raises(SurfSplatInputError, match="not a readable PLY"):
        load_ply(junk)
    points = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    from plyfile import PlyElement

    PlyData([PlyElement.describe(points, "vertex")]).write(str(tmp_path / "points.ply"))
    with pytest.raises(SurfSplatInputError, match="missing vertex properties"):
        load_ply(tmp_path / "points.ply")
    truncated = tmp_path / "trunc.ply"
    data = save_ply(scene(50), tmp_path / "full.ply").read_bytes()
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(SurfSplatInputError, match="trunc.ply"):
        load_ply(truncated)
