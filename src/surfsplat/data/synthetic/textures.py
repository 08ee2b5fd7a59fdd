"""Procedural solid textures: albedo as a closed-form function of a 3D surface point.

A texture never samples an image, so the colour of a surface point is the same whatever the
resolution of the rendering: the x4 rendering of a view is the scene's own high-resolution
truth, with detail (hard checker/tile edges, fine noise octaves up to several hundred cycles per
metre) that a x1 image cannot hold. Everything is integer hashing and float arithmetic in
PyTorch, so results are bit-identical across runs on one machine.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

Pattern = Literal["checker", "stripes", "marble", "wood", "tiles", "noise"]
PATTERNS: tuple[str, ...] = ("checker", "stripes", "marble", "wood", "tiles", "noise")

_MASK32 = 0xFFFFFFFF


@dataclass
class Texture:
    """Parameters of one procedural surface texture."""

    pattern: Pattern = "noise"  # which closed-form pattern (see `albedo`)
    colors: Tensor | None = None  # [3, 3] palette (three RGB colours in [0, 1])
    frequency: float = 4.0  # cycles per metre of the main pattern
    detail: float = 0.25  # amplitude of the fine multiplicative noise (0 = none)
    detail_frequency: float = 48.0  # cycles per metre of the first detail octave (3 octaves, x2 each)
    seed: int = 0  # lattice seed of every noise term


def lattice_hash(cells: Tensor, seed: int) -> Tensor:
    """Uniform values in [0, 1) for integer lattice points cells [..., 3] (int64): a
    multiplicative hash followed by MurmurHash3's 32-bit finalizer."""
    x, y, z = cells.unbind(-1)
    h = (x * 0x8DA6B343) ^ (y * 0xD8163841) ^ (z * 0xCB1AB31F) ^ ((seed * 0x165667B1) & _MASK32)
    h = h & _MASK32
    h = ((h ^ (h >> 16)) * 0x85EBCA6B) & _MASK32
    h = ((h ^ (h >> 13)) * 0xC2B2AE35) & _MASK32
    h = h ^ (h >> 16)
    return (h >> 8).to(torch.float32) / float(1 << 24)  # top 24 bits: exact in float32


def _seed_offset(seed: int) -> tuple[int, int, int]:
    """Integer lattice offset in [0, 64)^3 of a noise seed (the same hash as `lattice_hash`, on Python ints)."""
    out = []
    for k in range(3):
        h = ((seed * 0x8DA6B343) ^ (k * 0xD8163841) ^ ((k * 0x165667B1) & _MASK32)) & _MASK32
        h = ((h ^ (h >> 16)) * 0x85EBCA6B) & _MASK32
        h = ((h ^ (h >> 13)) * 0xC2B2AE35) & _MASK32
        h ^= h >> 16
        out.append(h % _GRID)
    return out[0], out[1], out[2]


_GRID = 64  # lattice period of the noise table (cells per axis)
_noise_table: Tensor | None = None


def _table() -> Tensor:
    """The shared noise table [1, 1, 65, 65, 65]: uniform values on a 64^3 periodic lattice, with
    the first slice repeated at the end of each axis so trilinear lookups wrap around."""
    global _noise_table
    if _noise_table is None:
        cells = torch.stack(torch.meshgrid(*(torch.arange(_GRID),) * 3, indexing="ij"), -1)  # [64, 64, 64, 3]
        values = lattice_hash(cells.reshape(-1, 3), seed=0x5EED).reshape(_GRID, _GRID, _GRID)
        values = torch.cat([values, values[:1]], 0)
        values = torch.cat([values, values[:, :1]], 1)
        values = torch.cat([values, values[:, :, :1]], 2)
        _noise_table = values[None, None].contiguous()
    return _noise_table


def value_noise(points: Tensor, seed: int) -> Tensor:
    """C2-smooth value noise in [0, 1]: lattice values blended with the quintic fade
    6t^5 - 15t^4 + 10t^3 (Perlin 2002).  points [R, 3] -> [R]

    The lattice values come from a fixed 64^3 periodic table (period 64 cells, i.e. 64 / f
    metres at frequency f); `seed` shifts the lookup by a hashed lattice offset. Sampling the
    table trilinearly at floor(q) + fade(frac(q)) gives exactly the quintic-weighted blend of
    the 8 corner values, in one grid_sample call.
    """
    q = points + torch.tensor(_seed_offset(seed), dtype=points.dtype, device=points.device)
    base = torch.floor(q)
    f = q - base
    w = f * f * f * (f * (f * 6 - 15) + 10)
    coords = torch.remainder(base, _GRID) + w  # in [0, 64]
    grid = coords / _GRID * 2 - 1  # align_corners=True: -1 -> index 0, +1 -> index 64
    table = _table().to(points)
    # grid_sample's last grid axis is (x -> W, y -> H, z -> D).
    out = torch.nn.functional.grid_sample(table, grid[None, None, None], mode="bilinear", align_corners=True)
    return out.reshape(-1)


