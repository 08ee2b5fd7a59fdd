"""`surfsplat export PLY --cameras CAMS`: PLY, mesh and videos from a reconstruction saved earlier.

    surfsplat export out/surfels.ply --cameras out/cameras.json --formats mesh video --out out/export

`export_reconstruction` is also what `reconstruct` and `demo` call, so every command writes the
same files:
    surfels.ply            the surfels (2DGS layout: two scales per surfel)
    surfels_3dgs.ply       the surfels baked for standard 3DGS viewers (3DGS layout; `--raw-3dgs`: unbaked)
    surfels_3dgs.json      the bake's figures: standard viewers' alpha and colour PSNR against our render
    cameras.json           the context cameras (JSON camera file)
    renders/               colour, depth and normal PNGs of every context view
    path/                  frames of the interpolated camera path; path.mp4, turntable.mp4
    mesh.ply               TSDF fusion of rendered depth, marching cubes
"""

from __future__ import annotations

import argparse
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
from torch import Tensor

from ..checks import SurfSplatInputError, check_output_dir
from ..compaction import DEFAULT_LEVEL, LEVELS
from ..export.bake import BakeConfig
from ..log import progress

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


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("ply", type=Path, help="surfels written by reconstruct (surfels.ply)")
    parser.add_argument(
        "--cameras",
        type=Path,
        required=True,
        help="the reconstruction's cameras.json, another JSON camera file, a COLMAP model or a scene folder",
    )
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: beside the PLY)")
    parser.add_argument("--formats", nargs="+", choices=FORMATS, default=["ply", "video", "mesh"], help="what to write")
    add_export_arguments(parser)


