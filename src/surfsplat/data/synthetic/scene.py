"""Procedural rooms: a textured box of walls around textured boxes, spheres and cylinders, plus
camera trajectories with RealEstate10K-like baselines. Deterministic from an integer seed.

World frame: z up, floor at z = 0, the room spans [-a, a] x [-b, b] x [0, height].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from ...geometry.cameras import Cameras, look_at
from ...utils.checks import SurfSplatInputError
from .primitives import Primitive
from .textures import random_texture

WORLD_DOWN = (0.0, 0.0, -1.0)  # world z is up; the cameras' image y axis leans down (no roll)


@dataclass
class SyntheticConfig:
    """How random rooms and camera paths are drawn (all lengths in metres)."""

    room_half_extent: tuple[float, float] = (2.5, 4.0)  # range of the room's half width / half depth
    room_height: tuple[float, float] = (2.5, 3.2)  # range of the ceiling height
    num_objects: tuple[int, int] = (3, 6)  # inclusive range of objects on the floor
    object_radius: tuple[float, float] = (0.25, 0.7)  # range of an object's footprint radius
    camera_height: tuple[float, float] = (1.0, 1.7)  # range of the camera height above the floor
    fov_deg: tuple[float, float] = (55.0, 75.0)  # range of the horizontal field of view
    baseline: tuple[float, float] = (0.15, 0.6)  # range of the distance between the first and last frame
    min_look_distance: float = 1.2  # the looked-at point is at least this far from the camera
    look_jitter: float = 0.2  # the looked-at point moves up to this much along a trajectory
    near: float = 0.5  # depth bound: every visible surface is at least this far (camera z)
    far: float = 15.0  # depth bound: beyond the largest room's diagonal


@dataclass
class Lighting:
    """View-independent lighting: ambient + one directional light + one lamp without shadows."""

    ambient: float = 0.35  # constant term
    directional: float = 0.35  # strength of the directional light
    direction: Tensor = field(default_factory=lambda: torch.tensor([0.3, -0.4, 0.866]))  # unit vector towards it
    lamp: float = 0.6  # strength of the point light
    position: Tensor = field(default_factory=lambda: torch.tensor([0.0, 0.0, 2.4]))  # lamp position
    falloff: float = 0.1  # lamp attenuation 1 / (1 + falloff * distance^2)


@dataclass
class SyntheticScene:
    """A procedural room: primitives[0:6] are the room's planes (normals pointing inwards)."""

    primitives: list[Primitive]
    lighting: Lighting
    room_min: Tensor  # [3]
    room_max: Tensor  # [3]
    seed: int
    config: SyntheticConfig


def _uniform(g: torch.Generator, lo: float, hi: float) -> float:
    return lo + (hi - lo) * float(torch.rand((), generator=g, dtype=torch.float64))


def _rot_z(angle: float) -> Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _frame_with_normal(normal: tuple[float, float, float]) -> Tensor:
    """A rotation whose local z axis is `normal` (an axis-aligned unit vector)."""
    n = torch.tensor(normal)
    helper = torch.tensor([0.0, 0.0, 1.0]) if abs(float(n[2])) < 0.5 else torch.tensor([1.0, 0.0, 0.0])
    u = torch.linalg.cross(helper, n)
    u = u / u.norm()
    v = torch.linalg.cross(n, u)
    return torch.stack([u, v, n], dim=1)


