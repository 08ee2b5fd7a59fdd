"""DTU's surface evaluation (Aanaes et al. 2016) as 2DGS, NeuS and their successors compute it.

    reference = load_dtu_reference("SampleSet/MVS Data", scan=24)   # ObsMask, Plane, STL points
    result = dtu_chamfer(points_mm, reference)                      # or dtu_chamfer_mesh(vertices, faces, ...)
    result.accuracy, result.completeness, result.overall            # millimetres

The reference files (not shipped; DTU's "SampleSet" and "Points" archives), relative to a folder:
    ObsMask/ObsMask{scan}_10.mat   ObsMask (bool grid), BB (2 x 3 corners, mm), Res (grid step, mm)
    ObsMask/Plane{scan}.mat        P (4): the table plane; reference points with P . [x, 1] > 0 count
    Points/stl/stl{scan:03}_total.ply   the structured-light reference point cloud (mm)

The protocol, step by step (the community's Python port of DTU's MATLAB script):
1. a mesh is sampled on a per-triangle grid at the down-sampling density (`sample_mesh_dtu`);
2. the points are shuffled, then thinned greedily to one per 0.2 mm (a point removes every later
   point within 0.2 mm of it);
3. points farther than 60 mm outside BB are dropped (the upper side keeps 120 mm, as the port does);
4. accuracy: the points that fall on an observed cell of ObsMask (cell = round((x - BB_min) / Res)),
   mean distance to the nearest STL point, over distances below 20 mm;
5. completeness: the STL points above the table plane, mean distance to the nearest point of step 3,
   over distances below 20 mm;
6. overall = (accuracy + completeness) / 2.
Points must be in DTU's world frame in millimetres: a reconstruction made in IDR's normalized frame
(`load_dtu(..., apply_scale_mat=True)`) goes back with x_world = scale_mat[:3, :3] x + scale_mat[:3, 3].
The shuffle is seeded here (the port's is not), so results are reproducible.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from plyfile import PlyData
from scipy.io import loadmat
from scipy.spatial import cKDTree
from torch import Tensor

from ..utils.checks import SurfSplatInputError
from .geometry import _points

DOWNSAMPLE_MM = 0.2  # down-sampling density of the reconstruction
PATCH_MM = 60.0  # margin around the observation box
MAX_DISTANCE_MM = 20.0  # distances at or above this are outliers, left out of both means


@dataclass(frozen=True)
class DtuReference:
    """One scan's reference data."""

    points: np.ndarray  # [S, 3] STL points (mm)
    obs_mask: np.ndarray  # [X, Y, Z] bool, observed cells
    bounds: np.ndarray  # [2, 3] BB: lowest and highest corner (mm)
    resolution: float  # Res: cell size (mm)
    plane: np.ndarray  # [4] table plane P


@dataclass(frozen=True)
class DtuMetrics:
    accuracy: float  # mm, reconstruction -> STL
    completeness: float  # mm, STL -> reconstruction
    overall: float  # (accuracy + completeness) / 2
    num_points: int  # reconstruction points after down-sampling
    num_observed: int  # of which fell on observed cells (accuracy's points)
    num_reference: int  # STL points above the plane (completeness's points)


def load_dtu_reference(folder: str | Path, scan: int) -> DtuReference:
    """Read ObsMask/ObsMask{scan}_10.mat, ObsMask/Plane{scan}.mat and Points/stl/stl{scan:03}_total.ply."""
    folder = Path(folder)
    obs_path = folder / "ObsMask" / f"ObsMask{scan}_10.mat"
    plane_path = folder / "ObsMask" / f"Plane{scan}.mat"
    stl_path = folder / "Points" / "stl" / f"stl{scan:03}_total.ply"
    obs = _read_mat(obs_path, ("ObsMask", "BB", "Res"))
    mask = np.asarray(obs["ObsMask"])
    if mask.ndim != 3:
        raise SurfSplatInputError(f"{obs_path}: ObsMask: expected a 3D grid, got shape {mask.shape}")
    bounds = np.asarray(obs["BB"], dtype=np.float64)
    if bounds.shape != (2, 3):
        raise SurfSplatInputError(f"{obs_path}: BB: expected shape (2, 3), got {bounds.shape}")
    res = np.asarray(obs["Res"], dtype=np.float64).reshape(-1)
    if res.size != 1 or not res[0] > 0:
        raise SurfSplatInputError(f"{obs_path}: Res: expected one positive number, got {res.tolist()}")
    plane = np.asarray(_read_mat(plane_path, ("P",))["P"], dtype=np.float64).reshape(-1)
    if plane.size != 4:
        raise SurfSplatInputError(f"{plane_path}: P: expected 4 plane coefficients, got {plane.size}")
    if not stl_path.is_file():
        raise FileNotFoundError(f"{stl_path}: DTU reference point cloud not found")
    try:
        vertex = PlyData.read(str(stl_path))["vertex"]
        points = np.stack([np.asarray(vertex[k], dtype=np.float64) for k in "xyz"], -1)
    except (KeyError, ValueError) as err:
        raise SurfSplatInputError(f"{stl_path}: expected a PLY with vertex x, y, z ({err})") from None
    return DtuReference(
        points=_points(str(stl_path), points),
        obs_mask=mask.astype(bool),
        bounds=bounds,
        resolution=float(res[0]),
        plane=plane,
    )


def _read_mat(path: Path, keys: tuple[str, ...]) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: DTU observation file not found")
    try:
        data = loadmat(str(path))
    except (ValueError, OSError) as err:
        raise SurfSplatInputError(f"{path}: not a readable .mat file ({err})") from None
    missing = [k for k in keys if k not in data]
    if missing:
        raise SurfSplatInputError(f"{path}: missing field(s) {missing}")
    return data


