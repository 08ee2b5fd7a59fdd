"""From a capture (many photos, a video) to the passes of the network and one fused scene.

    video = select_video_frames("capture.mp4", FrameConfig())         # frames by motion and sharpness
    passes = context_sets(cameras.centers, views_per_pass=2, ordered=True)
    fusion = SurfelFusion(FusionConfig()); fusion.add(gaussians, pass_cameras, h, w)
    fused, stats = refine_on_views(fusion.gaussians(), context_cameras, context_images, w, h)
    fitted, stats = optimize_on_views(fused, context_cameras, context_images, w, h, OptimizeConfig(steps=300))

`surfsplat.reconstruct` puts these together.
"""

from .fusion import FusionConfig, SurfelFusion
from .optimize import OptimizeConfig, optimize_on_views, optimize_summary
from .refine import RefineConfig, refine_on_views, refine_summary
from .video import FrameConfig, FrameRecord, VideoFrames, choose_frames, frame_name, is_video_file, select_video_frames
from .views import context_sets, nearest_neighbour_order

__all__ = [
    "FrameConfig",
    "FrameRecord",
    "FusionConfig",
    "OptimizeConfig",
    "RefineConfig",
    "SurfelFusion",
    "VideoFrames",
    "choose_frames",
    "context_sets",
    "frame_name",
    "is_video_file",
    "nearest_neighbour_order",
    "optimize_on_views",
    "optimize_summary",
    "refine_on_views",
    "refine_summary",
    "select_video_frames",
]
