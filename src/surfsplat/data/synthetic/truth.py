"""Exact geometry of procedural scenes: the one source of truth for geometry metrics.

    scene = make_scene(seed)
    context = Viewpoints(context_cameras, 64, 64)                  # what the reconstruction saw
    truth = geometry_truth(scene, target_cameras, 64, 64, seen_from=context)
    truth.depth, truth.normal, truth.mask                            # [C,1,H,W], [C,3,H,W], [C,1,H,W]
    samples = surface_samples(scene, 20_000, seen_from=context)      # area-uniform surface points

Everything here is analytic, in float64: depth and normals are the pixel-centre rays' first hits
(any resolution, any camera), surface samples are drawn on the primitives' closed-form surfaces, and
visibility is decided by casting the ray from a camera's centre to the point itself (no depth-map
quantization): a point is seen by a view when it projects inside that view's image, lies in front
of the camera, and nothing on the ray is hit before it.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import torch
from einops import rearrange
from torch import Tensor

from ...geometry.cameras import Cameras
from ...utils.checks import SurfSplatInputError
from .primitives import Primitive
from .render import cast_rays, pixel_rays, ray_geometry
from .scene import SyntheticConfig, SyntheticScene

# A point on a surface is unoccluded when the first hit on its ray is not in front of it by more than
# this relative margin: float64 ray casting reproduces the point's own depth to ~1e-12, and the margin
# (1 micrometre per metre) also accepts points given in float32, a few nanometres off their surface.
VISIBILITY_TOLERANCE = 1e-6
SCENE_KEY = re.compile(r"^synthetic-(\d+)-(\d+)$")  # chunk keys written by write_synthetic_chunks


@dataclass(frozen=True)
class Viewpoints:
    """Cameras and the size (pixels) of their images: what decides whether a point is seen."""

    cameras: Cameras
    width: int
    height: int

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise SurfSplatInputError(f"viewpoints: expected a positive image size, got {self.width}x{self.height}")


@dataclass
class GeometryTruth:
    """Exact geometry of C views at one resolution.

    depth:  [C, 1, H, W] camera-z depth of the pixel-centre ray's first hit (0 where nothing is hit)
    normal: [C, 3, H, W] unit world normal there, facing the camera (0 where nothing is hit)
    points: [C, 3, H, W] world position of the hit (0 where nothing is hit)
    hit:    [C, 1, H, W] bool, a surface is hit
    mask:   [C, 1, H, W] bool, hit and (with seen_from) seen by at least one of those viewpoints
    """

    depth: Tensor
    normal: Tensor
    points: Tensor
    hit: Tensor
    mask: Tensor


@dataclass
class SurfaceSamples:
    """Points drawn uniformly by area on a scene's surfaces."""

    points: Tensor  # [N, 3] world positions (float64)
    normals: Tensor  # [N, 3] unit outward normals of the primitives (room walls point into the room)
    primitive: Tensor  # [N] int64 index into scene.primitives


def geometry_truth(
    scene: SyntheticScene,
    cameras: Cameras,
    width: int,
    height: int,
    seen_from: Viewpoints | None = None,
    chunk: int = 1 << 18,
) -> GeometryTruth:
    """Exact depth, normals and hit points of `cameras` (K in pixels of a width x height image).

    seen_from: restrict `mask` to pixels whose surface point at least one of these viewpoints sees
    (e.g. the context views of a reconstruction: surfaces it could not have seen are not scored).
    """
    if width < 1 or height < 1:
        raise SurfSplatInputError(f"width, height: expected positive sizes, got {width}x{height}")
    origins, dirs = pixel_rays(cameras, width, height, torch.tensor([[0.5, 0.5]]), torch.float64)
    o = rearrange(origins, "c s h w k -> (c s h w) k")
    d = rearrange(dirs, "c s h w k -> (c s h w) k")
    depths, normals, prims = [], [], []
    for start in range(0, o.shape[0], chunk):
        t, n, p = ray_geometry(scene, o[start : start + chunk], d[start : start + chunk])
        depths.append(t)
        normals.append(n)
        prims.append(p)
    t, n, hit = torch.cat(depths), torch.cat(normals), torch.cat(prims) >= 0
    points = torch.where(hit[:, None], o + t[:, None] * d, torch.zeros_like(o))
    mask = hit.clone()
    if seen_from is not None:
        mask[hit] = seen_by(scene, points[hit], seen_from)
    c = len(cameras)
    return GeometryTruth(
        depth=rearrange(t, "(c h w) -> c 1 h w", c=c, h=height),
        normal=rearrange(n, "(c h w) k -> c k h w", c=c, h=height),
        points=rearrange(points, "(c h w) k -> c k h w", c=c, h=height),
        hit=rearrange(hit, "(c h w) -> c 1 h w", c=c, h=height),
        mask=rearrange(mask, "(c h w) -> c 1 h w", c=c, h=height),
    )