def downsample(points: np.ndarray, spacing: float = DOWNSAMPLE_MM, seed: int = 0) -> np.ndarray:
    """Greedy thinning in a seeded random order: a kept point removes every later point within `spacing`."""
    p = _points("points", points)
    p = p[np.random.default_rng(seed).permutation(p.shape[0])]
    neighbours = cKDTree(p).query_ball_point(p, r=spacing)
    keep = np.ones(p.shape[0], dtype=bool)
    for i, near in enumerate(neighbours):
        if keep[i]:
            keep[near] = False
            keep[i] = True
    return p[keep]


def sample_mesh_dtu(vertices: Tensor | np.ndarray, faces: Tensor | np.ndarray, spacing: float = DOWNSAMPLE_MM):
    """The vertices plus, per triangle (a, b, c) with edges e1 = b - a, e2 = c - a, the grid points
    a + (i + 0.5) / n1 e1 + (j + 0.5) / n2 e2 with (i + 0.5) / n1 + (j + 0.5) / n2 < 1, where
    n_k = floor(|e_k| / (spacing sqrt(|e1| |e2| / |e1 x e2|))): about one point per spacing^2 of area."""
    v = _points("vertices", vertices)
    f = np.asarray(faces.cpu().numpy() if isinstance(faces, Tensor) else faces)
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise SurfSplatInputError(f"faces: expected integer indices [F, 3], got {f.dtype} {f.shape}")
    tri = v[f]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    l1, l2 = np.linalg.norm(e1, axis=-1), np.linalg.norm(e2, axis=-1)
    area2 = np.linalg.norm(np.cross(e1, e2), axis=-1)
    ok = area2 > 0
    tri, e1, e2, l1, l2, area2 = tri[ok], e1[ok], e2[ok], l1[ok], l2[ok], area2[ok]
    step = spacing * np.sqrt(l1 * l2 / area2)
    n1, n2 = np.floor(l1 / step).astype(np.int64), np.floor(l2 / step).astype(np.int64)
    out = [v]
    # Triangles with the same grid share one pattern of barycentric coordinates.
    pairs, inverse = np.unique(np.stack([n1, n2], -1), axis=0, return_inverse=True)
    for k, (a, b) in enumerate(pairs):
        i, j = np.meshgrid(np.arange(a + 1) + 0.5, np.arange(b + 1) + 0.5, indexing="ij")
        ci, cj = i.ravel() / max(a, 1e-7), j.ravel() / max(b, 1e-7)
        inside = ci + cj < 1
        ci, cj = ci[inside], cj[inside]
        if ci.size == 0:
            continue
        group = np.flatnonzero(inverse.reshape(-1) == k)
        pts = tri[group, None, 0] + ci[None, :, None] * e1[group, None] + cj[None, :, None] * e2[group, None]
        out.append(pts.reshape(-1, 3))
    return np.concatenate(out)


def dtu_chamfer(
    points: Tensor | np.ndarray,
    reference: DtuReference,
    downsample_mm: float = DOWNSAMPLE_MM,
    patch_mm: float = PATCH_MM,
    max_distance_mm: float = MAX_DISTANCE_MM,
    seed: int = 0,
) -> DtuMetrics:
    """DTU accuracy, completeness and overall (mm) of reconstructed points [N, 3] in DTU's world frame."""
    data = downsample(points, downsample_mm, seed)
    low, high = reference.bounds[0], reference.bounds[1]
    inbound = np.all((data >= low - patch_mm) & (data < high + 2 * patch_mm), axis=-1)
    data_in = data[inbound]
    if data_in.shape[0] == 0:
        raise SurfSplatInputError("points: none lies near the scan's observation box (are they in DTU's mm frame?)")
    cell = np.around((data_in - low) / reference.resolution).astype(np.int64)
    on_grid = np.all((cell >= 0) & (cell < np.asarray(reference.obs_mask.shape)), axis=-1)
    observed = np.zeros(data_in.shape[0], dtype=bool)
    c = cell[on_grid]
    observed[on_grid] = reference.obs_mask[c[:, 0], c[:, 1], c[:, 2]]
    data_obs = data_in[observed]

    above = reference.points @ reference.plane[:3] + reference.plane[3] > 0
    stl_above = reference.points[above]

    def capped_mean(distances: np.ndarray) -> float:
        kept = distances[distances < max_distance_mm]
        return float(kept.mean()) if kept.size else math.nan

    accuracy = capped_mean(cKDTree(reference.points).query(data_obs, k=1)[0]) if data_obs.size else math.nan
    completeness = capped_mean(cKDTree(data_in).query(stl_above, k=1)[0]) if stl_above.size else math.nan
    return DtuMetrics(
        accuracy=accuracy,
        completeness=completeness,
        overall=(accuracy + completeness) / 2,
        num_points=int(data.shape[0]),
        num_observed=int(data_obs.shape[0]),
        num_reference=int(stl_above.shape[0]),
    )


def dtu_chamfer_mesh(
    vertices: Tensor | np.ndarray, faces: Tensor | np.ndarray, reference: DtuReference, **kwargs
) -> DtuMetrics:
    """`dtu_chamfer` of a mesh (vertices [V, 3] in mm, faces [F, 3]) sampled as DTU's script samples it."""
    spacing = kwargs.get("downsample_mm", DOWNSAMPLE_MM)
    return dtu_chamfer(sample_mesh_dtu(vertices, faces, spacing), reference, **kwargs)


__all__ = [
    "DOWNSAMPLE_MM",
    "MAX_DISTANCE_MM",
    "PATCH_MM",
    "DtuMetrics",
    "DtuReference",
    "downsample",
    "dtu_chamfer",
    "dtu_chamfer_mesh",
    "load_dtu_reference",
    "sample_mesh_dtu",
]
