"""Ray casting of synthetic scenes: images, exact depth and normals at any resolution.

For a camera with c2w = [R | o] and pixel intrinsics K, the ray through the pixel coordinate
(u, v) is o + t d with d = R K^-1 [u, v, 1]^T. d's camera-z component is 1, so the ray parameter
t of a hit is the hit's camera z-depth, exactly (no normalization). Pixel (row i, column j) is
centred at (j + 0.5, i + 0.5) (the package convention), so rendering at s times the resolution
with K' = diag(s, s, 1) K samples the same continuous image plane s times more densely.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from einops import rearrange
from torch import Tensor

from ...geometry.cameras import Cameras
from ...utils.checks import SurfSplatInputError
from .scene import SyntheticScene
from .textures import albedo


@dataclass
class SyntheticRender:
    """Ray-cast outputs for C cameras.

    image:     [C, 3, H, W] in [0, 1] (averaged over supersample^2 rays per pixel)
    depth:     [C, 1, H, W] camera-z depth of the pixel-centre ray's hit (0 where it hits nothing)
    normal:    [C, 3, H, W] unit world normal at that hit, facing the camera (0 where nothing)
    primitive: [C, 1, H, W] int64 index into scene.primitives (-1 where nothing)
    """

    image: Tensor
    depth: Tensor
    normal: Tensor
    primitive: Tensor


def pixel_rays(cameras: Cameras, width: int, height: int, offsets: Tensor, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """Rays through pixel (i, j) at image-plane coordinates (j + ox, i + oy) for every offset.

    offsets: [S, 2] (ox, oy) in pixels, (0.5, 0.5) = the pixel centre.
    Returns origins [C, S, H, W, 3] and directions [C, S, H, W, 3] with camera-z component 1.
    """
    c2w = cameras.c2w.to(dtype)
    K_inv = torch.linalg.inv(cameras.K.to(torch.float64)).to(dtype)  # [C, 3, 3]
    jj = torch.arange(width, dtype=dtype)
    ii = torch.arange(height, dtype=dtype)
    u = jj[None, None, :] + offsets[:, 0, None, None].to(dtype)  # [S, 1, W]
    v = ii[None, :, None] + offsets[:, 1, None, None].to(dtype)  # [S, H, 1]
    u, v = torch.broadcast_tensors(u, v)  # [S, H, W]
    pix = torch.stack([u, v, torch.ones_like(u)], -1)  # [S, H, W, 3]
    cam_dirs = torch.einsum("cij,shwj->cshwi", K_inv, pix)  # K^-1 [u, v, 1], z = 1 exactly
    dirs = torch.einsum("cij,cshwj->cshwi", c2w[:, :3, :3], cam_dirs)
    origins = c2w[:, None, None, None, :3, 3].expand_as(dirs)
    return origins, dirs


def cast_rays(scene: SyntheticScene, origins: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Nearest hit of rays [R, 3]: (t [R], inf on miss; outward world normal [R, 3]; primitive index [R], -1 on miss)."""
    best_t = torch.full(origins.shape[:1], torch.inf, dtype=origins.dtype)
    best_n = torch.zeros_like(origins)
    best_id = torch.full(origins.shape[:1], -1, dtype=torch.int64)
    for k, prim in enumerate(scene.primitives):
        t, n_local = prim.intersect(origins, dirs)
        closer = t < best_t
        best_t = torch.where(closer, t, best_t)
        best_n = torch.where(closer[:, None], n_local @ prim.rotation.to(origins).T, best_n)
        best_id = torch.where(closer, torch.full_like(best_id, k), best_id)
    return best_t, best_n, best_id


def shade(scene: SyntheticScene, points: Tensor, normals: Tensor, primitive: Tensor) -> Tensor:
    """Lambertian colour [R, 3] of hit points [R, 3] with world normals [R, 3] facing the viewer.

    View-independent on purpose: the scene is exactly representable by view-independent
    radiance, so disagreements between renderings come from geometry, not from lighting.
    """
    rgb = torch.zeros_like(points)
    for k, prim in enumerate(scene.primitives):
        mask = primitive == k
        if not bool(mask.any()):
            continue
        p = points[mask]
        n = normals[mask]
        local_p = prim.to_local(p)
        local_n = n @ prim.rotation.to(p)
        rgb[mask] = albedo(prim.texture, local_p, local_n)
    light = scene.lighting
    direction = light.direction.to(points)
    to_lamp = light.position.to(points) - points
    dist2 = (to_lamp * to_lamp).sum(-1)
    lamp = (normals * to_lamp).sum(-1).clamp_min(0) / dist2.sqrt() / (1 + light.falloff * dist2)
    irradiance = light.ambient + light.directional * (normals @ direction).clamp_min(0) + light.lamp * lamp
    hit = (primitive >= 0)[:, None]
    return torch.where(hit, (rgb * irradiance[:, None]).clamp(0, 1), torch.zeros_like(rgb))


