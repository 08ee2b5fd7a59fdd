"""Pictures of a triangle mesh from any camera: a z-buffer rasterizer with headlight shading.

    picture = render_mesh(mesh, camera, width, height)
    picture.shaded, picture.shape, picture.depth, picture.normal, picture.mask   # [3|3|1|3|1, H, W]

Written here because none of the project's dependencies rasterizes triangles on a CPU without an
OpenGL context (trimesh and pyrender render through OpenGL; scikit-image only fills 2D polygons
without depth). The rasterizer follows the usual rules: a pixel (row i, column j) is sampled at its
centre (j + 0.5, i + 0.5), the same convention as `surfsplat.render`; a sample is covered when its
screen-space barycentric coordinates are all >= 0; depth is interpolated perspective-correctly
(inverse depth is affine in screen space) and the nearest covering triangle wins. Triangles with a
vertex at or behind the camera plane z <= near are dropped (the TSDF meshes it draws lie in front of
every camera that looks at them).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry.cameras import Cameras
from ..utils.checks import SurfSplatInputError
from .mesh import Mesh

SHAPE_GREY = 0.8  # albedo of the shape-only picture
MAX_CANDIDATES = 4_000_000  # (triangle, pixel) pairs tested at once; bounds memory (~150 MB)


@dataclass
class MeshPicture:
    """One view of a mesh."""

    shaded: Tensor  # [3, H, W] headlight-shaded vertex colours (grey without colours), black where empty
    shape: Tensor  # [3, H, W] the same shading on a uniform light grey: the geometry alone
    depth: Tensor  # [1, H, W] camera z of the visible surface, 0 where empty
    normal: Tensor  # [3, H, W] world-frame unit normal of the visible face, facing the camera
    mask: Tensor  # [1, H, W] bool, True where a triangle covers the pixel centre
    face: Tensor  # [H, W] int64 index of the visible face, -1 where empty


def render_mesh(
    mesh: Mesh,
    camera: Cameras,  # one camera
    width: int,
    height: int,
    *,
    near: float = 1e-3,
    ambient: float = 0.3,  # shading = ambient + (1 - ambient) * |cos(normal, view ray)|
) -> MeshPicture:
    """Rasterize `mesh` as seen by `camera` (OpenCV axes, K in pixels of width x height)."""
    if not isinstance(camera, Cameras) or len(camera) != 1:
        raise SurfSplatInputError("camera: expected one surfsplat.Cameras entry")
    if width < 1 or height < 1:
        raise SurfSplatInputError(f"width, height: expected positive sizes, got {width}x{height}")
    c2w = camera.c2w[0].double()
    K = camera.K[0].double()
    verts = mesh.vertices.double()
    faces = mesh.faces.long()
    cam = (verts - c2w[:3, 3]) @ c2w[:3, :3]  # world -> camera: R^T (x - t)
    z = cam[:, 2]
    uv = (cam[:, :2] / z.clamp_min(near)[:, None]) @ K[:2, :2].T + K[:2, 2]  # pixel coordinates

    keep = (z[faces] > near).all(1)
    tri = faces[keep]
    face_ids = torch.nonzero(keep).squeeze(1)
    p = uv[tri]  # [T, 3, 2]
    # Pixel index range whose centres can fall inside each triangle's box.
    lo = torch.ceil(p.amin(1) - 0.5).clamp_min(0)
    hi = torch.floor(p.amax(1) - 0.5)
    hi = torch.minimum(hi, torch.tensor([width - 1.0, height - 1.0], dtype=hi.dtype))
    box = (hi - lo + 1).clamp_min(0).long()  # [T, 2] columns, rows
    count = box[:, 0] * box[:, 1]
    nonempty = count > 0
    tri, face_ids, p, lo, box, count = (
        tri[nonempty],
        face_ids[nonempty],
        p[nonempty],
        lo[nonempty],
        box[nonempty],
        count[nonempty],
    )

    inv_z = 1.0 / z[tri]  # [T, 3]
    # Screen-space edge functions: barycentric l_k of vertex k is affine in (x, y).
    a, b, c = p[:, 0], p[:, 1], p[:, 2]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    good = area.abs() > 1e-12
    best = torch.full((height * width,), float("inf"), dtype=torch.float64)
    cand_pixel, cand_depth, cand_face = [], [], []
    offsets = torch.cumsum(count, 0)
    start = 0
    while start < len(count):
        # The next run of triangles whose candidates fit in MAX_CANDIDATES (at least one triangle).
        base = offsets[start - 1] if start else torch.tensor(0)
        stop = int(torch.searchsorted(offsets, base + MAX_CANDIDATES, right=True))
        stop = max(stop, start + 1)
        sl = slice(start, stop)
        t = torch.repeat_interleave(torch.arange(start, stop), count[sl])
        local = torch.arange(len(t)) - torch.repeat_interleave(offsets[sl] - count[sl] - base, count[sl])
        px = lo[t, 0] + (local % box[t, 0]).double()
        py = lo[t, 1] + torch.div(local, box[t, 0], rounding_mode="floor").double()
        x, y = px + 0.5, py + 0.5
        l1 = ((x - a[t, 0]) * (c[t, 1] - a[t, 1]) - (y - a[t, 1]) * (c[t, 0] - a[t, 0])) / area[t]
        l2 = ((b[t, 0] - a[t, 0]) * (y - a[t, 1]) - (b[t, 1] - a[t, 1]) * (x - a[t, 0])) / area[t]
        l0 = 1 - l1 - l2
        inside = good[t] & (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
        t, px, py = t[inside], px[inside].long(), py[inside].long()
        depth = 1.0 / (l0[inside] * inv_z[t, 0] + l1[inside] * inv_z[t, 1] + l2[inside] * inv_z[t, 2])
        pixel = py * width + px
        best.scatter_reduce_(0, pixel, depth, reduce="amin")
        cand_pixel.append(pixel)
        cand_depth.append(depth)
        cand_face.append(t)
        start = stop

    face_map = torch.full((height * width,), -1, dtype=torch.int64)
    if cand_pixel:
        pixel, depth, t = torch.cat(cand_pixel), torch.cat(cand_depth), torch.cat(cand_face)
        win = depth == best[pixel]
        # Exact depth ties (shared edges seen edge-on) go to the lowest face index: deterministic.
        winner = torch.full((height * width,), len(face_ids), dtype=torch.int64)
        winner.scatter_reduce_(0, pixel[win], t[win], reduce="amin")
        hit = winner < len(face_ids)
        face_map[hit] = face_ids[winner[hit]]
    mask = face_map >= 0
    depth_map = torch.where(mask, best, torch.zeros_like(best))

    # Flat face normals in world frame, turned towards the camera.
    v0, v1, v2 = (verts[faces[:, k]] for k in range(3))
    face_normal = F.normalize(torch.linalg.cross(v1 - v0, v2 - v0), dim=-1)
    ids = face_map.clamp_min(0)
    n = face_normal[ids]  # [HW, 3]
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij"
    )
    rays_cam = torch.stack(
        [
            (xs.flatten() + 0.5 - K[0, 2]) / K[0, 0],
            (ys.flatten() + 0.5 - K[1, 2]) / K[1, 1],
            torch.ones(height * width, dtype=torch.float64),
        ],
        -1,
    )
    rays = F.normalize(rays_cam @ c2w[:3, :3].T, dim=-1)
    cos = (n * rays).sum(-1)
    n = torch.where((cos > 0)[:, None], -n, n)
    shade = ambient + (1 - ambient) * cos.abs()
    grey = torch.full((height * width, 3), SHAPE_GREY, dtype=torch.float64)
    # [HW, 3] mean of the visible face's vertex colours
    albedo = mesh.colors.double()[faces[ids]].mean(1) if mesh.colors.numel() else grey

    def lit(colour: Tensor) -> Tensor:
        return torch.where(mask[:, None], colour * shade[:, None], torch.zeros_like(colour))

    normal = torch.where(mask[:, None], n, torch.zeros_like(n))

    def image(x: Tensor) -> Tensor:  # [HW, C] -> [C, H, W] float32
        return x.reshape(height, width, -1).permute(2, 0, 1).float().contiguous()

    return MeshPicture(
        shaded=image(lit(albedo)),
        shape=image(lit(grey)),
        depth=image(depth_map[:, None]),
        normal=image(normal),
        mask=mask.reshape(1, height, width),
        face=face_map.reshape(height, width),
    )
