"""Settings of the compiled CPU renderer (importable without numba)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

from ...utils.checks import SurfSplatInputError
from ..types import RenderConventions

Precision = Literal["auto", "float32", "float64"]


@dataclass
class CpuRenderSettings(RenderConventions):
    tile_size: int = 32  # tile edge in pixels: the unit of parallel work and of early termination
    near_plane: float = 0.01  # Gaussians closer than this (camera z) are culled, as in the torch backend
    far_plane: float = 1e10  # Gaussians farther than this are culled
    parallel_chunk: int = 4  # tiles a thread takes at a time (small chunks balance uneven tiles)
    # Float type of the compositing (the per-pixel work): "auto" follows the Gaussians (float64 for
    # float64, float32 for any other); the per-Gaussian geometry is float64 either way.
    precision: Precision = "auto"

    def __post_init__(self) -> None:
        super().__post_init__()
        if not isinstance(self.tile_size, int) or isinstance(self.tile_size, bool) or self.tile_size <= 0:
            raise SurfSplatInputError(f"settings.tile_size: expected a positive int, got {self.tile_size!r}")
        if not 0 <= self.near_plane < self.far_plane:
            raise SurfSplatInputError(
                f"settings.near_plane/far_plane: expected 0 <= near < far, got {self.near_plane!r}, {self.far_plane!r}"
            )
        if not isinstance(self.parallel_chunk, int) or self.parallel_chunk <= 0:
            raise SurfSplatInputError(f"settings.parallel_chunk: expected a positive int, got {self.parallel_chunk!r}")
        if self.precision not in get_args(Precision):
            raise SurfSplatInputError(
                f"settings.precision: expected 'auto', 'float32' or 'float64', got {self.precision!r}"
            )
