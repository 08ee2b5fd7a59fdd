"""SurfSplat: feed-forward 2D Gaussian surfel reconstruction from posed images."""

from .compaction import compact
from .gaussians import Gaussians
from .geometry.cameras import Cameras

__version__ = "0.1.0"

__all__ = ["Cameras", "Gaussians", "compact", "__version__"]
