"""Meshes from rendered depth: TSDF fusion (Curless and Levoy 1996) and marching cubes.

    volume = tsdf_fusion(depths, cameras, colors=images, valid=alphas > 0.5)
    mesh = extract_mesh(volume)            # scikit-image's Lewiner marching cubes at level 0
    save_mesh(mesh, "scene.ply")           # or .obj

2DGS extracts meshes the same way: render depth of the surfels from many views, fuse the depth
maps into a truncated signed distance volume, take its zero level set. Per voxel centre x and view:
z = camera depth of x, d = rendered depth at the pixel x projects to (nearest pixel, centre at
j + 0.5), sdf = d - z. Views where x lies more than the truncation behind the surface (sdf < -trunc)
say nothing about x (it is occluded); the others add min(1, sdf / trunc) with weight 1 to a running
mean. Only faces on grid edges whose two ends were observed are kept, so the unobserved space
behind surfaces does not close the mesh with a false wall.

Device: the fusion runs where the depth maps are (a GPU's renders are fused on the GPU, each view
one pass over the voxels without a host wait); marching cubes is scikit-image's, so the volume goes
to the host for it, and the mesh comes back to the volume's device.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement, PlyParseError
from torch import Tensor

from ..geometry.cameras import Cameras
from ..utils.atomic import atomic_path
from ..utils.checks import SurfSplatInputError, check_tensor


@dataclass(frozen=True)
class TsdfConfig:
    """How depth maps are fused."""

    resolution: int = 128  # voxels along the longest side of the bounding box
    truncation_voxels: float = 3.0  # truncation band half-width, in voxels
    margin: float = 0.05  # bounding box growth on every side, as a fraction of its extent
    bounds_quantile: float = 0.01  # box from the [q, 1 - q] quantiles of the observed points (outliers out)
    max_voxels: int = 8_000_000  # refuse volumes larger than this (memory: ~40 bytes per voxel)


@dataclass
class TsdfVolume:
    """A fused volume on a regular grid; voxel (i, j, k) is centred at origin + ((i, j, k) + 0.5) * voxel_size."""

    tsdf: Tensor  # [X, Y, Z] in [-1, 1], 1 where unobserved
    weight: Tensor  # [X, Y, Z] number of views that observed the voxel
    color: Tensor  # [X, Y, Z, 3] mean colour of the observations (0 where unobserved)
    origin: Tensor  # [3] corner of the grid (float64)
    voxel_size: float


@dataclass
class Mesh:
    vertices: Tensor  # [M, 3] world positions (float32)
    faces: Tensor  # [F, 3] int64 vertex indices, counter-clockwise seen from outside the surface
    normals: Tensor  # [M, 3] unit normals
    colors: Tensor  # [M, 3] in [0, 1]


def fusion_bounds(
    depths: Tensor, cameras: Cameras, valid: Tensor, quantile: float = 0.01, margin: float = 0.05
) -> tuple[Tensor, Tensor]:
    """(low [3], high [3]) corners of a box around the back-projected valid depth samples."""
    points = backproject(depths, cameras, valid)
    if points.shape[0] == 0:
        raise SurfSplatInputError("depths: no valid depth sample to fuse")
    q = torch.tensor([quantile, 1 - quantile], dtype=torch.float64, device=points.device)
    sample = points
    if len(points) > 1_000_000:  # torch.quantile's limit; below it the order would not change a quantile
        # drawn on the host's generator (the same sample on every device), the indices sent once
        pick = torch.randperm(len(points), generator=torch.Generator().manual_seed(0))[:1_000_000]
        sample = points[pick.to(points.device)]
    lo, hi = torch.quantile(sample, q, dim=0)
    pad = (hi - lo).clamp_min(1e-6) * margin
    return lo - pad, hi + pad


def backproject(depths: Tensor, cameras: Cameras, valid: Tensor) -> Tensor:
    """World points [P, 3] (float64) of the valid pixels of depths [V, 1, H, W]."""
    v, _, h, w = depths.shape
    K_inv = torch.linalg.inv(cameras.K.to(depths.device, torch.float64))
    f64 = {"dtype": torch.float64, "device": depths.device}
    jj, ii = torch.meshgrid(torch.arange(w, **f64) + 0.5, torch.arange(h, **f64) + 0.5, indexing="xy")
    pix = torch.stack([jj, ii, torch.ones_like(jj)], -1)  # [H, W, 3]
    rays = torch.einsum("vij,hwj->vhwi", K_inv, pix)  # camera z = 1
    cam = rays * depths.to(torch.float64)[:, 0, :, :, None]
    c2w = cameras.c2w.to(depths.device, torch.float64)
    world = torch.einsum("vij,vhwj->vhwi", c2w[:, :3, :3], cam) + c2w[:, None, None, :3, 3]
    return world[valid[:, 0]]


def tsdf_fusion(
    depths: Tensor,  # [V, 1, H, W] camera-z depth (0 = no measurement)
    cameras: Cameras,  # V cameras, K in pixels of the depth maps
    colors: Tensor | None = None,  # [V, 3, H, W] in [0, 1]
    valid: Tensor | None = None,  # [V, 1, H, W] bool: which pixels to trust (e.g. rendered alpha > 0.5)
    config: TsdfConfig = TsdfConfig(),
    bounds: tuple[Tensor, Tensor] | None = None,  # (low [3], high [3]); default: from the depths
) -> TsdfVolume:
    """Fuse depth maps into a truncated signed distance volume (see the module doc)."""
    check_tensor("depths", depths, ("V", 1, "H", "W"))
    v, _, h, w = depths.shape
    if len(cameras) != v:
        raise SurfSplatInputError(f"cameras: expected {v} cameras (one per depth map), got {len(cameras)}")
    if colors is not None:
        check_tensor("colors", colors, (v, 3, h, w))
    if valid is None:
        valid = depths > 0
    elif tuple(valid.shape) != (v, 1, h, w) or valid.dtype != torch.bool:
        raise SurfSplatInputError(
            f"valid: expected a bool tensor of shape {(v, 1, h, w)}, got {valid.dtype} {tuple(valid.shape)}"
        )
    valid = valid & (depths > 0)
    if config.resolution < 2 or config.truncation_voxels <= 0:
        raise SurfSplatInputError(
            f"config: expected resolution >= 2 and truncation_voxels > 0, got {config.resolution}, {config.truncation_voxels}"
        )
    lo, hi = (
        bounds if bounds is not None else fusion_bounds(depths, cameras, valid, config.bounds_quantile, config.margin)
    )
    device = depths.device
    f64 = {"dtype": torch.float64, "device": device}
    lo, hi = lo.to(**f64), hi.to(**f64)
    if bool((hi <= lo).any()):
        raise SurfSplatInputError(f"bounds: expected low < high on every axis, got {lo.tolist()} and {hi.tolist()}")
    voxel = float((hi - lo).max()) / config.resolution
    dims = [max(2, int(torch.ceil((hi[a] - lo[a]) / voxel))) for a in range(3)]
    if dims[0] * dims[1] * dims[2] > config.max_voxels:
        raise SurfSplatInputError(f"config.resolution: a {dims} grid exceeds max_voxels = {config.max_voxels}")
    trunc = config.truncation_voxels * voxel

    axes = [lo[a] + (torch.arange(dims[a], **f64) + 0.5) * voxel for a in range(3)]
    centres = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)  # [X*Y*Z, 3]
    n = centres.shape[0]
    tsdf_sum = torch.zeros(n, **f64)
    weight = torch.zeros(n, **f64)
    color_sum = torch.zeros(n, 3, **f64)
    w2c = cameras.w2c.to(**f64)
    K = cameras.K.to(**f64)
    depth64 = depths.to(torch.float64)
    colors64 = colors.to(torch.float64) if colors is not None else None
    # Every voxel is visited in every view and the ones a view says nothing about add zero, rather
    # than gathering those it observes (nonzero, masks): sizes known ahead keep a device from
    # reporting each view's count to the host, and x + 0 leaves every sum as it was.
    for i in range(v):
        cam = centres @ w2c[i, :3, :3].T + w2c[i, :3, 3]
        z = cam[:, 2]
        in_front = z > 1e-9
        uv = cam @ K[i].T
        u = uv[:, 0] / z.clamp_min(1e-9)
        vv = uv[:, 1] / z.clamp_min(1e-9)
        col = torch.floor(u).long()  # pixel j covers [j, j + 1): its centre is j + 0.5
        row = torch.floor(vv).long()
        inside = in_front & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        r, c = row.clamp(0, h - 1), col.clamp(0, w - 1)  # outside voxels read some pixel, then count zero
        sdf = depth64[i, 0, r, c] - z
        # observed where the pixel is trusted and the voxel is not farther behind the surface than
        # the band (occluded: no information)
        seen = inside & valid[i, 0, r, c] & (sdf >= -trunc)
        tsdf_sum += torch.where(seen, (sdf / trunc).clamp(max=1.0), 0.0)
        weight += seen.to(torch.float64)
        if colors64 is not None:
            color_sum += torch.where(seen[:, None], colors64[i, :, r, c].T, 0.0)
    observed = weight > 0
    tsdf = torch.where(observed, tsdf_sum / weight.clamp_min(1), torch.ones_like(tsdf_sum))
    color = color_sum / weight.clamp_min(1)[:, None]
    return TsdfVolume(
        tsdf=tsdf.reshape(dims).float(),
        weight=weight.reshape(dims).float(),
        color=color.reshape(*dims, 3).float(),
        origin=lo,
        voxel_size=voxel,
    )


def extract_mesh(volume: TsdfVolume, min_weight: float = 1.0) -> Mesh:
    """The zero level set of the TSDF as a triangle mesh (marching cubes), coloured per vertex."""
    from skimage.measure import marching_cubes

    device = volume.tsdf.device
    # marching cubes runs on the host: the volume goes there once
    tsdf = volume.tsdf.cpu().numpy()
    observed = volume.weight.cpu().numpy() >= min_weight
    if not observed.any() or tsdf[observed].min() > 0 or tsdf[observed].max() < 0:
        raise SurfSplatInputError("volume: no observed zero crossing (nothing to mesh; check depths and bounds)")
    # TSDF values grow outwards (free space +1); scikit-image's "descent" then winds faces
    # counter-clockwise seen from outside, and its normals point down the gradient (inwards).
    verts, faces, normals, _ = marching_cubes(tsdf, level=0.0, spacing=(1.0, 1.0, 1.0), gradient_direction="descent")
    normals = -normals
    # Unobserved voxels hold +1, so the inner edge of the truncation band (observed -1 next to
    # unobserved) also crosses zero. Every vertex lies on one grid edge; keep a face only when
    # both ends of each of its vertices' edges were observed.
    lo = np.floor(verts).astype(np.int64)
    hi = np.minimum(np.ceil(verts).astype(np.int64), np.array(tsdf.shape) - 1)
    good = observed[lo[:, 0], lo[:, 1], lo[:, 2]] & observed[hi[:, 0], hi[:, 1], hi[:, 2]]
    faces = faces[good[faces].all(axis=1)]
    used = np.unique(faces)
    if used.size == 0:
        raise SurfSplatInputError("volume: no observed zero crossing (nothing to mesh; check depths and bounds)")
    remap = np.full(len(verts), -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    verts, normals, faces = verts[used], normals[used], remap[faces]
    # Grid indices are voxel centres: index 0 sits half a voxel inside the corner.
    vertices = torch.from_numpy(volume.origin.cpu().numpy() + (verts.astype(np.float64) + 0.5) * volume.voxel_size)
    normals_t = torch.from_numpy(np.ascontiguousarray(normals)).to(torch.float64)
    normals_t = normals_t / normals_t.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    idx = torch.from_numpy(np.round(verts).astype(np.int64))
    for a in range(3):
        idx[:, a] = idx[:, a].clamp(0, volume.tsdf.shape[a] - 1)
    colors = volume.color.cpu()[idx[:, 0], idx[:, 1], idx[:, 2]].clamp(0, 1)
    return Mesh(
        vertices=vertices.float().to(device),
        faces=torch.from_numpy(np.ascontiguousarray(faces).astype(np.int64)).to(device),
        normals=normals_t.float().to(device),
        colors=colors.to(device),
    )


def save_mesh(mesh: Mesh, path: str | os.PathLike) -> Path:
    """Write a mesh as binary PLY (vertex x y z nx ny nz red green blue, face vertex_indices) or
    as OBJ (v x y z r g b, vn, f with 1-based indices), chosen by the suffix; atomically."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".ply", ".obj"):
        raise SurfSplatInputError(f"{path}: expected a .ply or .obj file name")
    verts = mesh.vertices.detach().cpu().numpy().astype(np.float32)
    normals = mesh.normals.detach().cpu().numpy().astype(np.float32)
    rgb = (mesh.colors.detach().cpu().clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    faces = mesh.faces.detach().cpu().numpy().astype(np.int32)
    with atomic_path(path) as tmp:
        if suffix == ".ply":
            vertex = np.empty(
                len(verts),
                dtype=[(k, "f4") for k in ("x", "y", "z", "nx", "ny", "nz")]
                + [(k, "u1") for k in ("red", "green", "blue")],
            )
            for k, name in enumerate(("x", "y", "z")):
                vertex[name] = verts[:, k]
            for k, name in enumerate(("nx", "ny", "nz")):
                vertex[name] = normals[:, k]
            for k, name in enumerate(("red", "green", "blue")):
                vertex[name] = rgb[:, k]
            face = np.empty(len(faces), dtype=[("vertex_indices", "i4", (3,))])
            face["vertex_indices"] = faces
            PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(face, "face")], text=False).write(
                str(tmp)
            )
        else:
            with open(tmp, "w") as f:
                f.write("# surfsplat mesh: TSDF fusion of rendered depth\n")
                colours = rgb.astype(np.float32) / 255
                for p, c in zip(verts, colours):
                    f.write(f"v {p[0]:.6f} {p[1]:.6f} {p[2]:.6f} {c[0]:.4f} {c[1]:.4f} {c[2]:.4f}\n")
                for nrm in normals:
                    f.write(f"vn {nrm[0]:.5f} {nrm[1]:.5f} {nrm[2]:.5f}\n")
                for a, b, c in faces + 1:
                    f.write(f"f {a}//{a} {b}//{b} {c}//{c}\n")
    return path


