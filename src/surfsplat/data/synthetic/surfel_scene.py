"""A small procedural surfel scene: what a feed-forward model would predict from two views.

A textured sphere in front of a textured backdrop plane is ray-cast from each source view; every
source pixel becomes one surfel at the ray's first hit, oriented by the analytic surface normal,
one source pixel wide (scale = depth / focal), as a per-pixel feed-forward predictor lays them out.
Used by the built-in render command, the renderer benchmark and the tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from ...geometry.cameras import Cameras, look_at
from ...geometry.gaussians import Gaussians
from ...geometry.rotations import matrix_to_quat
from ...geometry.sh import rgb_to_sh_dc

SPHERE_CENTER = (0.0, 0.0, 3.2)
SPHERE_RADIUS = 1.0
PLANE_Z = 4.5  # backdrop plane z = PLANE_Z, facing the cameras


@dataclass
class SurfelScene:
    gaussians: Gaussians  # N = views * resolution^2 surfels
    sources: Cameras  # the views the surfels were made from
    target: Cameras  # a nearby novel view
    resolution: int  # source image size (square)


def texture(points: Tensor) -> Tensor:
    """Procedural colour at world points [..., 3] -> [..., 3] in [0, 1], detailed at every scale."""
    x, y, z = points.unbind(-1)
    checker = ((torch.floor(x * 4) + torch.floor(y * 4) + torch.floor(z * 4)) % 2) * 0.25
    fine = 0.15 * torch.sin(37 * x + 11 * z) * torch.cos(41 * y - 7 * x)
    r = 0.45 + checker + fine + 0.1 * torch.sin(3 * y)
    g = 0.35 + 0.5 * checker + 0.2 * torch.cos(5 * x + 2 * z) - fine
    b = 0.55 - checker * 0.6 + 0.15 * torch.sin(9 * z + 4 * y)
    return torch.stack((r, g, b), dim=-1).clamp(0, 1)


def ray_cast(cameras: Cameras, width: int, height: int) -> tuple[Tensor, Tensor, Tensor]:
    """First hit of every pixel ray with the sphere and the backdrop plane.

    Returns points [C, H, W, 3], unit normals facing the camera [C, H, W, 3], camera-z depth [C, H, W].
    """
    j = torch.arange(width, dtype=torch.float64) + 0.5
    i = torch.arange(height, dtype=torch.float64) + 0.5
    yy, xx = torch.meshgrid(i, j, indexing="ij")
    pix = torch.stack((xx, yy, torch.ones_like(xx)), dim=-1)  # [H, W, 3]
    K_inv = torch.linalg.inv(cameras.K.to(torch.float64))
    c2w = cameras.c2w.to(torch.float64)
    d_cam = torch.einsum("cij,hwj->chwi", K_inv, pix)  # z = 1
    d_world = torch.einsum("cij,chwj->chwi", c2w[:, :3, :3], d_cam)
    o = c2w[:, None, None, :3, 3].expand_as(d_world)
    # Sphere: |o + t d - c|^2 = r^2.
    c = torch.tensor(SPHERE_CENTER, dtype=torch.float64)
    oc = o - c
    a = (d_world * d_world).sum(-1)
    b = 2 * (oc * d_world).sum(-1)
    cc = (oc * oc).sum(-1) - SPHERE_RADIUS**2
    disc = b * b - 4 * a * cc
    t_sphere = torch.where(disc > 0, (-b - disc.clamp_min(0).sqrt()) / (2 * a), torch.full_like(a, torch.inf))
    t_sphere = torch.where(t_sphere > 0, t_sphere, torch.full_like(a, torch.inf))
    t_plane = (PLANE_Z - o[..., 2]) / d_world[..., 2]
    t_plane = torch.where(t_plane > 0, t_plane, torch.full_like(a, torch.inf))
    hit_sphere = t_sphere < t_plane
    t = torch.where(hit_sphere, t_sphere, t_plane)
    points = o + t[..., None] * d_world
    n_sphere = F.normalize(points - c, dim=-1)
    n_plane = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).expand_as(points)
    normals = torch.where(hit_sphere[..., None], n_sphere, n_plane)
    # Depth is camera z; with K^-1 [x, y, 1] directions, t is exactly that.
    return points, normals, t


def frame_from_normal(normals: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] whose third column is the given unit normal."""
    helper = torch.where(
        normals[..., 0:1].abs() < 0.9,
        torch.tensor([1.0, 0.0, 0.0], dtype=normals.dtype).expand_as(normals),
        torch.tensor([0.0, 1.0, 0.0], dtype=normals.dtype).expand_as(normals),
    )
    u = F.normalize(torch.linalg.cross(helper, normals), dim=-1)
    v = torch.linalg.cross(normals, u)
    return torch.stack((u, v, normals), dim=-1)


def make_scene(resolution: int = 256, views: int = 2, opacity: float = 0.5, focal: float = 1.1) -> SurfelScene:
    """Surfels from `views` source views at resolution^2 (131,072 for the default two 256^2 views).

    focal is normalized by the image width (0.9-1.2 is typical of RealEstate10K).
    """
    f = focal * resolution
    K = torch.tensor([[f, 0, resolution / 2], [0, f, resolution / 2], [0, 0, 1.0]])
    target_point = torch.tensor([0.0, 0.0, SPHERE_CENTER[2]])
    eyes = [torch.tensor([0.25 * (v - (views - 1) / 2), 0.05 * v, 0.0]) for v in range(views)]
    sources = Cameras(torch.stack([look_at(e, target_point) for e in eyes]), K.expand(views, 3, 3).clone())
    target = Cameras(look_at(torch.tensor([0.08, -0.1, 0.25]), target_point)[None], K[None].clone())

    points, normals, depth = ray_cast(sources, resolution, resolution)
    rot = frame_from_normal(normals)
    scale = (depth / f).to(torch.float32)
    n = views * resolution * resolution
    colors = texture(points).reshape(n, 3).to(torch.float32)
    gaussians = Gaussians(
        means=points.reshape(n, 3).to(torch.float32),
        quats=matrix_to_quat(rot.reshape(n, 3, 3)).to(torch.float32),
        scales=scale.reshape(n, 1).expand(n, 2).contiguous(),
        opacities=torch.full((n,), opacity),
        sh=rgb_to_sh_dc(colors)[:, :, None],
    )
    return SurfelScene(gaussians, sources, target, resolution)
