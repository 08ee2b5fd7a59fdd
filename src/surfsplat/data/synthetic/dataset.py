"""The synthetic scenes as a map-style training Dataset and as chunks on disk.

Sample i is a fixed function of (seed, i): scene, camera path, view choice and pixels are the
same in every run and every worker, so a DistributedSampler shards it like any map dataset.
Samples follow the layout documented in `surfsplat.data.dataset`, plus "normal" [V, 3, H, W].
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor
from torch.utils.data import Dataset

from ...geometry.cameras import Cameras
from ...utils.checks import SurfSplatInputError
from ..chunks import ChunkWriter, scene_to_example
from ..dataset import Sample, mix_seed
from ..posed_images import PosedImages
from .render import render_synthetic
from .scene import SyntheticConfig, SyntheticScene, Trajectory, make_scene, make_trajectory


@dataclass
class SyntheticDatasetConfig:
    """Synthetic training samples: context views at both ends of a camera path, targets between."""

    length: int = 1000  # number of samples (one procedural room each)
    seed: int = 0  # base seed; sample i uses a seed mixed from (seed, i)
    image_shape: tuple[int, int] = (256, 256)  # (H, W) of every view
    num_context_views: int = 2  # 2: the path's ends; more: the ends plus random points between
    num_target_views: int = 4  # uniformly random points along the path
    supersample: int = 2  # rays per pixel per axis for the images (anti-aliasing); depth is exact per pixel centre
    with_depth: bool = True  # add "depth" and "normal" to every view
    # Native high-resolution truth of the targets: 0 = none; s > 1 adds "image_hr" and "K_hr" to the
    # target views, ray-cast with K scaled by s (one ray per pixel: at s >= 2 a pixel is already finer
    # than the input's), over a random `highres_crop` x `highres_crop` window of the s-times image
    # (0: the whole image), so x4 supervision costs what x1 costs.
    highres_factor: int = 0
    highres_crop: int = 0
    scene: SyntheticConfig = field(default_factory=SyntheticConfig)  # how rooms and paths are drawn


class SyntheticDataset(Dataset):
    """Map-style dataset of procedural rooms; see the module doc for determinism."""

    def __init__(self, config: SyntheticDatasetConfig | None = None) -> None:
        self.config = config or SyntheticDatasetConfig()
        c = self.config
        if c.length < 1:
            raise SurfSplatInputError(f"length: expected >= 1, got {c.length}")
        if c.num_context_views < 2 or c.num_target_views < 1:
            raise SurfSplatInputError(
                f"num_context_views >= 2 and num_target_views >= 1 expected, got {c.num_context_views}, {c.num_target_views}"
            )
        h, w = c.image_shape
        if h < 1 or w < 1:
            raise SurfSplatInputError(f"image_shape: expected positive (H, W), got {c.image_shape}")
        if c.highres_factor < 0 or c.highres_factor == 1:
            raise SurfSplatInputError(f"highres_factor: expected 0 (off) or an integer >= 2, got {c.highres_factor}")
        if c.highres_factor and not 0 <= c.highres_crop <= c.highres_factor * min(h, w):
            raise SurfSplatInputError(
                f"highres_crop: expected 0 (whole image) up to {c.highres_factor * min(h, w)}, got {c.highres_crop}"
            )

    def __len__(self) -> int:
        return self.config.length

    def _check(self, index: int) -> int:
        if not 0 <= index < len(self):
            raise IndexError(f"sample {index} out of range for {len(self)} samples")
        return index

    def scene_seed(self, index: int) -> int:
        return mix_seed(self.config.seed, self._check(index)) & 0x7FFFFFFF

    def scene(self, index: int) -> SyntheticScene:
        """The procedural room of sample `index`."""
        return make_scene(self.scene_seed(index), self.config.scene)

    def trajectory(self, index: int, scene: SyntheticScene | None = None) -> Trajectory:
        scene = scene or self.scene(index)
        h, w = self.config.image_shape
        g = torch.Generator().manual_seed(mix_seed(self.scene_seed(index), 1))
        return make_trajectory(scene, g, aspect=w / h)

    def path_positions(self, index: int) -> tuple[Tensor, Tensor]:
        """(context, target) positions in [0, 1] along the sample's camera path."""
        c = self.config
        g = torch.Generator().manual_seed(mix_seed(self.scene_seed(index), 2))
        inner = torch.sort(torch.rand(c.num_context_views - 2, generator=g, dtype=torch.float64)).values
        context = torch.cat([torch.zeros(1, dtype=torch.float64), inner, torch.ones(1, dtype=torch.float64)])
        target = torch.rand(c.num_target_views, generator=g, dtype=torch.float64)
        return context, target

    def cameras(self, index: int, scale: float = 1.0) -> tuple[Cameras, Cameras]:
        """(context, target) cameras of a sample, for images `scale` times the configured size."""
        trajectory = self.trajectory(index)
        h, w = self.config.image_shape
        context, target = self.path_positions(index)
        cams = [trajectory.cameras(s, w, h) for s in (context, target)]
        if scale != 1.0:
            cams = [c.scaled(scale) for c in cams]
        return cams[0], cams[1]

    def __getitem__(self, index: int) -> Sample:
        c = self.config
        scene = self.scene(index)
        context, target = self.cameras(index)
        h, w = c.image_shape
        both = Cameras(torch.cat([context.c2w, target.c2w]), torch.cat([context.K, target.K]), validate=False)
        out = render_synthetic(scene, both, w, h, supersample=c.supersample)
        nc = len(context)

        def views(sl: slice, cams: Cameras) -> dict[str, Tensor]:
            n = len(cams)
            v = {
                "image": out.image[sl],
                "c2w": cams.c2w.float(),
                "K": cams.K.float(),
                "near": torch.full((n,), c.scene.near),
                "far": torch.full((n,), c.scene.far),
                "index": torch.arange(n, dtype=torch.int64),
            }
            if c.with_depth:
                v["depth"] = out.depth[sl]
                v["normal"] = out.normal[sl]
            return v

        sample = {
            "context": views(slice(0, nc), context),
            "target": views(slice(nc, None), target),
            "scene": f"synthetic-{c.seed}-{index}",
        }
        if c.highres_factor:
            sample["target"].update(self._highres(index, scene, target))
        return sample

    def highres_window(self, index: int, num_views: int) -> tuple[int, int, int, int]:
        """(x0, y0, width, height) per target view of the high-resolution crop, in s-times pixels;
        a fixed function of (seed, index), like everything else of a sample."""
        c = self.config
        s, (h, w) = c.highres_factor, c.image_shape
        cw, ch = (c.highres_crop, c.highres_crop) if c.highres_crop else (s * w, s * h)
        g = torch.Generator().manual_seed(mix_seed(self.scene_seed(index), 3))
        x0 = torch.randint(0, s * w - cw + 1, (num_views,), generator=g)
        y0 = torch.randint(0, s * h - ch + 1, (num_views,), generator=g)
        return x0, y0, cw, ch

    def _highres(self, index: int, scene: SyntheticScene, target: Cameras) -> dict[str, Tensor]:
        x0, y0, cw, ch = self.highres_window(index, len(target))
        K = target.scaled(float(self.config.highres_factor)).K.clone()
        K[:, 0, 2] -= x0.to(K.dtype)  # a crop only moves the principal point
        K[:, 1, 2] -= y0.to(K.dtype)
        images = [
            render_synthetic(scene, Cameras(target.c2w[i : i + 1], K[i : i + 1], validate=False), cw, ch).image[0]
            for i in range(len(target))
        ]
        return {"image_hr": torch.stack(images), "K_hr": K.float()}


