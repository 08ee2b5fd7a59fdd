"""Camera poses and intrinsics from the photos alone (pycolmap), for `surfsplat poses` and
`surfsplat reconstruct` without a camera file. See `estimate.py` for the pipeline and conventions."""

from .errors import aligned_pose_errors, relative_pose_errors
from .estimate import PairStats, PoseCamera, PoseConfig, PoseSummary, estimate_cameras
from .exif import exif_focal

__all__ = [
    "PairStats",
    "aligned_pose_errors",
    "PoseCamera",
    "PoseConfig",
    "PoseSummary",
    "estimate_cameras",
    "exif_focal",
    "relative_pose_errors",
]