def make_scene(seed: int, config: SyntheticConfig | None = None) -> SyntheticScene:
    """A random room from `seed`: six textured planes and config.num_objects objects resting on
    the floor without overlapping (boxes turned about z, spheres, upright cylinders)."""
    config = config or SyntheticConfig()
    g = torch.Generator().manual_seed(int(seed))
    a = _uniform(g, *config.room_half_extent)
    b = _uniform(g, *config.room_half_extent)
    height = _uniform(g, *config.room_height)

    prims: list[Primitive] = []
    floor_tex = random_texture(g, pattern=["wood", "tiles", "checker"][int(torch.randint(3, (), generator=g))])
    wall_patterns = ["stripes", "noise", "marble", "tiles"]
    walls = [
        ((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), floor_tex),  # floor
        ((0.0, 0.0, height), (0.0, 0.0, -1.0), random_texture(g, pattern="noise")),  # ceiling
    ]
    for point, normal in (
        ((-a, 0.0, 0.0), (1.0, 0.0, 0.0)),
        ((a, 0.0, 0.0), (-1.0, 0.0, 0.0)),
        ((0.0, -b, 0.0), (0.0, 1.0, 0.0)),
        ((0.0, b, 0.0), (0.0, -1.0, 0.0)),
    ):
        pattern = wall_patterns[int(torch.randint(len(wall_patterns), (), generator=g))]
        walls.append((point, normal, random_texture(g, pattern=pattern)))
    for point, normal, tex in walls:
        prims.append(Primitive("plane", torch.tensor(point), _frame_with_normal(normal), torch.zeros(3), tex))

    count = int(torch.randint(config.num_objects[0], config.num_objects[1] + 1, (), generator=g))
    footprints: list[tuple[float, float, float]] = []
    for _ in range(200 * max(count, 1)):
        if len(footprints) == count:
            break
        r = _uniform(g, *config.object_radius)
        x = _uniform(g, -a + r + 0.3, a - r - 0.3)
        y = _uniform(g, -b + r + 0.3, b - r - 0.3)
        if any((x - fx) ** 2 + (y - fy) ** 2 < (r + fr + 0.3) ** 2 for fx, fy, fr in footprints):
            continue
        footprints.append((x, y, r))
        kind = ["box", "sphere", "cylinder"][int(torch.randint(3, (), generator=g))]
        tex = random_texture(g)
        if kind == "box":
            # Half extents whose horizontal diagonal is the footprint radius.
            angle = _uniform(g, 0.3, 1.27)
            hx, hy = r * math.cos(angle), r * math.sin(angle)
            hz = _uniform(g, 0.2, 1.0)
            prims.append(
                Primitive(
                    "box", torch.tensor([x, y, hz]), _rot_z(_uniform(g, 0, math.pi)), torch.tensor([hx, hy, hz]), tex
                )
            )
        elif kind == "sphere":
            prims.append(
                Primitive(
                    "sphere", torch.tensor([x, y, r]), _rot_z(_uniform(g, 0, math.pi)), torch.tensor([r, 0.0, 0.0]), tex
                )
            )
        else:
            hz = _uniform(g, 0.25, 0.9)
            prims.append(
                Primitive(
                    "cylinder",
                    torch.tensor([x, y, hz]),
                    _rot_z(_uniform(g, 0, math.pi)),
                    torch.tensor([r, hz, 0.0]),
                    tex,
                )
            )
    lighting = Lighting(
        direction=torch.nn.functional.normalize(
            torch.tensor([_uniform(g, -0.5, 0.5), _uniform(g, -0.5, 0.5), 1.0]), dim=0
        ),
        position=torch.tensor([_uniform(g, -0.5 * a, 0.5 * a), _uniform(g, -0.5 * b, 0.5 * b), height - 0.3]),
    )
    return SyntheticScene(
        primitives=prims,
        lighting=lighting,
        room_min=torch.tensor([-a, -b, 0.0]),
        room_max=torch.tensor([a, b, height]),
        seed=int(seed),
        config=config,
    )


def _clearance(scene: SyntheticScene, eyes: Tensor) -> Tensor:
    """Distance [N] from each eye to the nearest surface (walls exactly, objects by their signed distance)."""
    dists = torch.stack([prim.signed_distance(eyes) for prim in scene.primitives], -1)
    return dists.amin(-1)