def add_export_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by reconstruct and export."""
    group = parser.add_argument_group("renders, videos and mesh")
    group.add_argument("--scale", type=float, default=1.0, help="render resolution factor for images and videos")
    group.add_argument("--frames", type=int, default=48, help="frames of the interpolated path and of the turntable")
    group.add_argument("--degrees", type=float, default=30.0, help="total sweep of the turntable")
    group.add_argument("--fps", type=float, default=24.0)
    group.add_argument("--mesh-resolution", type=int, default=128, help="TSDF voxels along the longest side")
    group.add_argument(
        "--mode",
        choices=("surfel", "ewa"),
        default=None,
        help="rasterization (default: surfel; ewa for 3DGS-layout files)",
    )
    group.add_argument(
        "--alpha-threshold",
        type=float,
        default=0.001,
        help="forced alpha blending tau (paper Sec. 3.4; reconstruct uses the model's); negative turns it off",
    )
    group.add_argument(
        "--raw-3dgs",
        action="store_true",
        help="write surfels_3dgs.ply as the thin surfels are, without baking it for standard 3DGS viewers "
        "(which then show it faint: they do not apply forced alpha blending)",
    )
    add_compact_argument(
        group,
        f"fewer surfels for the same picture (surfsplat.compact): level 1 (gentle) to 5 (strong); "
        f"{DEFAULT_LEVEL} when no level is given",
    )
    group.add_argument("--no-progress", action="store_true")


def add_compact_argument(group: argparse._ActionsContainer, help_text: str) -> None:
    """`--compact [LEVEL]`: a compaction level of `surfsplat.compact`, the default level when none is given."""
    group.add_argument(
        "--compact",
        nargs="?",
        type=int,
        const=DEFAULT_LEVEL,
        default=None,
        choices=sorted(LEVELS),
        metavar="LEVEL",
        help=help_text,
    )


def options_from_args(args: argparse.Namespace, formats: tuple[str, ...], mode: str) -> ExportOptions:
    return ExportOptions(
        formats=formats,
        scale=args.scale,
        path_frames=args.frames,
        turntable_frames=args.frames,
        turntable_degrees=args.degrees,
        fps=args.fps,
        mesh_resolution=args.mesh_resolution,
        mode=args.mode or mode,
        progress=not args.no_progress,
        alpha_threshold=None if args.alpha_threshold < 0 else args.alpha_threshold,
        bake=None if args.raw_3dgs else BakeConfig(),
    )


def run(args: argparse.Namespace) -> int:
    from ..export.paths import load_cameras
    from ..export.ply import load_ply

    if not args.ply.is_file():
        raise FileNotFoundError(f"{args.ply}: no such PLY file")
    out = args.out or args.ply.parent
    # cameras.json is left out of the clash check: written from the cameras read, it holds what an
    # input cameras.json in the same place already held.
    writes = [name for name in output_names(args.formats) if name != "cameras.json"]
    option = "--out" if args.out is not None else "--out (default: the PLY's folder)"
    check_output_dir(out, option, inputs=[args.ply, args.cameras], writes=writes)
    cams = load_cameras(args.cameras)
    gaussians = load_ply(args.ply)
    mode = "ewa" if gaussians.explicit_covariances is not None else "surfel"
    options = options_from_args(args, tuple(args.formats), mode)
    gaussians = compact_from_args(args, gaussians, cams.cameras.to(torch.float32), cams.height, cams.width, options)
    written = export_reconstruction(
        gaussians,
        cams.cameras.to(torch.float32),
        cams.width,
        cams.height,
        out,
        options,
        names=cams.names,
        near=cams.near,
        far=cams.far,
        write_surfels="ply" in options.formats,
    )
    print_written(written)
    return 0


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


def compact_from_args(args: argparse.Namespace, gaussians, cameras, height: int, width: int, options: ExportOptions):
    """`--compact LEVEL`: the compacted surfels (unchanged without the option), with a one-line summary."""
    if args.compact is None:
        return gaussians
    from ..compaction import compact_surfels

    expected = len(cameras) * height * width
    if len(gaussians) != expected:
        raise SurfSplatInputError(
            f"--compact: expected the uncompacted reconstruction, one surfel per pixel of {len(cameras)} context "
            f"views of {width}x{height} ({expected:,}), got {len(gaussians):,} surfels"
        )
    result = compact_surfels(
        gaussians, cameras, height, width, args.compact, mode=options.mode, alpha_threshold=options.alpha_threshold
    )
    s = result.stats
    print(
        f"compact level {args.compact}: {s['input']:,} -> {s['output']:,} surfels ({s['input'] / s['output']:.2f}x fewer; "
        f"{s['pruned']:,} pruned, {s['duplicates']:,} duplicates, {s['merged_away']:,} merged away)"
    )
    return result.gaussians


def print_written(written: dict[str, Path]) -> None:
    width = max(len(k) for k in written)
    for key, path in written.items():
        print(f"  {key.ljust(width)}  {path}")


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
) -> dict[str, Path]:
    """Write what people look at for one reconstruction; returns {what: path}. Each file is written
    under a temporary name and renamed, so an interrupted export leaves no half-written file.
    `seconds`, when given, receives the wall time of each step (ply, bake, renders, path, turntable,
    mesh)."""
    import time

    from ..export.images import colorize_depth, normal_to_rgb, write_png
    from ..export.mesh import TsdfConfig, mesh_from_renders, save_mesh
    from ..export.paths import focus_point, interpolate_cameras, save_cameras, turntable
    from ..export.ply import save_ply
    from ..export.video import video_unavailable, write_video

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
        lap("bake")
    written["cameras"] = save_cameras(out / "cameras.json", cameras, width, height, names, near, far)

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
    path = draw(path_cams, "camera path") if path_cams is not None else None
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
    from ..export.bake import bake_for_viewers, thin_gaussians
    from ..export.figures import write_text
    from ..export.ply import save_ply

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


@torch.no_grad()
def render_frames(gaussians, cameras, width: int, height: int, options: ExportOptions, what: str) -> Frames:
    """Render cameras one at a time (bounded memory) with a progress bar."""
    from ..render import render

    outs = []
    for i in progress(
        range(len(cameras)),
        desc=f"render {what}",
        unit="frame",
        enabled=options.progress and len(cameras) >= 4,
        leave=False,
    ):
        r = render(gaussians, cameras[i], width, height, mode=options.mode, alpha_threshold=options.alpha_threshold)
        outs.append(r)
    return Frames(*(torch.cat([getattr(r, k) for r in outs]).cpu() for k in ("color", "alpha", "depth", "normal")))


def _cat_cameras(a, b):
    from ..geometry.cameras import Cameras

    return Cameras(torch.cat([a.c2w, b.c2w.to(a.c2w)]), torch.cat([a.K, b.K.to(a.K)]), validate=False)