def load_mesh(path: str | os.PathLike) -> Mesh:
    """Read a triangle mesh PLY (vertex x y z [nx ny nz] [red green blue], face vertex_indices), the
    layout `save_mesh` writes; missing normals are zero, missing colours mid grey."""
    path = Path(path)
    try:
        ply = PlyData.read(str(path))
        vertex, face = ply["vertex"], ply["face"]
    except (PlyParseError, ValueError, KeyError, EOFError, OSError, struct.error) as err:
        raise SurfSplatInputError(f"{path}: not a readable mesh PLY ({err})") from None
    names = set(vertex.data.dtype.names)
    if not {"x", "y", "z"} <= names:
        raise SurfSplatInputError(f"{path}: mesh vertices need x, y, z properties")

    def columns(keys: tuple[str, str, str], default: float, scale: float = 1.0) -> np.ndarray:
        if not set(keys) <= names:
            return np.full((len(vertex.data), 3), default, dtype=np.float32)
        return np.stack([np.asarray(vertex[k], dtype=np.float32) / scale for k in keys], axis=-1)

    vertices = columns(("x", "y", "z"), 0.0)
    try:
        faces = np.stack([np.asarray(f, dtype=np.int64) for f in face["vertex_indices"]]) if len(face.data) else None
    except ValueError:
        raise SurfSplatInputError(f"{path}: faces must all be triangles") from None
    if faces is None or faces.ndim != 2 or faces.shape[1] != 3:
        raise SurfSplatInputError(f"{path}: expected a non-empty list of triangles")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise SurfSplatInputError(f"{path}: face indices outside the {len(vertices)} vertices")
    return Mesh(
        vertices=torch.from_numpy(vertices),
        faces=torch.from_numpy(faces),
        normals=torch.from_numpy(columns(("nx", "ny", "nz"), 0.0)),
        colors=torch.from_numpy(columns(("red", "green", "blue"), 0.5 * 255, scale=255.0)),
    )