@dataclass
class Trajectory:
    """A straight camera path: eyes and looked-at points move linearly from s = 0 to s = 1."""

    eye0: Tensor  # [3]
    eye1: Tensor  # [3]
    target0: Tensor  # [3]
    target1: Tensor  # [3]
    fov_deg: float  # horizontal field of view

    def cameras(self, s: Tensor, width: int, height: int) -> Cameras:
        """Cameras at path parameters s [N] in [0, 1] for width x height images (square pixels,
        principal point at the image centre)."""
        s = s.to(torch.float64)[:, None]
        eyes = self.eye0.double() * (1 - s) + self.eye1.double() * s
        targets = self.target0.double() * (1 - s) + self.target1.double() * s
        c2w = look_at(eyes, targets, WORLD_DOWN).float()
        f = 0.5 * width / math.tan(math.radians(self.fov_deg) / 2)
        K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]]).repeat(len(s), 1, 1)
        return Cameras(c2w, K)


def make_trajectory(
    scene: SyntheticScene,
    generator: torch.Generator,
    aspect: float = 1.0,
    max_tries: int = 1000,
) -> Trajectory:
    """A random straight path inside the room looking at one of its objects.

    The baseline (eye0 -> eye1) is drawn from config.baseline, mostly sideways with some forward
    motion, as in RealEstate10K walk-throughs. Every camera along the path keeps a clearance of
    near / cos(half the diagonal field of view) from every surface, so each visible point has
    camera z-depth >= config.near; `aspect` is width / height of the images to be rendered.
    """
    cfg = scene.config
    objects = scene.primitives[6:]
    lo, hi = scene.room_min.double(), scene.room_max.double()
    for _ in range(max_tries):
        fov = _uniform(generator, *cfg.fov_deg)
        half_w = math.tan(math.radians(fov) / 2)
        half_diag = math.atan(half_w * math.sqrt(1 + 1 / aspect**2))
        clearance = cfg.near / math.cos(half_diag) + 0.05
        eye0 = torch.tensor(
            [
                _uniform(generator, float(lo[0]) + clearance, float(hi[0]) - clearance),
                _uniform(generator, float(lo[1]) + clearance, float(hi[1]) - clearance),
                _uniform(generator, *cfg.camera_height),
            ],
            dtype=torch.float64,
        )
        if objects:
            target = objects[int(torch.randint(len(objects), (), generator=generator))].center.double()
        else:
            target = (lo + hi) / 2
        target = target + (torch.rand(3, generator=generator, dtype=torch.float64) - 0.5) * 0.4
        forward = target - eye0
        if forward.norm() < cfg.min_look_distance or abs(float(forward[2] / forward.norm())) > 0.6:
            continue
        forward_h = torch.nn.functional.normalize(
            torch.tensor([float(forward[0]), float(forward[1]), 0.0], dtype=torch.float64), dim=0
        )
        right = torch.tensor([float(forward_h[1]), -float(forward_h[0]), 0.0], dtype=torch.float64)
        theta = math.radians(_uniform(generator, -60.0, 60.0))
        sign = 1.0 if float(torch.rand((), generator=generator)) < 0.5 else -1.0
        direction = sign * math.cos(theta) * right + math.sin(theta) * forward_h
        direction[2] = _uniform(generator, -0.1, 0.1)
        direction = direction / direction.norm()
        eye1 = eye0 + _uniform(generator, *cfg.baseline) * direction
        jitter = torch.nn.functional.normalize(torch.randn(3, generator=generator, dtype=torch.float64), dim=0)
        target1 = target + jitter * _uniform(generator, 0.0, cfg.look_jitter)
        # Straight path: check the clearance densely along it (surfaces are convex or planar).
        s = torch.linspace(0, 1, 33, dtype=torch.float64)[:, None]
        eyes = eye0 * (1 - s) + eye1 * s
        if float(_clearance(scene, eyes.float()).min()) < clearance:
            continue
        if float((target1 - eye1).norm()) < cfg.min_look_distance:
            continue
        return Trajectory(eye0.float(), eye1.float(), target.float(), target1.float(), fov)
    raise SurfSplatInputError(
        f"synthetic scene {scene.seed}: no camera path satisfies the clearance after {max_tries} tries"
    )
