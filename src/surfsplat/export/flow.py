"""`export_reconstruction`: everything people look at for one reconstruction, in one folder.

`surfsplat reconstruct`, `surfsplat export`, `Scene.save` and the demo all call it, so every entry
point writes the same files:
    surfels.ply            the surfels (2DGS layout: two scales per surfel)
    surfels_3dgs.ply       the surfels baked for standard 3DGS viewers (`bake=None`: unbaked)
    surfels_3dgs.json      the bake's figures: standard viewers' alpha and colour PSNR against our render
    cameras.json           the context cameras (JSON camera file)
    renders/               colour, depth and normal PNGs of every context view
    path/                  frames of the interpolated camera path; path.mp4, turntable.mp4
    mesh.ply               TSDF fusion of rendered depth, marching cubes
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
from torch import Tensor

from ..utils.checks import SurfSplatInputError
from ..utils.log import progress
from .bake import BakeConfig

logger = logging.getLogger(__name__)


FORMATS = ("ply", "renders", "video", "mesh")


@dataclass(frozen=True)
class ExportOptions:
    """What `export_reconstruction` writes and how."""

    formats: tuple[str, ...] = FORMATS  # any of ply, renders, video, mesh
    scale: float = 1.0  # render resolution factor for images and videos (K scaled by it)
    path_frames: int = 48  # frames of the interpolated camera path (video and mesh views)
    turntable_frames: int = 48  # frames of the turntable video
    turntable_degrees: float = 30.0  # total sweep of the turntable
    fps: float = 24.0  # frame rate of both videos
    mesh_resolution: int = 128  # TSDF voxels along the longest side
    mode: Literal["surfel", "ewa"] = "surfel"  # rasterization
    alpha_threshold: float | None = 0.001  # forced alpha blending tau (None: plain compositing)
    antialiased: bool = False  # renders with the antialiasing filter (a scene fitted with it)
    progress: bool = True  # progress over frames (a bar on a terminal, log lines elsewhere)
    bake: BakeConfig | None = BakeConfig()  # surfels_3dgs.ply for standard 3DGS viewers (None: unbaked)

    def __post_init__(self) -> None:
        unknown = sorted(set(self.formats) - set(FORMATS))
        if unknown:
            raise SurfSplatInputError(f"formats: unknown {unknown}, expected any of {FORMATS}")
        if not self.scale > 0:
            raise SurfSplatInputError(f"scale: expected a positive factor, got {self.scale}")
        if self.path_frames < 2 or self.turntable_frames < 2:
            raise SurfSplatInputError("path_frames and turntable_frames: expected at least 2 frames")


def output_names(formats) -> list[str]:
    """The files `export_reconstruction` writes at the top of its folder for `formats`."""
    names = ["cameras.json"]
    if "ply" in formats:
        names += ["surfels.ply", "surfels_3dgs.ply"]
    if "video" in formats:
        names += ["path.mp4", "turntable.mp4"]
    if "mesh" in formats:
        names.append("mesh.ply")
    return names


def export_reconstruction(
    gaussians,  # unbatched surfsplat.Gaussians
    cameras,  # the context cameras (surfsplat.Cameras), K in pixels of width x height
    width: int,
    height: int,
    out_dir: str | Path,
    options: ExportOptions = ExportOptions(),
    *,
    names: list[str] | None = None,
    near: float | None = None,
    far: float | None = None,
    write_surfels: bool = True,
    seconds: dict[str, float] | None = None,
    crop=None,  # surfsplat.data.transforms.WorkingCrop of the photos the cameras' K is in pixels of
    lenses=None,  # each view's source Lens (a capture with a lens), recorded in cameras.json
) -> dict[str, Path]:
    """Write what people look at for one reconstruction; returns {what: path}. Each file is written
    under a temporary name and renamed, so an interrupted export leaves no half-written file.
    `seconds`, when given, receives the wall time of each step (ply, bake, renders, path, turntable,
    mesh). `crop` and `lenses` are recorded in cameras.json (see `save_cameras`)."""
    import time

    from ..data.cameras import save_cameras
    from .images import colorize_depth, normal_to_rgb, write_png
    from .mesh import TsdfConfig, mesh_from_renders, save_mesh
    from .paths import focus_point, interpolate_cameras, turntable
    from .ply import save_ply
    from .video import video_unavailable, write_video

    out = Path(out_dir)
    written: dict[str, Path] = {}
    seconds = {} if seconds is None else seconds
    tick = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal tick
        now = time.perf_counter()
        seconds[name] = seconds.get(name, 0.0) + now - tick
        tick = now

    if "video" in options.formats:
        reason = video_unavailable()
        if reason is not None:  # fail before any work, not after minutes of rendering
            raise SurfSplatInputError(f"--formats video: {reason}")
    if write_surfels and "ply" in options.formats:
        written["surfels (2DGS PLY)"] = save_ply(gaussians, out / "surfels.ply")
        lap("ply")
        written.update(write_viewer_ply(gaussians, cameras, width, height, out, options))
        lap("bake" if options.bake is not None else "3dgs ply")
    written["cameras"] = save_cameras(
        out / "cameras.json", cameras, width, height, names, near, far, crop=crop, lenses=lenses
    )

    s = options.scale
    w, h = max(1, round(width * s)), max(1, round(height * s))

    def draw(cams, what: str):
        return render_frames(gaussians, cams.scaled(s), w, h, options, what)

    # Depth is valid where forced alpha blending normalised it (alpha >= tau); without FAB, where
    # the surfels cover the pixel (alpha >= 0.5).
    tau = options.alpha_threshold if options.alpha_threshold is not None else 0.5
    context = draw(cameras, "context views")
    if "renders" in options.formats:
        shown = (context.alpha >= tau).float()
        for i in range(len(cameras)):
            tag = f"view{i:02d}"
            write_png(out / "renders" / f"{tag}_color.png", context.color[i])
            write_png(out / "renders" / f"{tag}_depth.png", colorize_depth(context.depth[i], shown[i]))
            write_png(out / "renders" / f"{tag}_normal.png", normal_to_rgb(context.normal[i]))
        written["context renders"] = out / "renders"
    lap("renders")
    need_path = "video" in options.formats or "mesh" in options.formats
    path_cams = interpolate_cameras(cameras, options.path_frames) if need_path and len(cameras) >= 2 else None
    path = None
    if path_cams is not None:
        path = draw(path_cams, "camera path")
        lap("path")
    if "video" in options.formats:
        if path is not None:
            for f in range(len(path_cams)):
                write_png(out / "path" / f"frame{f:03d}.png", path.color[f])
            written["path frames"] = out / "path"
            written["path video"] = write_video(out / "path.mp4", path.color, options.fps)
        focus = focus_point(context.depth, context.alpha >= tau, cameras)
        spin = draw(turntable(cameras, focus, options.turntable_frames, options.turntable_degrees), "turntable")
        written["turntable video"] = write_video(out / "turntable.mp4", spin.color, options.fps)
        lap("turntable")
    if "mesh" in options.formats:
        views = [context] + ([path] if path is not None else [])
        fuse_cams = cameras if path_cams is None else _cat_cameras(cameras, path_cams)
        mesh = mesh_from_renders(
            torch.cat([v.depth for v in views]),
            torch.cat([v.alpha for v in views]),
            torch.cat([v.color for v in views]),
            fuse_cams.scaled(s),
            TsdfConfig(resolution=options.mesh_resolution),
            min_alpha=tau,
        )
        written["mesh (TSDF fusion)"] = save_mesh(mesh, out / "mesh.ply")
        lap("mesh")
    return written


def write_viewer_ply(gaussians, cameras, width: int, height: int, out: Path, options: ExportOptions) -> dict[str, Path]:
    """surfels_3dgs.ply: baked for standard 3DGS viewers (`surfsplat.export.bake`), with its figures in
    surfels_3dgs.json; with `options.bake` None, the thin surfels as they are."""
    from .bake import bake_for_viewers, thin_gaussians
    from .figures import write_text
    from .ply import save_ply

    if options.bake is None:
        return {"surfels (3DGS PLY, unbaked)": save_ply(thin_gaussians(gaussians), out / "surfels_3dgs.ply")}
    baked, report = bake_for_viewers(
        gaussians,
        cameras,
        height,
        width,
        options.bake,
        mode=options.mode,
        alpha_threshold=options.alpha_threshold,
        show_progress=options.progress,
        antialiased=options.antialiased,
    )
    logger.debug(report.summary())  # the figures are in surfels_3dgs.json; -v shows them here
    return {
        "surfels (3DGS PLY, baked for viewers)": save_ply(baked, out / "surfels_3dgs.ply"),
        "viewer bake figures": write_text(out / "surfels_3dgs.json", json.dumps(report.to_dict(), indent=1) + "\n"),
    }


@dataclass
class Frames:
    color: Tensor  # [F, 3, H, W]
    alpha: Tensor  # [F, 1, H, W]
    depth: Tensor  # [F, 1, H, W]
    normal: Tensor  # [F, 3, H, W]


@torch.inference_mode()
def render_frames(gaussians, cameras, width: int, height: int, options: ExportOptions, what: str) -> Frames:
    """Render cameras one at a time (bounded memory) with a progress bar; the frames stay on the
    Gaussians' device (the mesh fuses them there; PNG and MP4 writing takes them to the host)."""
    from ..render import render

    outs = []
    for i in progress(
        range(len(cameras)),
        desc=f"render {what}",
        unit="frame",
        enabled=options.progress and len(cameras) >= 4,
        leave=False,
    ):
        r = render(
            gaussians,
            cameras[i],
            width,
            height,
            mode=options.mode,
            alpha_threshold=options.alpha_threshold,
            antialiased=options.antialiased,
        )
        outs.append(r)
    return Frames(*(torch.cat([getattr(r, k) for r in outs]) for k in ("color", "alpha", "depth", "normal")))


def _cat_cameras(a, b):
    from ..geometry.cameras import Cameras

    return Cameras(torch.cat([a.c2w, b.c2w.to(a.c2w)]), torch.cat([a.K, b.K.to(a.K)]), validate=False)