def ray_geometry(scene: SyntheticScene, origins: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Depth t [R] (0 on miss), unit normal [R, 3] facing the ray (0 on miss) and primitive [R] of rays [R, 3]."""
    t, n, prim = cast_rays(scene, origins, dirs)
    hit = prim >= 0
    t_hit = torch.where(hit, t, torch.zeros_like(t))
    # Unit length exactly (a sphere's p / r is off by the hit point's rounding), then face the
    # viewer: the side of the surface the ray arrives from.
    n = torch.nn.functional.normalize(n, dim=-1)
    n = torch.where(((n * dirs).sum(-1) > 0)[:, None], -n, n)
    n = torch.where(hit[:, None], n, torch.zeros_like(n))
    return t_hit, n, prim


def render_rays(scene: SyntheticScene, origins: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Colour [R, 3], depth t [R] (0 on miss), camera-facing normal [R, 3] and primitive [R] of rays [R, 3]."""
    t_hit, n, prim = ray_geometry(scene, origins, dirs)
    points = origins + t_hit[:, None] * dirs
    return shade(scene, points, n, prim), t_hit, n, prim


def render_synthetic(
    scene: SyntheticScene,
    cameras: Cameras,
    width: int,
    height: int,
    supersample: int = 1,
    dtype: torch.dtype = torch.float32,
    chunk: int = 1 << 18,
) -> SyntheticRender:
    """Render `scene` for every camera at width x height (K in pixels of that size).

    supersample: s >= 1 averages s x s rays per pixel at offsets ((a + 0.5) / s, (b + 0.5) / s),
        i.e. the pixel centres of the s-times larger image: a view rendered with supersample s
        equals the s x s average pooling of the same view rendered at s times the resolution
        (K scaled by s) with supersample 1, up to float rounding of the ray directions. Depth,
        normal and primitive are always those of the pixel-centre ray (exact values, not averages).
    chunk: rays per batch, which bounds memory at any resolution.
    """
    if width < 1 or height < 1:
        raise SurfSplatInputError(f"width, height: expected positive sizes, got {width}x{height}")
    if supersample < 1:
        raise SurfSplatInputError(f"supersample: expected an integer >= 1, got {supersample}")
    centre = torch.tensor([[0.5, 0.5]])
    origins, dirs = pixel_rays(cameras, width, height, centre, dtype)
    o = rearrange(origins, "c s h w k -> (c s h w) k")
    d = rearrange(dirs, "c s h w k -> (c s h w) k")
    colors, depths, normals, prims = [], [], [], []
    for start in range(0, o.shape[0], chunk):
        rgb, t, n, p = render_rays(scene, o[start : start + chunk], d[start : start + chunk])
        colors.append(rgb)
        depths.append(t)
        normals.append(n)
        prims.append(p)
    C = len(cameras)
    depth = rearrange(torch.cat(depths), "(c h w) -> c 1 h w", c=C, h=height)
    normal = rearrange(torch.cat(normals), "(c h w) k -> c k h w", c=C, h=height)
    primitive = rearrange(torch.cat(prims), "(c h w) -> c 1 h w", c=C, h=height)
    if supersample == 1:
        image = rearrange(torch.cat(colors), "(c h w) k -> c k h w", c=C, h=height)
    else:
        s = supersample
        grid = (torch.arange(s, dtype=torch.float64) + 0.5) / s
        offsets = torch.stack(torch.meshgrid(grid, grid, indexing="xy"), -1).reshape(-1, 2)  # [s*s, 2] (ox, oy)
        image = torch.zeros(C, 3, height, width, dtype=dtype)
        for k in range(offsets.shape[0]):
            origins, dirs = pixel_rays(cameras, width, height, offsets[k : k + 1], dtype)
            o = rearrange(origins, "c s h w k -> (c s h w) k")
            d = rearrange(dirs, "c s h w k -> (c s h w) k")
            sub = torch.cat(
                [render_rays(scene, o[i : i + chunk], d[i : i + chunk])[0] for i in range(0, o.shape[0], chunk)]
            )
            image += rearrange(sub, "(c h w) k -> c k h w", c=C, h=height)
        image /= offsets.shape[0]
    return SyntheticRender(image=image, depth=depth, normal=normal, primitive=primitive)