def seen_by(scene: SyntheticScene, points: Tensor, views: Viewpoints) -> Tensor:
    """bool [N]: which surface points [N, 3] at least one view sees (in its image, in front, unoccluded)."""
    if points.ndim != 2 or points.shape[-1] != 3:
        raise SurfSplatInputError(f"points: expected shape [N, 3], got {tuple(points.shape)}")
    p = points.to(torch.float64)
    seen = torch.zeros(p.shape[0], dtype=torch.bool)
    c2w = views.cameras.c2w.to(torch.float64)
    K = views.cameras.K.to(torch.float64)
    for k in range(c2w.shape[0]):
        rotation, origin = c2w[k, :3, :3], c2w[k, :3, 3]
        local = (p - origin) @ rotation  # camera frame: R^T (p - o)
        z = local[:, 2]
        front = z > 0
        z_safe = torch.where(front, z, torch.ones_like(z))
        pixel = (local / z_safe[:, None]) @ K[k].T
        inside = front & (pixel[:, 0] >= 0) & (pixel[:, 0] < views.width) & (pixel[:, 1] >= 0)
        inside &= pixel[:, 1] < views.height
        if not bool(inside.any()):
            continue
        # The ray from the centre through the point, scaled to camera-z 1: its hit parameter is a depth.
        dirs = (p[inside] - origin) / z[inside, None]
        t, _, _ = cast_rays(scene, origin.expand_as(dirs), dirs)
        visible = t >= z[inside] * (1 - VISIBILITY_TOLERANCE)
        idx = inside.nonzero().squeeze(-1)
        seen[idx[visible]] = True
    return seen


def surface_samples(
    scene: SyntheticScene,
    count: int,
    seen_from: Viewpoints | None = None,
    generator: torch.Generator | None = None,
    max_rounds: int = 64,
) -> SurfaceSamples:
    """`count` points uniform by area on the scene's surfaces (room walls clipped to the room).

    seen_from: keep only points these viewpoints see; candidates are drawn until `count` of them are
    seen, so the samples stay uniform by area over the visible surface.
    """
    if count < 1:
        raise SurfSplatInputError(f"count: expected at least 1 surface sample, got {count}")
    generator = generator if generator is not None else torch.Generator().manual_seed(0)
    patches = [patch for k, prim in enumerate(scene.primitives) for patch in _patches(scene, k, prim)]
    areas = torch.tensor([area for area, _, _ in patches], dtype=torch.float64)
    kept: list[tuple[Tensor, Tensor, Tensor]] = []
    have = 0
    batch = max(count, 4096)
    for _ in range(max_rounds):
        which = torch.multinomial(areas, batch, replacement=True, generator=generator)
        for j in which.unique().tolist():
            n = int((which == j).sum())
            _, prim_index, sampler = patches[j]
            points, normals = sampler(n, generator)
            if seen_from is not None:
                keep = seen_by(scene, points, seen_from)
                points, normals = points[keep], normals[keep]
            kept.append((points, normals, torch.full((points.shape[0],), prim_index, dtype=torch.int64)))
            have += points.shape[0]
        if have >= count:
            break
    else:
        raise SurfSplatInputError(
            f"surface samples: only {have} of {count} points are seen by the viewpoints after {max_rounds} rounds"
        )
    points, normals, prim = (torch.cat(parts) for parts in zip(*kept))
    # Candidates were grouped by patch above; shuffle so that any prefix is an area-uniform sample too.
    order = torch.randperm(points.shape[0], generator=generator)[:count]
    return SurfaceSamples(points=points[order], normals=normals[order], primitive=prim[order])


def _uniform(n: int, lo: float, hi: float, generator: torch.Generator) -> Tensor:
    return lo + (hi - lo) * torch.rand(n, generator=generator, dtype=torch.float64)


