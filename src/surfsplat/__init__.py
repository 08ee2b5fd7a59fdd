"""SurfSplat: feed-forward 2D Gaussian surfel reconstruction from posed images."""

from .capture.optimize import OptimizeConfig
from .compaction import compact
from .geometry.cameras import Cameras
from .geometry.gaussians import Gaussians
from .reconstruction import CaptureOptions, Scene, reconstruct

__version__ = "0.1.0"

__all__ = ["Cameras", "CaptureOptions", "Gaussians", "OptimizeConfig", "Scene", "compact", "reconstruct", "__version__"]
