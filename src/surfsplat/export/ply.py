"""PLY files in the layouts Gaussian-splatting viewers read.

2DGS layout (surfels): x y z, nx ny nz, f_dc_0..2, f_rest_0.., opacity (logit), scale_0 scale_1
(log), rot_0..3 (quaternion w, x, y, z). 3DGS layout adds scale_2; it is used for Gaussians that
carry explicit covariances (the release-compatible adapter), whose shape no surfel describes.
f_rest is channel-major as in 3DGS: f_rest_{c * (B - 1) + k} is SH coefficient k + 1 of colour c.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from plyfile import PlyData, PlyElement, PlyParseError

from ..geometry.gaussians import Gaussians
from ..geometry.rotations import matrix_to_quat
from ..geometry.sh import sh_degree_from_bases
from ..utils.atomic import atomic_path
from ..utils.checks import SurfSplatInputError

Precision = Literal["float32", "float64"]


# The vertex fields every surfel PLY carries (2DGS layout: two scales); normals nx, ny, nz are optional.
SURFEL_FIELDS = (
    "x",
    "y",
    "z",
    "f_dc_0",
    "f_dc_1",
    "f_dc_2",
    "opacity",
    "scale_0",
    "scale_1",
    "rot_0",
    "rot_1",
    "rot_2",
    "rot_3",
)


def save_ply(gaussians: Gaussians, path: str | os.PathLike, precision: Precision = "float32") -> Path:
    """Write unbatched Gaussians to `path` (atomically: a temporary file is renamed into place).

    float32 is what viewers read; float64 stores the logit/log encodings without rounding, so a
    round trip reproduces float32 inputs bit for bit.
    """
    g = gaussians.detach().to("cpu")
    if g.means.ndim != 2:
        raise SurfSplatInputError(f"gaussians: expected unbatched Gaussians ([N, 3] means), got {tuple(g.means.shape)}")
    dt = np.float32 if precision == "float32" else np.float64
    means = g.means.double()
    n, bases = g.sh.shape[0], g.sh.shape[-1]
    if g.explicit_covariances is not None:
        # Eigen-decompose the covariance into a rotation and three scales (3DGS layout).
        # Axes ordered largest first, so the first two span the surfel and the third is its normal.
        evals, evecs = torch.linalg.eigh(g.explicit_covariances.double())
        evals, evecs = evals.flip(-1), evecs.flip(-1)
        evecs = torch.where(torch.linalg.det(evecs)[:, None, None] < 0, -evecs, evecs)  # proper rotations
        scales = evals.clamp_min(1e-30).sqrt()
        quats = matrix_to_quat(evecs)
        normals = evecs[:, :, 2]
    else:
        scales = g.scales.double()
        quats = g.quats.double()
        normals = g.rotations.double()[:, :, 2]
    opac = g.opacities.double().clamp(1e-12, 1 - 1e-12)
    columns: list[tuple[str, np.ndarray]] = [
        ("x", means[:, 0]),
        ("y", means[:, 1]),
        ("z", means[:, 2]),
        ("nx", normals[:, 0]),
        ("ny", normals[:, 1]),
        ("nz", normals[:, 2]),
    ]
    sh = g.sh.double()
    columns += [(f"f_dc_{c}", sh[:, c, 0]) for c in range(3)]
    rest = sh[:, :, 1:].reshape(n, 3 * (bases - 1))
    columns += [(f"f_rest_{i}", rest[:, i]) for i in range(rest.shape[1])]
    columns.append(("opacity", torch.log(opac) - torch.log1p(-opac)))
    log_scales = torch.log(scales.clamp_min(1e-30))
    columns += [(f"scale_{i}", log_scales[:, i]) for i in range(scales.shape[1])]
    columns += [(f"rot_{i}", quats[:, i]) for i in range(4)]

    vertex = np.empty(n, dtype=[(name, dt) for name, _ in columns])
    for name, values in columns:
        vertex[name] = values.numpy() if isinstance(values, torch.Tensor) else values
    path = Path(path)
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(vertex, "vertex")], text=False).write(str(tmp))
    return path


def load_ply(path: str | os.PathLike, dtype: torch.dtype = torch.float32) -> Gaussians:
    """Read a 2DGS (two scales) or 3DGS (three scales) PLY into Gaussians.

    A 3DGS file becomes surfels spanned by its first two axes (the largest ones in files written
    here) plus explicit covariances holding the exact 3D shape, so EWA rendering reproduces it.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such PLY file")
    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"]
    except (PlyParseError, ValueError, KeyError, EOFError, OSError, struct.error) as err:
        raise SurfSplatInputError(f"{path}: not a readable PLY file ({err})") from None
    names = set(v.data.dtype.names)
    missing = sorted(set(SURFEL_FIELDS) - names)
    if missing:
        raise SurfSplatInputError(f"{path}: not a Gaussian-splat PLY, missing vertex properties {missing}")

    def col(name: str) -> torch.Tensor:
        return torch.from_numpy(np.asarray(v[name], dtype=np.float64))

    used = [
        p.name for p in v.properties if p.name in SURFEL_FIELDS or p.name.startswith("f_rest_") or p.name == "scale_2"
    ]
    for name in used:
        bad = np.flatnonzero(~np.isfinite(np.asarray(v[name], dtype=np.float64)))
        if len(bad):
            raise SurfSplatInputError(
                f"{path}: vertex property '{name}' holds NaN or inf ({len(bad)} vertices, the first is vertex {bad[0]})"
            )

    n = len(v.data)
    rest_names = sorted((p for p in names if p.startswith("f_rest_")), key=lambda p: int(p.split("_")[-1]))
    if len(rest_names) % 3:
        raise SurfSplatInputError(f"{path}: {len(rest_names)} f_rest properties is not a multiple of 3")
    bases = 1 + len(rest_names) // 3
    try:
        sh_degree_from_bases(bases)
    except ValueError as err:
        raise SurfSplatInputError(f"{path}: {err}") from None
    sh = torch.empty(n, 3, bases, dtype=torch.float64)
    for c in range(3):
        sh[:, c, 0] = col(f"f_dc_{c}")
    if rest_names:
        rest = torch.stack([col(p) for p in rest_names], dim=-1)
        sh[:, :, 1:] = rest.reshape(n, 3, bases - 1)
    means = torch.stack([col("x"), col("y"), col("z")], dim=-1)
    opacities = torch.sigmoid(col("opacity"))
    quats = torch.stack([col(f"rot_{i}") for i in range(4)], dim=-1)
    three = "scale_2" in names
    scales = torch.exp(torch.stack([col(f"scale_{i}") for i in range(3 if three else 2)], dim=-1))
    covariances = None
    if three:
        g3 = Gaussians(means, quats, scales[:, :2], opacities, sh)
        R = g3.rotations
        covariances = (R * scales.square()[:, None, :]) @ R.transpose(1, 2)
    g = Gaussians(
        means=means.to(dtype),
        quats=quats.to(dtype),
        scales=scales[:, :2].to(dtype),
        opacities=opacities.to(dtype),
        sh=sh.to(dtype),
        explicit_covariances=None if covariances is None else covariances.to(dtype),
    )
    return g
