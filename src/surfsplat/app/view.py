"""The copy of the 3DGS PLY the page's 3D view shows: the same splats, placed so that the view's
default camera looks at the scene as the first photo did.

gradio's splat viewer (gsplat.js) always starts orbiting the origin at distance 5 from the angles
(alpha, beta) = (0.5, 0.5) rad, in an OpenCV-like frame (x right, y down, z forward); a
reconstruction sits wherever its cameras put it. So the splats are moved into the first camera's
frame, scaled so that the median depth in front of it is FRAMING x 5, shifted so that point is the
origin, and turned so that the first camera lands on the viewer's default line of sight (the
viewer a step behind it, so the whole picture fits). Only positions,
rotations and scales change (the viewer draws the SH's constant term only, so the higher bands are
left out); the downloads keep the PLY as written.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

VIEWER_RADIUS = 5.0  # gsplat.js OrbitControls' default distance to its target (the origin)
VIEWER_ANGLES = (0.5, 0.5)  # its default (alpha, beta) in radians
FRAMING = 0.7  # the median depth becomes this share of the viewer's distance: it starts a step behind the first photo
KEPT = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2")


def viewer_rotation(alpha: float = VIEWER_ANGLES[0], beta: float = VIEWER_ANGLES[1]) -> np.ndarray:
    """[3, 3] camera-to-world rotation of the viewer's default camera (columns: right, down, forward)
    at target + r (sin a cos b, -sin b, -cos a cos b) looking at the target without roll."""
    position = np.array([math.sin(alpha) * math.cos(beta), -math.sin(beta), -math.cos(alpha) * math.cos(beta)])
    forward = -position / np.linalg.norm(position)
    right = np.array([forward[2], 0.0, -forward[0]])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return np.stack([right, down, forward], 1)


def write_view_ply(source: str | Path, target: str | Path, first_c2w: torch.Tensor) -> Path:
    """Write the viewer's copy of the 3DGS PLY `source` (see the module docstring); `first_c2w` is
    the first context camera's [4, 4] OpenCV camera-to-world matrix."""
    from plyfile import PlyData, PlyElement
    from scipy.spatial.transform import Rotation

    vertex = PlyData.read(str(source))["vertex"]
    c2w = first_c2w.detach().to(torch.float64).cpu().numpy()
    R0, t0 = c2w[:3, :3], c2w[:3, 3]
    xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], -1).astype(np.float64)
    local = (xyz - t0) @ R0  # R0^T (x - t0), row vectors
    ahead = local[:, 2][local[:, 2] > 0]
    depth = float(np.median(ahead)) if len(ahead) else 1.0
    scale = FRAMING * VIEWER_RADIUS / depth
    turn = viewer_rotation()
    shown = (scale * local - np.array([0.0, 0.0, FRAMING * VIEWER_RADIUS])) @ turn.T
    q = np.stack([vertex["rot_1"], vertex["rot_2"], vertex["rot_3"], vertex["rot_0"]], -1).astype(np.float64)
    rotated = (Rotation.from_matrix(turn @ R0.T) * Rotation.from_quat(q)).as_quat()  # x y z w
    out = np.empty(len(xyz), dtype=[(name, "f4") for name in (*KEPT, "rot_0", "rot_1", "rot_2", "rot_3")])
    for name in KEPT:
        out[name] = vertex[name]
    out["x"], out["y"], out["z"] = shown[:, 0], shown[:, 1], shown[:, 2]
    for k in range(3):
        out[f"scale_{k}"] = vertex[f"scale_{k}"] + math.log(scale)  # log scales
    out["rot_0"], out["rot_1"], out["rot_2"], out["rot_3"] = rotated[:, 3], rotated[:, 0], rotated[:, 1], rotated[:, 2]
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(out, "vertex")]).write(str(target))
    return target