def fbm(points: Tensor, seed: int, octaves: int, frequency: float, gain: float = 0.5) -> Tensor:
    """Fractal sum of value-noise octaves (frequency doubling, amplitude x gain), normalized
    to [0, 1].  points [R, 3] in metres -> [R]"""
    total = torch.zeros(points.shape[0], dtype=points.dtype, device=points.device)
    norm = 0.0
    amp = 1.0
    for k in range(octaves):
        total = total + amp * value_noise(points * (frequency * 2**k), seed + 7919 * k)
        norm += amp
        amp *= gain
    return total / norm


def _mix(colors: Tensor, a: Tensor, b: Tensor | None = None) -> Tensor:
    """Blend palette colours: lerp(c0, c1, a), then towards c2 by b.  -> [R, 3]"""
    out = colors[0] + (colors[1] - colors[0]) * a[:, None]
    if b is not None:
        out = out + (colors[2] - out) * b[:, None]
    return out


def albedo(texture: Texture, points: Tensor, normals: Tensor) -> Tensor:
    """Albedo [R, 3] in [0, 1] of `texture` at surface points [R, 3] (metres) with unit surface
    normals [R, 3], both in the texture's frame (the primitive's local frame)."""
    if texture.colors is None:
        raise ValueError("texture.colors: a [3, 3] palette is required")
    colors = texture.colors.to(points)
    q = points * texture.frequency
    s = texture.seed
    p = texture.pattern
    if p == "checker":
        parity = torch.remainder(torch.floor(q).sum(-1), 2.0)
        out = _mix(colors, parity, 0.3 * fbm(points, s, 3, 1.5))
    elif p == "stripes":
        phase = 2 * math.pi * q[:, 0] + 3.0 * fbm(points, s, 3, 1.0)
        out = _mix(colors, 0.5 + 0.5 * torch.sin(phase), 0.4 * fbm(points, s + 1, 3, 2.0))
    elif p == "marble":
        turbulence = fbm(points, s, 5, 1.5)
        vein = (0.5 + 0.5 * torch.sin(2 * math.pi * (q[:, 0] + q[:, 2]) + 10.0 * turbulence)).pow(0.3)
        out = _mix(colors, vein, 0.3 * fbm(points, s + 1, 4, 4.0))
    elif p == "wood":
        ring = torch.sqrt(q[:, 0] ** 2 + q[:, 1] ** 2) + 1.5 * fbm(points, s, 3, 2.0)
        grain = torch.remainder(ring, 1.0)
        out = _mix(colors, grain.pow(3), 0.25 * fbm(points * torch.tensor([1.0, 1.0, 0.1]).to(points), s + 1, 3, 20.0))
    elif p == "tiles":
        cell = torch.floor(q)
        frac = q - cell
        # Grout lines: within 6% of a cell border along an axis the surface runs along. The axis
        # closest to the normal is left out, or a face lying on a cell border would be all grout.
        border = torch.minimum(frac, 1 - frac)
        along = normals.abs() < 0.5
        grout = ((border < 0.06) & along).any(-1).to(points.dtype)
        tint = lattice_hash(cell.to(torch.int64), s + 3)
        tile = _mix(colors, tint)
        out = tile + (colors[2] - tile) * grout[:, None]
    elif p == "noise":
        out = _mix(colors, fbm(q, s, 5, 1.0), 0.5 * fbm(points, s + 1, 4, 3.0))
    else:
        raise ValueError(f"texture.pattern: expected one of {PATTERNS}, got {p!r}")
    if texture.detail > 0:
        # Mean-one multiplicative detail: 1 + detail * (2 * fbm - 1).
        fine = fbm(points, s + 11, 3, texture.detail_frequency, gain=0.7)
        out = out * (1 + texture.detail * (2 * fine - 1))[:, None]
    return out.clamp(0, 1)


def random_texture(generator: torch.Generator, pattern: Pattern | None = None) -> Texture:
    """A texture with random pattern, palette, frequency and seed drawn from `generator`."""

    def uniform(lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand((), generator=generator))

    if pattern is None:
        pattern = PATTERNS[int(torch.randint(len(PATTERNS), (), generator=generator))]
    base = torch.rand(3, generator=generator) * 0.7 + 0.2
    # Palette: a base colour, a contrasting one, and a third for grout / secondary blends.
    colors = torch.stack(
        [
            base,
            (1 - base) * 0.8 + 0.1 * torch.rand(3, generator=generator),
            torch.rand(3, generator=generator) * 0.8 + 0.1,
        ]
    )
    frequency = {"checker": (2.0, 6.0), "tiles": (2.0, 5.0), "stripes": (3.0, 10.0)}.get(pattern, (0.8, 3.0))
    return Texture(
        pattern=pattern,
        colors=colors,
        frequency=uniform(*frequency),
        detail=uniform(0.15, 0.35),
        detail_frequency=uniform(30.0, 60.0),
        seed=int(torch.randint(1 << 30, (), generator=generator)),
    )