def mesh_from_renders(
    depths: Tensor,  # [V, 1, H, W]
    alphas: Tensor,  # [V, 1, H, W]
    colors: Tensor,  # [V, 3, H, W]
    cameras: Cameras,
    config: TsdfConfig = TsdfConfig(),
    min_alpha: float = 0.5,
) -> Mesh:
    """TSDF fusion of rendered depth where the render is valid (alpha >= min_alpha), then marching
    cubes. With forced alpha blending, depth is normalised wherever alpha >= tau_alpha, so pass tau."""
    check_tensor("alphas", alphas, tuple(depths.shape))
    valid = alphas >= min_alpha
    return extract_mesh(tsdf_fusion(depths, cameras, colors=colors, valid=valid, config=config))


def mesh_summary(mesh: Mesh) -> dict[str, object]:
    """Counts and extent of a mesh, for reports."""
    lo = mesh.vertices.amin(0).tolist() if len(mesh.vertices) else []
    hi = mesh.vertices.amax(0).tolist() if len(mesh.vertices) else []
    return {"vertices": int(mesh.vertices.shape[0]), "faces": int(mesh.faces.shape[0]), "bounds": [lo, hi]}


__all__ = [
    "Mesh",
    "TsdfConfig",
    "TsdfVolume",
    "backproject",
    "extract_mesh",
    "fusion_bounds",
    "mesh_from_renders",
    "mesh_summary",
    "save_mesh",
    "tsdf_fusion",
]
