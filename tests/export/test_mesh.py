"""TSDF fusion and marching cubes against analytic depth maps of a sphere and a plane."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from plyfile import PlyData

from surfsplat import Cameras
from surfsplat.export.mesh import Mesh, TsdfConfig, extract_mesh, load_mesh, save_mesh, tsdf_fusion
from surfsplat.utils.checks import SurfSplatInputError

H = W = 48
FOCAL = 45.0


def _look_at(eye: torch.Tensor) -> torch.Tensor:
    z = -eye / eye.norm()  # towards the origin
    down = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    x = torch.linalg.cross(down, z)
    x = x / x.norm()
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, torch.linalg.cross(z, x), z, eye
    return c2w


def _ring(views: int, radius: float = 4.0) -> Cameras:
    angles = [2 * math.pi * k / views for k in range(views)]
    c2w = torch.stack(
        [
            _look_at(
                torch.tensor([radius * math.cos(a), radius * math.sin(a), 0.6 * math.sin(2 * a)], dtype=torch.float64)
            )
            for a in angles
        ]
    )
    K = torch.tensor([[FOCAL, 0, W / 2], [0, FOCAL, H / 2], [0, 0, 1]], dtype=torch.float64).repeat(views, 1, 1)
    return Cameras(c2w, K)


def _pixel_rays(cams: Cameras) -> torch.Tensor:
    jj, ii = torch.meshgrid(torch.arange(W) + 0.5, torch.arange(H) + 0.5, indexing="xy")
    pix = torch.stack([jj, ii, torch.ones_like(jj)], -1).double()
    return torch.einsum("ij,hwj->hwi", torch.linalg.inv(cams.K[0]), pix)  # camera z = 1


def sphere_depths(cams: Cameras, radius: float = 1.0) -> torch.Tensor:
    """Exact camera-z depth of a sphere at the origin at every pixel centre (0 where the ray misses)."""
    rays = _pixel_rays(cams)
    out = torch.zeros(len(cams), 1, H, W, dtype=torch.float64)
    for v in range(len(cams)):
        d = rays @ cams.c2w[v, :3, :3].T
        o = cams.c2w[v, :3, 3]
        a, b, c = (d * d).sum(-1), 2 * (d * o).sum(-1), (o * o).sum() - radius**2
        disc = b * b - 4 * a * c
        t = (-b - disc.clamp_min(0).sqrt()) / (2 * a)
        out[v, 0] = torch.where(disc > 0, t, torch.zeros_like(t))
    return out


@pytest.fixture(scope="module")
def sphere_mesh():
    cams = _ring(8)
    depths = sphere_depths(cams)
    colors = torch.zeros(8, 3, H, W)
    colors[:, 0] = 0.8  # a red sphere
    volume = tsdf_fusion(depths.float(), cams, colors=colors, config=TsdfConfig(resolution=48))
    return volume, extract_mesh(volume)


def test_sphere_vertices_lie_on_the_sphere(sphere_mesh):
    volume, mesh = sphere_mesh
    r = mesh.vertices.double().norm(dim=-1)
    err = (r - 1).abs() / volume.voxel_size
    # Marching cubes on a fused TSDF: sub-voxel accuracy (median a quarter voxel, worst under 1.5).
    assert float(err.median()) < 0.25
    assert float(torch.quantile(err, 0.99)) < 1.0
    assert float(err.max()) < 1.5
    assert mesh.faces.shape[0] > 1000


def test_sphere_faces_and_normals_point_outwards(sphere_mesh):
    _, mesh = sphere_mesh
    v = mesh.vertices.double()
    tri = v[mesh.faces]
    face_normals = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    outward_faces = ((face_normals * tri.mean(1)).sum(-1) > 0).double().mean()
    radial = v / v.norm(dim=-1, keepdim=True)
    cosine = (mesh.normals.double() * radial).sum(-1)
    assert float(outward_faces) > 0.99
    assert float(cosine.median()) > 0.95  # gradient normals of a 48-voxel grid: ~15 degrees typical
    assert float((cosine > 0).double().mean()) > 0.97  # the poles are seen only at grazing angles
    torch.testing.assert_close(mesh.colors[:, 0].median(), torch.tensor(0.8), atol=1e-6, rtol=0)


def test_unobserved_space_behind_the_surface_makes_no_faces():
    # One view of a fronto-parallel plane z = 2: the band behind it meets unobserved voxels, a
    # false wall would appear there at z ~ 2 + truncation without the observed-edge rule.
    cams = Cameras(
        torch.eye(4, dtype=torch.float64)[None],
        torch.tensor([[[FOCAL, 0, W / 2], [0, FOCAL, H / 2], [0, 0, 1]]], dtype=torch.float64),
    )
    depths = torch.full((1, 1, H, W), 2.0)
    lo = torch.tensor([-0.8, -0.8, 1.5], dtype=torch.float64)
    hi = torch.tensor([0.8, 0.8, 2.5], dtype=torch.float64)
    volume = tsdf_fusion(depths, cams, config=TsdfConfig(resolution=32), bounds=(lo, hi))
    mesh = extract_mesh(volume)
    torch.testing.assert_close(
        mesh.vertices[:, 2].double(), torch.full((len(mesh.vertices),), 2.0, dtype=torch.float64), atol=1e-5, rtol=0
    )
    assert mesh.normals[:, 2].max() < -0.99  # facing the camera at the origin


def test_save_mesh_ply_and_obj(tmp_path, sphere_mesh):
    _, mesh = sphere_mesh
    ply = PlyData.read(str(save_mesh(mesh, tmp_path / "m.ply")))
    assert {p.name for p in ply["vertex"].properties} == {"x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"}
    np.testing.assert_allclose(ply["vertex"]["x"], mesh.vertices[:, 0].numpy(), rtol=0, atol=0)
    faces = np.stack(ply["face"]["vertex_indices"])
    assert np.array_equal(faces, mesh.faces.numpy())
    lines = (save_mesh(mesh, tmp_path / "m.obj")).read_text().splitlines()
    assert sum(line.startswith("v ") for line in lines) == len(mesh.vertices)
    assert sum(line.startswith("f ") for line in lines) == len(mesh.faces)
    first_face = next(line for line in lines if line.startswith("f "))
    a = int(first_face.split()[1].split("//")[0])
    assert a == int(mesh.faces[0, 0]) + 1  # OBJ indices are 1-based
    with pytest.raises(SurfSplatInputError, match="expected a .ply or .obj"):
        save_mesh(mesh, tmp_path / "m.stl")


def test_interrupted_mesh_write_leaves_nothing(tmp_path, monkeypatch):
    mesh = Mesh(torch.rand(3, 3), torch.tensor([[0, 1, 2]]), torch.rand(3, 3), torch.rand(3, 3))

    def broken(self, target):
        with open(target, "wb") as f:
            f.write(b"ply\npartial")
        raise KeyboardInterrupt

    monkeypatch.setattr(PlyData, "write", broken)
    with pytest.raises(KeyboardInterrupt):
        save_mesh(mesh, tmp_path / "m.ply")
    assert list(tmp_path.iterdir()) == []


def test_fusion_input_errors():
    cams = _ring(2)
    with pytest.raises(SurfSplatInputError, match="expected 3 cameras"):
        tsdf_fusion(torch.ones(3, 1, H, W), cams)
    with pytest.raises(SurfSplatInputError, match="no valid depth sample"):
        tsdf_fusion(torch.zeros(2, 1, H, W), cams)
    with pytest.raises(SurfSplatInputError, match="valid: expected a bool tensor"):
        tsdf_fusion(torch.ones(2, 1, H, W), cams, valid=torch.ones(2, 1, H, W))


def test_load_mesh_reads_back_what_save_mesh_wrote(tmp_path, sphere_mesh):
    _, sphere_mesh = sphere_mesh
    path = save_mesh(sphere_mesh, tmp_path / "sphere.ply")
    back = load_mesh(path)
    assert torch.equal(back.vertices, sphere_mesh.vertices.float())
    assert torch.equal(back.faces, sphere_mesh.faces)
    assert torch.equal(back.normals, sphere_mesh.normals.float())
    # colours are stored as bytes: within half a step of 1/255
    assert (back.colors - sphere_mesh.colors).abs().max() <= 0.5 / 255 + 1e-6
    (tmp_path / "quads.ply").write_bytes(
        path.read_bytes().replace(b"property list uchar int vertex_indices", b"property list uchar int vertex_index")
    )
    with pytest.raises(SurfSplatInputError, match="quads.ply"):
        load_mesh(tmp_path / "quads.ply")
