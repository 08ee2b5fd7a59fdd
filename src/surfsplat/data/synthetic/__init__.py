"""Procedural synthetic scenes: textured rooms and objects (planes, boxes, spheres, cylinders),
ray-cast in PyTorch with exact depth and normals at any resolution.

    scene = make_scene(seed)                                   # deterministic from the seed
    path = make_trajectory(scene, torch.Generator().manual_seed(1))
    cams = path.cameras(torch.tensor([0.0, 1.0]), 256, 256)   # OpenCV c2w, pixel K
    out = render_synthetic(scene, cams, 256, 256)              # image, depth, normal, primitive
    hr = render_synthetic(scene, cams.scaled(4), 1024, 1024)   # native x4 truth, not an upsampling
"""

from .dataset import SyntheticDataset, SyntheticDatasetConfig, write_synthetic_chunks
from .primitives import Primitive
from .render import SyntheticRender, cast_rays, pixel_rays, render_rays, render_synthetic
from .scene import Lighting, SyntheticConfig, SyntheticScene, Trajectory, look_at, make_scene, make_trajectory
from .textures import Texture, albedo, fbm, value_noise

__all__ = [
    "Lighting",
    "Primitive",
    "SyntheticConfig",
    "SyntheticDataset",
    "SyntheticDatasetConfig",
    "SyntheticRender",
    "SyntheticScene",
    "Texture",
    "Trajectory",
    "albedo",
    "cast_rays",
    "fbm",
    "look_at",
    "make_scene",
    "make_trajectory",
    "pixel_rays",
    "render_rays",
    "render_synthetic",
    "value_noise",
    "write_synthetic_chunks",
]
