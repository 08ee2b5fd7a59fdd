"""Analytic primitives: ray intersection, outward normal and signed distance in closed form.

Each primitive lives in its own local frame: world = center + rotation @ local. Rays are
o + t d with d not necessarily unit length; render.py builds d with camera-z component 1, so
the t returned here IS the camera z-depth.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from .textures import Texture

PrimitiveKind = Literal["plane", "box", "sphere", "cylinder"]
KINDS: tuple[str, ...] = ("plane", "box", "sphere", "cylinder")
T_MIN = 1e-5  # hits closer than this along the ray are ignored (self-intersection guard)


@dataclass
class Primitive:
    """One analytic surface.

    kind:     "plane" (infinite; local z is its normal), "box" (half extents size),
              "sphere" (radius size[0]), "cylinder" (capped, axis local z, radius size[0],
              half height size[1])
    center:   [3] world position of the local origin
    rotation: [3, 3] local-to-world rotation (columns are the local axes in world coordinates)
    size:     [3] see kind
    texture:  its procedural surface texture, evaluated in the local frame
    """

    kind: PrimitiveKind
    center: Tensor  # [3]
    rotation: Tensor  # [3, 3]
    size: Tensor  # [3]
    texture: Texture

    def to_local(self, points: Tensor) -> Tensor:
        """[R, 3] world points -> local coordinates."""
        return (points - self.center.to(points)) @ self.rotation.to(points)

    def intersect(self, origins: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        """First hit with t > T_MIN: (t [R], inf where missed; outward normal [R, 3] in the LOCAL frame)."""
        o = self.to_local(origins)
        d = dirs @ self.rotation.to(dirs)
        fn = {"plane": _plane, "box": _box, "sphere": _sphere, "cylinder": _cylinder}[self.kind]
        return fn(o, d, self.size.to(origins))

    def signed_distance(self, points: Tensor) -> Tensor:
        """Signed distance [R] of world points (negative inside; for a plane, the side its normal leaves)."""
        p = self.to_local(points)
        s = self.size.to(points)
        if self.kind == "plane":
            return p[:, 2]
        if self.kind == "sphere":
            return p.norm(dim=-1) - s[0]
        if self.kind == "box":
            q = p.abs() - s
            return q.clamp_min(0).norm(dim=-1) + q.amax(-1).clamp_max(0)
        if self.kind == "cylinder":
            q = torch.stack([p[:, :2].norm(dim=-1) - s[0], p[:, 2].abs() - s[1]], -1)
            return q.clamp_min(0).norm(dim=-1) + q.amax(-1).clamp_max(0)
        raise ValueError(f"primitive kind: expected one of {KINDS}, got {self.kind!r}")

    def local_normal(self, local_points: Tensor) -> Tensor:
        """Outward unit normal [R, 3] (local frame) at local points on the surface."""
        p = local_points
        s = self.size.to(p)
        if self.kind == "plane":
            return torch.zeros_like(p) + torch.tensor([0.0, 0.0, 1.0]).to(p)
        if self.kind == "sphere":
            return p / p.norm(dim=-1, keepdim=True)
        if self.kind == "box":
            axis = (p.abs() / s).argmax(-1)
            return torch.nn.functional.one_hot(axis, 3).to(p) * torch.sign(p)
        if self.kind == "cylinder":
            on_cap = (p[:, 2].abs() - s[1]).abs() < (p[:, :2].norm(dim=-1) - s[0]).abs()
            side = torch.cat([p[:, :2] / p[:, :2].norm(dim=-1, keepdim=True), torch.zeros_like(p[:, :1])], -1)
            cap = torch.zeros_like(p)
            cap[:, 2] = torch.sign(p[:, 2])
            return torch.where(on_cap[:, None], cap, side)
        raise ValueError(f"primitive kind: expected one of {KINDS}, got {self.kind!r}")


def _nearest_positive(candidates: Tensor) -> tuple[Tensor, Tensor]:
    """candidates [R, k] (inf = invalid) -> (smallest t > T_MIN [R], its column [R])."""
    c = torch.where(candidates > T_MIN, candidates, torch.full_like(candidates, torch.inf))
    return c.min(-1)


def _plane(o: Tensor, d: Tensor, size: Tensor) -> tuple[Tensor, Tensor]:
    # n . (o + t d) = 0 with n = e_z.
    dz = d[:, 2]
    t = torch.where(dz != 0, -o[:, 2] / torch.where(dz != 0, dz, torch.ones_like(dz)), torch.full_like(dz, torch.inf))
    t = torch.where(t > T_MIN, t, torch.full_like(t, torch.inf))
    n = torch.zeros_like(o)
    n[:, 2] = 1
    return t, n


def _sphere(o: Tensor, d: Tensor, size: Tensor) -> tuple[Tensor, Tensor]:
    # |o + t d|^2 = r^2: a t^2 + b t + c = 0.
    r = size[0]
    a = (d * d).sum(-1)
    b = 2 * (o * d).sum(-1)
    c = (o * o).sum(-1) - r * r
    disc = b * b - 4 * a * c
    root = disc.clamp_min(0).sqrt()
    inf = torch.full_like(a, torch.inf)
    t0 = torch.where(disc >= 0, (-b - root) / (2 * a), inf)
    t1 = torch.where(disc >= 0, (-b + root) / (2 * a), inf)
    t, _ = _nearest_positive(torch.stack([t0, t1], -1))
    p = o + torch.where(torch.isfinite(t), t, torch.zeros_like(t))[:, None] * d
    return t, p / r


def _box(o: Tensor, d: Tensor, size: Tensor) -> tuple[Tensor, Tensor]:
    # Slab method (Kay & Kajiya 1986): intersect the three pairs of parallel faces.
    tiny = torch.finfo(d.dtype).tiny
    safe = torch.where(d.abs() > tiny, d, torch.where(d >= 0, 1.0, -1.0) * tiny)
    t1 = (-size - o) / safe
    t2 = (size - o) / safe
    t_near, t_far = torch.minimum(t1, t2), torch.maximum(t1, t2)
    enter, enter_axis = t_near.max(-1)
    leave, leave_axis = t_far.min(-1)
    hit = (leave >= enter) & (leave > T_MIN)
    inside = enter <= T_MIN  # ray starts inside: the hit is where it leaves
    t = torch.where(hit, torch.where(inside, leave, enter), torch.full_like(enter, torch.inf))
    axis = torch.where(inside, leave_axis, enter_axis)
    sign = torch.where(inside, 1.0, -1.0) * torch.sign(safe.gather(-1, axis[:, None]).squeeze(-1))
    n = torch.nn.functional.one_hot(axis, 3).to(o) * sign[:, None]
    return t, n


def _cylinder(o: Tensor, d: Tensor, size: Tensor) -> tuple[Tensor, Tensor]:
    r, h = size[0], size[1]
    inf = torch.full_like(o[:, 0], torch.inf)
    # Side: (ox + t dx)^2 + (oy + t dy)^2 = r^2, accepted where |z| <= h.
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = 2 * (o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1])
    c = o[:, 0] ** 2 + o[:, 1] ** 2 - r * r
    disc = b * b - 4 * a * c
    ok = (disc >= 0) & (a > 0)
    root = disc.clamp_min(0).sqrt()
    a_safe = torch.where(a > 0, a, torch.ones_like(a))
    sides = []
    for t_side in ((-b - root) / (2 * a_safe), (-b + root) / (2 * a_safe)):
        z = o[:, 2] + t_side * d[:, 2]
        sides.append(torch.where(ok & (z.abs() <= h), t_side, inf))
    # Caps: z = +-h, accepted where x^2 + y^2 <= r^2.
    caps = []
    dz = d[:, 2]
    dz_safe = torch.where(dz != 0, dz, torch.ones_like(dz))
    for zc in (h, -h):
        t_cap = (zc - o[:, 2]) / dz_safe
        xy = o[:, :2] + t_cap[:, None] * d[:, :2]
        caps.append(torch.where((dz != 0) & ((xy * xy).sum(-1) <= r * r), t_cap, inf))
    t, which = _nearest_positive(torch.stack(sides + caps, -1))
    p = o + torch.where(torch.isfinite(t), t, torch.zeros_like(t))[:, None] * d
    side_n = torch.cat([p[:, :2] / r, torch.zeros_like(p[:, :1])], -1)
    cap_n = torch.zeros_like(p)
    cap_n[:, 2] = torch.where(which == 2, 1.0, -1.0)
    n = torch.where((which >= 2)[:, None], cap_n, side_n)
    return t, n
