"""SurfSplat: feed-forward 2D Gaussian surfel reconstruction from posed images.

The public names load on first use (PEP 562), so `import surfsplat.cli` runs before torch is imported:
the command line sets its OpenMP defaults first (`surfsplat.cli`).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

# public name -> the module that defines it
_PUBLIC = {
    "Cameras": ".geometry.cameras",
    "CaptureOptions": ".reconstruction",
    "Gaussians": ".geometry.gaussians",
    "OptimizeConfig": ".capture.optimize",
    "Scene": ".reconstruction",
    "compact": ".compaction",
    "reconstruct": ".reconstruction",
}

__all__ = ["Cameras", "CaptureOptions", "Gaussians", "OptimizeConfig", "Scene", "compact", "reconstruct", "__version__"]

if TYPE_CHECKING:
    from .capture.optimize import OptimizeConfig
    from .compaction import compact
    from .geometry.cameras import Cameras
    from .geometry.gaussians import Gaussians
    from .reconstruction import CaptureOptions, Scene, reconstruct


def __getattr__(name: str) -> Any:
    if name not in _PUBLIC:
        raise AttributeError(f"module 'surfsplat' has no attribute {name!r}")
    value = getattr(importlib.import_module(_PUBLIC[name], __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))
