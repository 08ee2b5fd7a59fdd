"""Data: single-scene readers, RealEstate10K-style chunks, view samplers, streaming datasets,
converters and the procedural synthetic world.

    scene = load_scene("my_capture")          # LLFF / DTU / transforms.json / COLMAP / RE10K .txt
    scene.images  # [N, 3, H, W] in [0, 1];  scene.cameras: OpenCV c2w, pixel K
"""

from .chunks import ChunkWriter, example_to_scene, load_example, read_chunk, read_index, scene_to_example, write_chunks
from .dataset import ChunkDataset, ChunkDatasetConfig, DatasetSummary, views_to_cameras
from .eval_index import EvaluationEntry, EvaluationIndex
from .load import detect_format, load_scene, load_scene_cameras
from .posed_images import PosedImages
from .synthetic import SyntheticDataset, SyntheticDatasetConfig, make_scene, render_synthetic, write_synthetic_chunks
from .transforms import center_crop, horizontal_flip, rescale_and_crop, resize_views
from .view_sampler import (
    BoundedViewSampler,
    BoundedViewSamplerConfig,
    EvaluationViewSampler,
    NotEnoughViews,
    StepCounter,
)

__all__ = [
    "BoundedViewSampler",
    "BoundedViewSamplerConfig",
    "ChunkDataset",
    "ChunkDatasetConfig",
    "ChunkWriter",
    "DatasetSummary",
    "EvaluationEntry",
    "EvaluationIndex",
    "EvaluationViewSampler",
    "NotEnoughViews",
    "PosedImages",
    "StepCounter",
    "load_scene_cameras",
    "SyntheticDataset",
    "SyntheticDatasetConfig",
    "center_crop",
    "detect_format",
    "example_to_scene",
    "horizontal_flip",
    "load_example",
    "load_scene",
    "make_scene",
    "read_chunk",
    "read_index",
    "render_synthetic",
    "rescale_and_crop",
    "resize_views",
    "scene_to_example",
    "views_to_cameras",
    "write_chunks",
    "write_synthetic_chunks",
]
