"""From a capture (many photos, a video) to the passes of the network and one fused scene.

    video = select_video_frames("capture.mp4", FrameConfig())         # frames by motion and sharpness
    passes = context_sets(cameras.centers, views_per_pass=2, ordered=True)
    fusion = SurfelFusion(FusionConfig()); fusion.add(gaussians, pass_cameras, h, w)
    fused, stats = refine_on_views(fusion.gaussians(), context_cameras, context_images, w, h)

`surfsplat.reconstruct` puts these together.
"""

from .fusion import FusionConfig, SurfelFusion
from .refine import RefineConfig, refine_on_views, refine_summary
from .video import FrameConfig, FrameRecord, VideoFrames, choose_frames, frame_name, is_video_file, select_video_frames
from .views import context_sets, nearest_neighbour_order

__all__ = [
    "FrameConfig",
    "FrameRecord",
    "FusionConfig",
    "RefineConfig",
    "SurfelFusion",
    "VideoFrames",
    "choose_frames",
    "context_sets",
    "frame_name",
    "is_video_file",
    "nearest_neighbour_order",
    "refine_on_views",
    "refine_summary",
    "select_video_frames",
]
