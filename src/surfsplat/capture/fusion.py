"""Fuse the surfels of many forward passes into one scene, streaming.

    fusion = SurfelFusion(FusionConfig(), mode="surfel", alpha_threshold=0.001)
    for gaussians, cameras in passes:          # one surfel per pixel of each pass's views
        fusion.add(gaussians, cameras, height, width)
    scene = fusion.gaussians()

Overlapping passes predict the same surfaces again (every view of a capture sees much of what its
neighbours see). The views are added one at a time; before a view's surfels join, the scene fused
so far is rendered from that view (colour-free: depth, normal and alpha, with the reconstruction's
forced alpha blending), and a new surfel is a duplicate, and dropped, when at the pixel it was
predicted for the fused scene already
- covers the pixel (alpha >= `cover_alpha`),
- lies at the surfel's depth within `depth_tolerance` (relative: the network's depth error is
  relative, about a tenth on the rooms, so two passes' predictions of one wall differ by that), and
- faces the same way (normals within `normal_degrees`).
Surfels on surfaces the scene does not cover yet, or in front of what is fused (nearer by more than
the tolerance: an occluder the scene lacks), join it. Surfels behind the fused surface are hidden
from their own view by the scene as fused (`drop_hidden`): they would not change that view's
picture, and they are mostly the network's disagreement with itself at depth edges, where
stretched surfels of one pass span the gap another pass sees through; keeping them made the count
grow with the number of frames rather than the area (measured in the README). The views of one
pass are checked against each other the same way, so the count grows with the area seen rather
than with the number of frames.

The finer view wins: each fused surfel remembers its footprint (the world size of a pixel of the
view that predicted it, camera depth / focal). Before the duplicate test, a fused surfel that the
joining view sees at its own predicted depth (same tolerance and orientation) with a footprint
under `replace_ratio` of the surfel's own is replaced: it leaves the scene and the joining view's
surfels there stay. Along a capture that walks toward a surface, the close views' sharper and
better-triangulated surfels take over from the first distant ones.

Fusion is the compaction's cross-view duplicate removal (`compaction._duplicate_cover`) carried
over to a scene that grows: it compares with the rendered scene, so a surface seen again much later
(a loop) is recognised too, and it needs no per-view pixel ownership, which passes do not share.

Memory: only the fused surfels are held (and one view's render); the passes stream through.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..geometry.pixels import pixel_footprints, pixel_grid
from ..utils.checks import SurfSplatInputError


@dataclass(frozen=True)
class FusionConfig:
    """When a new surfel duplicates the fused scene."""

    depth_tolerance: float = 0.1  # |z_new - z_fused| <= this x z_fused (camera depth at the surfel's pixel)
    normal_degrees: float = 60.0  # the surfel's normal within this angle of the fused normal
    cover_alpha: float = 0.5  # the fused scene covers a pixel where its alpha reaches this
    drop_hidden: bool = True  # a new surfel behind the fused surface (beyond the tolerance) is hidden: dropped
    # a view whose footprint is under this x a fused surfel's replaces it (None: never)
    replace_ratio: float | None = 0.7

    def __post_init__(self) -> None:
        if not (math.isfinite(self.depth_tolerance) and self.depth_tolerance >= 0):
            raise SurfSplatInputError(f"fusion.depth_tolerance: expected >= 0, got {self.depth_tolerance}")
        if not 0 <= self.normal_degrees <= 180:
            raise SurfSplatInputError(f"fusion.normal_degrees: expected 0..180, got {self.normal_degrees}")
        if not 0 < self.cover_alpha <= 1:
            raise SurfSplatInputError(f"fusion.cover_alpha: expected a value in (0, 1], got {self.cover_alpha}")
        if self.replace_ratio is not None and not 0 < self.replace_ratio <= 1:
            raise SurfSplatInputError(
                f"fusion.replace_ratio: expected a value in (0, 1] or None, got {self.replace_ratio}"
            )


class SurfelFusion:
    """The scene fused so far; `add` one pass at a time."""

    def __init__(
        self,
        config: FusionConfig | None = None,
        *,
        mode: str = "surfel",
        alpha_threshold: float | None = 0.001,
        backend: str = "auto",
    ):
        self.config = config or FusionConfig()
        self.mode = mode
        self.alpha_threshold = alpha_threshold
        self.backend = backend
        self._parts: list[Gaussians] = []
        self._footprints: list[Tensor] = []  # [N] per part: camera depth / focal of the predicting view
        self._fused: Gaussians | None = None
        self.stats = {"passes": 0, "predicted": 0, "duplicates": 0, "replaced": 0}

    def __len__(self) -> int:
        return sum(len(p) for p in self._parts)

    def gaussians(self) -> Gaussians:
        """The fused scene (all surfels kept so far)."""
        if not self._parts:
            raise SurfSplatInputError("fusion: no surfels were added")
        if self._fused is None or len(self._fused) != len(self):
            self._fused = Gaussians.cat(self._parts)
            self._parts = [self._fused]
            self._footprints = [torch.cat(self._footprints)]
        return self._fused

    @torch.no_grad()
    def add(
        self,
        gaussians: Gaussians,  # [N] unbatched
        cameras: Cameras,  # the V views of the pass, K in pixels of height x width
        height: int,
        width: int,
        pixels: Tensor | None = None,  # [N, 3] (view, row, column) each surfel was predicted at
    ) -> int:
        """Add a pass's surfels that are not duplicates of the scene so far; returns how many joined.
        Without `pixels` the surfels are the model's output: one per pixel, (view, row, column) order."""
        v = len(cameras)
        if pixels is None:
            if len(gaussians) != v * height * width:
                raise SurfSplatInputError(
                    f"fusion: expected one surfel per pixel of {v} views of {width}x{height} "
                    f"({v * height * width:,}), got {len(gaussians):,}; pass their pixels"
                )
            pixels = pixel_grid(v, height, width, gaussians.means.device)
        elif pixels.shape != (len(gaussians), 3):
            raise SurfSplatInputError(f"fusion: pixels expected [{len(gaussians)}, 3], got {tuple(pixels.shape)}")
        g = gaussians.detach()
        pixels = pixels.to(g.means.device)
        cameras = cameras.to(device=g.means.device, dtype=g.means.dtype)
        joined = 0
        for view in range(v):
            idx = torch.nonzero(pixels[:, 0] == view).squeeze(-1)
            if len(idx) == 0:
                continue
            part = g.subset(idx)
            on_view = torch.zeros(len(part), dtype=torch.long, device=g.means.device)
            footprint = pixel_footprints(part, cameras[view], width, height, on_view)
            if self._parts and self.config.replace_ratio is not None:
                self._replace(part, footprint, pixels[idx, 1:], cameras[view], height, width)
            if self._parts:
                duplicate = self._duplicates(part, pixels[idx, 1:], cameras[view], height, width)
                self.stats["duplicates"] += int(duplicate.sum())
                part, footprint = part.subset(~duplicate), footprint[~duplicate]
            if len(part):
                self._parts.append(part)
                self._footprints.append(footprint)
                joined += len(part)
            self.stats["predicted"] += len(idx)
        self.stats["passes"] += 1
        return joined

    def _replace(
        self, new: Gaussians, footprint: Tensor, pixel: Tensor, camera: Cameras, height: int, width: int
    ) -> None:
        """Drop the fused surfels that one view's new surfels (at `pixel`, [M, 2] row, column) show
        finer: the fused surfel projects to a pixel whose new surfel lies at its depth, faces its way,
        and has a footprint under replace_ratio x its own."""
        fused = self.gaussians()
        old_footprint = self._footprints[0]
        w2c = camera.w2c[0]
        uv, z, front = _project(fused.means, camera)
        col, row = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        inside = front & (col >= 0) & (col < width) & (row >= 0) & (row < height)
        # the new surfel predicted at each pixel (-1: none)
        at = torch.full((height * width,), -1, dtype=torch.long, device=z.device)
        at[pixel[:, 0] * width + pixel[:, 1]] = torch.arange(len(new), device=z.device)
        which = torch.where(inside, at[(row * width + col).clamp(0, height * width - 1)], torch.full_like(col, -1))
        candidate = torch.nonzero(which >= 0).squeeze(-1)
        if len(candidate) == 0:
            return
        j = which[candidate]
        z_new = new.means[j] @ w2c[2, :3] + w2c[2, 3]
        cfg = self.config
        same_depth = (z[candidate] - z_new).abs() <= cfg.depth_tolerance * z_new
        cosine = (fused.normals[candidate] * new.normals[j]).sum(-1).abs()
        facing = cosine >= math.cos(math.radians(cfg.normal_degrees))
        finer = footprint[j] < cfg.replace_ratio * old_footprint[candidate]
        gone = candidate[same_depth & facing & finer]
        if len(gone) == 0:
            return
        keep = torch.ones(len(fused), dtype=torch.bool, device=z.device)
        keep[gone] = False
        self._fused = fused.subset(keep)
        self._parts = [self._fused]
        self._footprints = [old_footprint[keep]]
        self.stats["replaced"] += len(gone)

    def _duplicates(self, new: Gaussians, pixel: Tensor, camera: Cameras, height: int, width: int) -> Tensor:
        """[M] which of one view's new surfels lie on the fused scene as that view sees it."""
        from ..render import render

        fused = self.gaussians()
        seen = fused.subset(_in_view(fused.means, camera, height, width))
        if len(seen) == 0:
            return torch.zeros(len(new), dtype=torch.bool, device=new.means.device)
        colourless = Gaussians(
            seen.means, seen.quats, seen.scales, seen.opacities, torch.zeros_like(seen.sh[..., :1]), validate=False
        )
        out = render(
            colourless,
            camera,
            width,
            height,
            mode=self.mode,
            backend=self.backend,
            alpha_threshold=self.alpha_threshold,
        )
        r, c = pixel[:, 0], pixel[:, 1]
        alpha = out.alpha[0, 0, r, c]
        depth = out.depth[0, 0, r, c]
        normal = out.normal[0, :, r, c].T  # [M, 3] world, facing the camera
        w2c = camera.w2c[0]
        z = new.means @ w2c[2, :3] + w2c[2, 3]
        n = new.normals
        toward = camera.centers[0] - new.means
        n = torch.where((n * toward).sum(-1, keepdim=True) < 0, -n, n)
        cfg = self.config
        covered = alpha >= cfg.cover_alpha
        same_depth = (z - depth).abs() <= cfg.depth_tolerance * depth
        facing = (n * normal).sum(-1) >= math.cos(math.radians(cfg.normal_degrees)) * normal.norm(dim=-1)
        if cfg.drop_hidden:
            hidden = z > (1 + cfg.depth_tolerance) * depth
            return covered & ((same_depth & facing) | hidden)
        return covered & same_depth & facing


def _in_view(means: Tensor, camera: Cameras, height: int, width: int, margin: float = 0.25) -> Tensor:
    """[N] surfels in front of the camera whose centres project within the image grown by `margin`
    of its size each side (the render of the fused scene needs only these)."""
    uv, _, front = _project(means, camera)
    mu, mv = margin * width, margin * height
    return front & (uv[:, 0] > -mu) & (uv[:, 0] < width + mu) & (uv[:, 1] > -mv) & (uv[:, 1] < height + mv)


def _project(means: Tensor, camera: Cameras) -> tuple[Tensor, Tensor, Tensor]:  # means [N, 3]
    """Pixel coordinates [N, 2], camera depths [N] and whether each point is in front of `camera`
    (points behind it get meaningless coordinates)."""
    w2c = camera.w2c[0]
    p = means @ w2c[:3, :3].T + w2c[:3, 3]
    z = p[:, 2]
    front = z > 1e-6
    uv = (p @ camera.K[0].T)[:, :2] / torch.where(front, z, torch.ones_like(z))[:, None]
    return uv, z, front