def write_synthetic_chunks(
    out_dir: str | Path,
    num_scenes: int,
    seed: int = 0,
    image_shape: tuple[int, int] = (256, 256),
    num_frames: int = 32,
    supersample: int = 2,
    image_format: str = "png",
    config: SyntheticConfig | None = None,
    target_bytes: int = int(1e8),
) -> dict[str, str]:
    """Render `num_scenes` rooms as videos of `num_frames` frames evenly spaced along each camera
    path, and write them as chunks (key `synthetic-{seed}-{i}`) with 16-bit PNG depths in
    millimetres. PNG images keep the rendering exact up to 8-bit quantization. Pair it with a
    `BoundedViewSampler` whose gaps fit num_frames. Returns the index."""
    dataset = SyntheticDataset(
        SyntheticDatasetConfig(
            length=num_scenes,
            seed=seed,
            image_shape=image_shape,
            supersample=supersample,
            scene=config or SyntheticConfig(),
        )
    )
    h, w = image_shape
    with ChunkWriter(out_dir, target_bytes=target_bytes) as writer:
        for i in range(num_scenes):
            scene = dataset.scene(i)
            cams = dataset.trajectory(i, scene).cameras(torch.linspace(0, 1, num_frames, dtype=torch.float64), w, h)
            out = render_synthetic(scene, cams, w, h, supersample=supersample)
            record = PosedImages(
                images=out.image, cameras=cams, names=[str(k) for k in range(num_frames)], depths=out.depth
            )
            writer.add(
                scene_to_example(record, key=f"synthetic-{seed}-{i}", url="synthetic", image_format=image_format)
            )
    return dict(writer.index)
