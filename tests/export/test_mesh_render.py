"""The mesh rasterizer against closed forms: coverage of pixel centres, perspective-correct depth
of a tilted plane, camera-facing normals, occlusion order and chunking."""

from __future__ import annotations

import math

import pytest
import torch

from surfsplat.export import mesh_render
from surfsplat.export.mesh import Mesh
from surfsplat.export.mesh_render import render_mesh
from surfsplat.geometry.cameras import Cameras

F, C, SIZE = 40.0, 16.0, 32


def _camera() -> Cameras:
    K = torch.tensor([[F, 0.0, C], [0.0, F, C], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Cameras(torch.eye(4, dtype=torch.float64)[None], K[None])


def _quad(x0, x1, y0, y1, z_of, color=(0.5, 0.5, 0.5)) -> Mesh:
    """Two triangles spanning [x0, x1] x [y0, y1] on the surface z = z_of(x, y)."""
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    verts = torch.tensor([(x, y, z_of(x, y)) for x, y in corners], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    return Mesh(verts.float(), faces, torch.zeros(4, 3), torch.tensor([color] * 4))


def _merge(*meshes: Mesh) -> Mesh:
    offset, faces = 0, []
    for m in meshes:
        faces.append(m.faces + offset)
        offset += len(m.vertices)
    cat = lambda name: torch.cat([getattr(m, name) for m in meshes])  # noqa: E731
    return Mesh(cat("vertices"), torch.cat(faces), cat("normals"), cat("colors"))


def _centres() -> tuple[torch.Tensor, torch.Tensor]:
    ys, xs = torch.meshgrid(
        torch.arange(SIZE, dtype=torch.float64), torch.arange(SIZE, dtype=torch.float64), indexing="ij"
    )
    return xs + 0.5, ys + 0.5


def test_fronto_parallel_square_covers_exactly_the_pixel_centres_inside_it() -> None:
    x0, x1, y0, y1, z = -0.21, 0.33, -0.13, 0.27, 2.0
    picture = render_mesh(_quad(x0, x1, y0, y1, lambda x, y: z), _camera(), SIZE, SIZE)
    u, v = _centres()
    inside = (u > F * x0 / z + C) & (u < F * x1 / z + C) & (v > F * y0 / z + C) & (v < F * y1 / z + C)
    assert inside.sum() > 50
    assert torch.equal(picture.mask[0], inside)
    assert torch.allclose(picture.depth[0][inside], torch.tensor(z), atol=1e-6)
    assert (picture.depth[0][~inside] == 0).all()
    # The face normal is +-z; facing the camera means -z.
    assert torch.allclose(picture.normal[:, inside].T, torch.tensor([0.0, 0.0, -1.0]), atol=1e-6)
    # Same lighting on both pictures: the shape picture is the 0.5 grey quad's shading at albedo 0.8.
    assert torch.allclose(picture.shape, picture.shaded * (mesh_render.SHAPE_GREY / 0.5), atol=1e-6)
    assert (picture.shape[:, ~inside] == 0).all() and (picture.shape[:, inside] > 0.2).all()


def test_tilted_plane_depth_is_perspective_correct_at_every_pixel_centre() -> None:
    slope = 0.5
    plane = lambda x, y: 2.0 + slope * x  # noqa: E731
    picture = render_mesh(_quad(-1.0, 1.0, -1.0, 1.0, plane), _camera(), SIZE, SIZE)
    u, v = _centres()
    xn = (u - C) / F
    truth = 2.0 / (1 - slope * xn)  # ray t * (xn, yn, 1) meets z = 2 + slope * x
    mask = picture.mask[0]
    assert mask.float().mean() > 0.9
    err = (picture.depth[0][mask].double() - truth[mask]).abs() / truth[mask]
    assert float(err.max()) < 1e-6  # affine (not perspective-correct) depth would be off by ~1e-2
    n = torch.tensor([slope, 0.0, -1.0]) / math.hypot(slope, 1.0)
    assert torch.allclose(picture.normal[:, mask].T, n, atol=1e-6)


@pytest.mark.parametrize("near_first", [True, False])
def test_the_nearest_surface_wins_whatever_the_face_order(near_first: bool) -> None:
    near = _quad(-0.3, 0.2, -0.3, 0.2, lambda x, y: 2.0, color=(1.0, 0.0, 0.0))
    far = _quad(-0.1, 0.6, -0.1, 0.6, lambda x, y: 3.0, color=(0.0, 0.0, 1.0))
    mesh = _merge(near, far) if near_first else _merge(far, near)
    picture = render_mesh(mesh, _camera(), SIZE, SIZE)
    u, v = _centres()
    in_near = (u > F * -0.3 / 2 + C) & (u < F * 0.2 / 2 + C) & (v > F * -0.3 / 2 + C) & (v < F * 0.2 / 2 + C)
    in_far = (u > F * -0.1 / 3 + C) & (u < F * 0.6 / 3 + C) & (v > F * -0.1 / 3 + C) & (v < F * 0.6 / 3 + C)
    assert (in_near & in_far).sum() > 10
    assert torch.allclose(picture.depth[0][in_near], torch.tensor(2.0))
    assert torch.allclose(picture.depth[0][in_far & ~in_near], torch.tensor(3.0))
    red = picture.shaded[0] > 0.5
    assert torch.equal(red, in_near)


def test_chunked_rasterization_matches_one_pass(monkeypatch) -> None:
    mesh = _quad(-1.0, 1.0, -1.0, 1.0, lambda x, y: 2.0 + 0.3 * x - 0.2 * y)
    whole = render_mesh(mesh, _camera(), SIZE, SIZE)
    monkeypatch.setattr(mesh_render, "MAX_CANDIDATES", 100)
    chunked = render_mesh(mesh, _camera(), SIZE, SIZE)
    assert torch.equal(whole.depth, chunked.depth) and torch.equal(whole.face, chunked.face)


def test_triangles_behind_the_camera_are_dropped() -> None:
    behind = _quad(-0.5, 0.5, -0.5, 0.5, lambda x, y: -1.0)
    picture = render_mesh(behind, _camera(), SIZE, SIZE)
    assert not picture.mask.any()
