"""Procedural synthetic scenes: textured rooms and objects (planes, boxes, spheres, cylinders),
ray-cast in PyTorch with exact depth and normals at any resolution.

    scene = make_scene(seed)                                   # deterministic from the seed
    path = make_trajectory(scene, torch.Generator().manual_seed(1))
    cams = path.cameras(torch.tensor([0.0, 1.0]), 256, 256)   # OpenCV c2w, pixel K
    out = render_synthetic(scene, cams, 256, 256)              # image, depth, normal, primitive
    hr = render_synthetic(scene, cams.scaled(4), 1024, 1024)   # native x4 truth, not an upsampling
    truth = geometry_truth(scene, cams, 256, 256, seen_from=Viewpoints(context_cams, 256, 256))
    samples = surface_samples(scene, 20_000, seen_from=Viewpoints(context_cams, 256, 256))
"""

from .dataset import SyntheticDataset, SyntheticDatasetConfig, write_synthetic_chunks
from .primitives import Primitive
from .render import SyntheticRender, cast_rays, pixel_rays, ray_geometry, render_rays, render_synthetic
from .scene import Lighting, SyntheticConfig, SyntheticScene, Trajectory, make_scene, make_trajectory
from .textures import Texture, albedo, fbm, value_noise
from .truth import (
    GeometryTruth,
    SurfaceSamples,
    Viewpoints,
    geometry_truth,
    scene_from_key,
    seen_by,
    surface_samples,
)

__all__ = [
    "GeometryTruth",
    "Lighting",
    "Primitive",
    "SyntheticConfig",
    "SyntheticDataset",
    "SyntheticDatasetConfig",
    "SyntheticRender",
    "SurfaceSamples",
    "SyntheticScene",
    "Texture",
    "Trajectory",
    "Viewpoints",
    "albedo",
    "cast_rays",
    "fbm",
    "geometry_truth",
    "make_scene",
    "make_trajectory",
    "pixel_rays",
    "ray_geometry",
    "render_rays",
    "render_synthetic",
    "scene_from_key",
    "seen_by",
    "surface_samples",
    "value_noise",
    "write_synthetic_chunks",
]