def _patches(scene: SyntheticScene, index: int, prim: Primitive) -> list[tuple[float, int, object]]:
    """(area, primitive index, sampler(n, generator) -> (world points [n, 3], world normals [n, 3])) per face."""
    rotation = prim.rotation.to(torch.float64)
    center = prim.center.to(torch.float64)
    size = prim.size.to(torch.float64)

    def world(sample_local):
        def sampler(n: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
            local_p, local_n = sample_local(n, generator)
            return center + local_p @ rotation.T, local_n @ rotation.T

        return sampler

    if prim.kind == "plane":
        # Room walls: infinite planes, of which the part inside the room's box is surface.
        normal = rotation[:, 2]
        axis = int(normal.abs().argmax())
        if abs(abs(float(normal[axis])) - 1.0) > 1e-6:
            raise SurfSplatInputError(f"scene {scene.seed}: plane {index} is not axis-aligned; its area is unbounded")
        lo, hi = scene.room_min.to(torch.float64), scene.room_max.to(torch.float64)
        a, b = [k for k in range(3) if k != axis]

        def plane(n: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
            p = torch.empty(n, 3, dtype=torch.float64)
            p[:, axis] = center[axis]
            p[:, a] = _uniform(n, float(lo[a]), float(hi[a]), generator)
            p[:, b] = _uniform(n, float(lo[b]), float(hi[b]), generator)
            return p, normal.expand(n, 3)

        return [(float((hi[a] - lo[a]) * (hi[b] - lo[b])), index, plane)]
    if prim.kind == "box":
        out = []
        for axis in range(3):
            a, b = (axis + 1) % 3, (axis + 2) % 3
            for sign in (-1.0, 1.0):

                def face(n, generator, axis=axis, a=a, b=b, sign=sign):
                    p = torch.empty(n, 3, dtype=torch.float64)
                    p[:, axis] = sign * size[axis]
                    p[:, a] = _uniform(n, -float(size[a]), float(size[a]), generator)
                    p[:, b] = _uniform(n, -float(size[b]), float(size[b]), generator)
                    normal = torch.zeros(n, 3, dtype=torch.float64)
                    normal[:, axis] = sign
                    return p, normal

                out.append((float(4 * size[a] * size[b]), index, world(face)))
        return out
    if prim.kind == "sphere":
        r = float(size[0])

        def sphere(n: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
            # Normalized Gaussian vectors are uniform on the sphere (Muller 1959).
            v = torch.nn.functional.normalize(torch.randn(n, 3, generator=generator, dtype=torch.float64), dim=-1)
            return r * v, v

        return [(4 * math.pi * r * r, index, world(sphere))]
    if prim.kind == "cylinder":
        r, h = float(size[0]), float(size[1])

        def side(n: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
            angle = _uniform(n, 0.0, 2 * math.pi, generator)
            radial = torch.stack([angle.cos(), angle.sin(), torch.zeros_like(angle)], -1)
            p = r * radial
            p[:, 2] = _uniform(n, -h, h, generator)
            return p, radial

        def cap(n, generator, sign):
            # sqrt of a uniform radius fraction: uniform by area on the disc.
            radius = r * torch.rand(n, generator=generator, dtype=torch.float64).sqrt()
            angle = _uniform(n, 0.0, 2 * math.pi, generator)
            p = torch.stack([radius * angle.cos(), radius * angle.sin(), torch.full_like(radius, sign * h)], -1)
            normal = torch.zeros(n, 3, dtype=torch.float64)
            normal[:, 2] = sign
            return p, normal

        return [
            (2 * math.pi * r * 2 * h, index, world(side)),
            (math.pi * r * r, index, world(lambda n, g: cap(n, g, 1.0))),
            (math.pi * r * r, index, world(lambda n, g: cap(n, g, -1.0))),
        ]
    raise SurfSplatInputError(f"scene {scene.seed}: primitive {index} has unknown kind {prim.kind!r}")


def scene_from_key(key: str, config: SyntheticConfig | None = None) -> SyntheticScene | None:
    """The procedural room behind a chunk key `synthetic-{seed}-{i}` (as `write_synthetic_chunks`
    names them, with the same SyntheticConfig), or None for any other key."""
    from .dataset import SyntheticDataset, SyntheticDatasetConfig

    match = SCENE_KEY.match(key)
    if match is None:
        return None
    seed, index = int(match.group(1)), int(match.group(2))
    dataset = SyntheticDataset(SyntheticDatasetConfig(length=index + 1, seed=seed, scene=config or SyntheticConfig()))
    return dataset.scene(index)


__all__ = [
    "GeometryTruth",
    "SurfaceSamples",
    "Viewpoints",
    "geometry_truth",
    "scene_from_key",
    "seen_by",
    "surface_samples",
]
