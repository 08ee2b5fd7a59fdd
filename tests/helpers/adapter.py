"""Reference pieces of the adapter tests: release formulas, cameras and analytic depth maps."""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from surfsplat.model.adapter import pixel_centers

F64 = torch.float64


# ---------------------------------------------------------------------------------------------- scenes
def intrinsics(fx: float, fy: float, cx: float, cy: float, dtype=F64) -> torch.Tensor:
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype)


def plane_depth(K: torch.Tensor, H: int, W: int, normal: torch.Tensor, distance: float) -> torch.Tensor:
    """Camera z of the plane {P : normal . P = distance} along each pixel ray."""
    return distance / (camera_rays(K, H, W) @ normal)


def sphere_depth(K, H, W, centre, radius, background):
    """Camera z of a sphere in front of a fronto-parallel plane at z = background; returns (depth, hit)."""
    rays = camera_rays(K, H, W)
    b = rays @ centre
    a = rays.square().sum(-1)
    disc = b * b - a * (centre @ centre - radius**2)
    hit = disc > 0
    t = (b - disc.clamp_min(0).sqrt()) / a  # nearer root; rays have z = 1, so t is the camera z
    return torch.where(hit, t, torch.full_like(t, background)), hit


def tilted_normal(theta_deg: float, phi_deg: float) -> torch.Tensor:
    """Unit normal tilted by theta from the optical axis, towards azimuth phi (n_z > 0)."""
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return torch.tensor([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)], dtype=F64)


def rigid(R: torch.Tensor, t) -> torch.Tensor:
    T = torch.eye(4, dtype=R.dtype)
    T[:3, :3] = R
    T[:3, 3] = torch.as_tensor(t, dtype=R.dtype)
    return T


def random_rotation(seed: int, dtype=F64) -> torch.Tensor:
    return torch.from_numpy(Rotation.random(random_state=seed).as_matrix()).to(dtype)


def softplus_inverse(y: float) -> float:
    return math.log(math.expm1(y))


# ---------------------------------------------------------------------------------------------- official mode
def release_reference(depths, raw, images, K_norm, c2w, mask=(1.0, 0.025, 0.00625)):
    """The golden README's formulas, written out in NumPy float64 for one batch element.

    depths [V, H, W], raw [V, 32, H, W], images [V, 3, H, W], K_norm [V, 3, 3] normalized, c2w [V, 4, 4].
    """
    V, H, W = depths.shape
    sig = lambda x: 1 / (1 + np.exp(-x))  # noqa: E731
    out = {k: [] for k in ("means", "cov", "normals", "scales", "quats", "opacity", "sh_cam")}
    for v in range(V):
        R, t = c2w[v, :3, :3], c2w[v, :3, 3]
        jj, ii = np.meshgrid(np.arange(W), np.arange(H))
        x = (jj + 0.5) / W + (sig(raw[v, 1]) - 0.5) / W
        y = (ii + 0.5) / H + (sig(raw[v, 2]) - 0.5) / H
        rays = np.stack((x, y, np.ones_like(x)), -1) @ np.linalg.inv(K_norm[v]).T
        rays = rays / rays[..., 2:]
        m = t + (rays @ R.T) * depths[v][..., None]
        gx = np.zeros_like(m)
        gy = np.zeros_like(m)
        gx[1:-1, 1:-1] = ((m[:-2, 2:] - m[:-2, :-2]) + 2 * (m[1:-1, 2:] - m[1:-1, :-2]) + (m[2:, 2:] - m[2:, :-2])) / 8
        gy[1:-1, 1:-1] = ((m[2:, :-2] - m[:-2, :-2]) + 2 * (m[2:, 1:-1] - m[:-2, 1:-1]) + (m[2:, 2:] - m[:-2, 2:])) / 8
        gx = np.pad(gx[1:-1, 1:-1], ((1, 1), (1, 1), (0, 0)), mode="edge")
        gy = np.pad(gy[1:-1, 1:-1], ((1, 1), (1, 1), (0, 0)), mode="edge")
        n = np.cross(gx, gy)
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
        nf = n * np.sign(n[..., 2:])
        vv = np.stack((-nf[..., 1], nf[..., 0], np.zeros_like(nf[..., 0])), -1)
        c, s = nf[..., 2], np.linalg.norm(vv, axis=-1)
        vx = np.zeros(vv.shape + (3,))
        vx[..., 0, 1], vx[..., 0, 2], vx[..., 1, 2] = -vv[..., 2], vv[..., 1], -vv[..., 0]
        vx[..., 1, 0], vx[..., 2, 0], vx[..., 2, 1] = vv[..., 2], -vv[..., 1], vv[..., 0]
        Rr = np.eye(3) + s[..., None, None] * vx + (1 - c)[..., None, None] * (vx @ vx)
        gxc, gyc = np.clip(gx, -0.1, 0.1), np.clip(gy, -0.1, 0.1)
        base = np.stack((np.hypot(gxc[..., 0], gxc[..., 2]), np.hypot(gyc[..., 1], gyc[..., 2])), -1)
        mult = np.clip(np.log1p(np.exp(raw[v, 3:5])), 1 / 3, 3).transpose(1, 2, 0)
        sc = np.clip(np.concatenate((base * mult, np.full((H, W, 1), 1e-10)), -1), 1e-10, 3)
        cov = Rr @ (sc[..., :, None] ** 2 * np.eye(3)) @ np.swapaxes(Rr, -1, -2)
        out["cov"].append(R @ cov @ R.T)  # the double rotation
        w = np.sqrt(1 + Rr[..., 0, 0] + Rr[..., 1, 1] + Rr[..., 2, 2]) / 2
        q = np.stack(
            ((Rr[..., 2, 1] - Rr[..., 1, 2]) / (4 * w), (Rr[..., 0, 2] - Rr[..., 2, 0]) / (4 * w),
             (Rr[..., 1, 0] - Rr[..., 0, 1]) / (4 * w), w), -1)  # fmt: skip
        sh = raw[v, 5:].reshape(3, 9, H, W).transpose(2, 3, 0, 1) * np.repeat(mask, [1, 3, 5])
        sh[..., 0] += (images[v].transpose(1, 2, 0) - 0.5) / 0.28209479177387814
        for key, val in (("means", m), ("normals", n), ("scales", sc), ("quats", q), ("sh_cam", sh)):
            out[key].append(val)
        out["opacity"].append(sig(raw[v, 0]) * 0.6)
    return {k: torch.from_numpy(np.stack(v).reshape(V * H * W, *np.stack(v).shape[3:])) for k, v in out.items()}


def camera_rays(K: torch.Tensor, H: int, W: int) -> torch.Tensor:
    """[H, W, 3] rays K^-1 [x, y, 1] through pixel centres (z = 1)."""
    xy = pixel_centers(H, W, dtype=K.dtype)
    return torch.cat((xy, torch.ones_like(xy[..., :1])), dim=-1) @ torch.linalg.inv(K).T
