"""`AppConfig`: how the app is served (address, limits, how long files are kept) and its defaults."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from ..capture.refine import RefineConfig
from ..utils.checks import SurfSplatInputError
from .run import APP_OPTIMIZE_SECONDS


@dataclass(frozen=True)
class AppConfig:
    """Every field has the default `surfsplat app` uses."""

    host: str = "127.0.0.1"  # this machine only; another address serves the network
    port: int = 7860  # gradio's usual port (0: any free port)
    max_upload_mb: float = 200.0  # one run's uploads together (a zip's unpacked size too)
    # a shared server's limits, checked before any heavy work: views of one run (photos, the photos a
    # capture's camera file lists, a video's frames used), and the seconds of one run (checked at every step)
    max_views: int = 60
    max_seconds: float = 600.0
    keep_minutes: float = 60.0  # a run's folder (uploads and results) is removed this long after it started
    max_queue: int | None = 20  # people waiting at most (None: no limit); more are told to come back
    working_size: int = 256  # the page's default working size (long side in pixels)
    refine_fits: float = RefineConfig.fits_per_view  # the page's default refinement: fits of each context view
    optimize_seconds: float = APP_OPTIMIZE_SECONDS  # the page's default per-scene optimization budget (0: none)
    device: str = "auto"  # torch device of the runs ("auto": CUDA when available)
    sessions_dir: str | None = None  # where session folders go (default: <temp>/surfsplat-app)
    # ExportOptions for the page's outputs (RunSettings fields: path_frames, turntable_frames, mesh_resolution, bake_steps)
    export: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise SurfSplatInputError(f"port (--port): expected 0 to 65535, got {self.port}")
        if not self.max_upload_mb > 0:
            raise SurfSplatInputError(
                f"max_upload_mb (--max-upload-mb): expected a positive size, got {self.max_upload_mb}"
            )
        if isinstance(self.max_views, bool) or not isinstance(self.max_views, int) or self.max_views < 2:
            raise SurfSplatInputError(f"max_views (--max-views): expected at least 2 views, got {self.max_views}")
        if not self.max_seconds > 0:
            raise SurfSplatInputError(
                f"max_seconds (--max-run-seconds): expected a positive time, got {self.max_seconds}"
            )
        if not self.keep_minutes > 0:
            raise SurfSplatInputError(
                f"keep_minutes (--keep-minutes): expected a positive time, got {self.keep_minutes}"
            )
        unknown = set(self.export) - {"path_frames", "turntable_frames", "mesh_resolution", "bake_steps", "zoom"}
        if unknown:
            raise SurfSplatInputError(f"export: unknown settings {sorted(unknown)}")

    def max_upload_bytes(self) -> int:
        return int(self.max_upload_mb * 1e6)

    def root(self) -> Path:
        return Path(self.sessions_dir) if self.sessions_dir else Path(tempfile.gettempdir()) / "surfsplat-app"

    @property
    def local_only(self) -> bool:
        return self.host in ("127.0.0.1", "localhost", "::1")
