"""Per-scene optimization of a reconstruction: in `reconstruct`, or on a folder it saved.

    scene = optimize_scene(scene, context_images, OptimizeConfig(steps=300))   # in place
    scene, images = load_reconstruction("out/")                                # what reconstruct saved
    written = optimize_saved("out/", "out_optimized/", OptimizeConfig(steps=300))

The held-out views (`CaptureOptions.holdout_every`) are scored before and after and never enter
the fit: it is given the context cameras and photos only.
"""

from __future__ import annotations

import time
from pathlib import Path

import torch
from torch import Tensor

from ..capture.optimize import OptimizeConfig, optimize_on_views
from ..utils.checks import SurfSplatInputError
from .scene import Scene


def optimize_scene(
    scene: Scene,
    images: Tensor,  # [V, 3, height, width] the context photos at the scene's working size
    config: OptimizeConfig,
    *,
    progress: bool = False,
    backend: str = "auto",
) -> Scene:
    """`scene` with its surfels optimized on its context views (changed in place and returned):
    `optimize_stats`, `seconds["optimize"]`, the forced-alpha threshold the fit rendered with, and, with
    held-out views, their figures and renders before the fit in `holdout.before` /
    `holdout.before_renders`, after it in `holdout`, and along it in `optimize_stats["held_out_curve"]`."""
    held = scene.holdout
    curve: list[dict] = []
    monitor = None
    if held is not None:
        out = scene.score_holdout()
        held.before = held.scores()
        held.before_renders = out.color.clamp(0, 1)

        def monitor(step: int, seconds: float, surfels, alpha_threshold: float | None) -> None:
            """The held-out PSNR along the fit (its time is not the fit's), for the report's curve."""
            from ..metrics import psnr
            from ..render import render

            colour = render(
                surfels,
                held.cameras,
                scene.width,
                scene.height,
                mode=scene.mode,
                alpha_threshold=alpha_threshold,
                antialiased=config.antialiased,
            ).color
            value = psnr(colour.clamp(0, 1), held.images.to(colour)).mean()
            curve.append({"step": step, "seconds": seconds, "surfels": len(surfels), "psnr": float(value)})

    tick = time.perf_counter()
    scene.gaussians, scene.optimize_stats = optimize_on_views(
        scene.gaussians,
        scene.cameras,
        images,
        scene.width,
        scene.height,
        config,
        mode=scene.mode,
        alpha_threshold=scene.alpha_threshold,
        backend=backend,
        progress=progress,
        monitor=monitor,
    )
    scene.alpha_threshold = scene.optimize_stats["alpha_threshold"]  # the surfels render as they were fitted
    scene.antialiased = scene.optimize_stats["antialiased"]
    if curve:
        scene.optimize_stats["held_out_curve"] = curve
    scene.seconds["optimize"] = time.perf_counter() - tick
    if held is not None:
        scene.score_holdout()
        # smaller and larger renders of the held-out views
        held.zoom = {**scene.zoom_scores().to_dict(), "antialiased": scene.antialiased}
    return scene


def load_reconstruction(folder: str | Path) -> tuple[Scene, Tensor]:
    """The scene `Scene.save` wrote in `folder` (surfels.ply, cameras.json, reconstruction.json) and its
    context photos at the working size ([V, 3, height, width]), read from the files reconstruction.json
    names and resized as `reconstruct` resized them. Where the reconstruction held views out (its
    capture/held_out_cameras.json and the photos reconstruction.json names), they come back as the
    scene's `holdout`, to be scored again and never fitted."""
    from ..data.cameras import load_cameras
    from ..data.images import read_image
    from ..data.transforms import rescale_and_crop
    from ..export.ply import load_ply
    from ..utils.checks import read_json

    folder = Path(folder)
    summary_file, ply, cameras_file = folder / "reconstruction.json", folder / "surfels.ply", folder / "cameras.json"
    for path in (summary_file, ply, cameras_file):
        if not path.is_file():
            raise SurfSplatInputError(
                f"{folder}: no {path.name} (expected a folder written by surfsplat reconstruct with the ply format)"
            )
    summary = read_json(summary_file)
    if not isinstance(summary, dict) or not {"size", "images", "near", "far"} <= set(summary):
        raise SurfSplatInputError(f"{summary_file}: expected reconstruct's summary (size, images, near, far)")
    height, width = (int(v) for v in summary["size"])
    cams = load_cameras(cameras_file)
    if (cams.width, cams.height) != (width, height):
        raise SurfSplatInputError(
            f"{cameras_file}: cameras of {cams.width}x{cams.height}, the scene is {width}x{height}"
        )

    def photo(source: str, what: str) -> Tensor:
        path = Path(source)
        if not path.is_absolute() and not path.is_file():
            path = folder / path
        if not path.is_file():
            raise SurfSplatInputError(
                f"{summary_file}: {what} photo {source!r} not found (the optimization fits and scores the photos "
                "the reconstruction was made from)"
            )
        rgb, _ = read_image(path, background=(0.0, 0.0, 0.0))  # as reconstruct composites them
        resized, _, _ = rescale_and_crop(rgb[None].float(), torch.eye(3)[None], (height, width))
        return resized[0].clamp(0, 1)

    photos = [photo(source, "context") for source in summary["images"]]
    if len(photos) != len(cams.names):
        raise SurfSplatInputError(f"{summary_file}: {len(photos)} photos for {len(cams.names)} cameras")
    gaussians = load_ply(ply)
    holdout = None
    held = (summary.get("capture") or {}).get("held_out") or {}
    held_cameras = folder / "capture" / "held_out_cameras.json"
    if held.get("sources") and held_cameras.is_file():
        from .scene import HeldOut

        held_set = load_cameras(held_cameras)
        holdout = HeldOut(
            list(held_set.names),
            held_set.cameras.to(torch.float32),
            torch.stack([photo(source, "held-out") for source in held["sources"]]),
            sources=list(held["sources"]),
        )
    scene = Scene(
        gaussians=gaussians,
        cameras=cams.cameras.to(torch.float32),
        width=width,
        height=height,
        names=list(cams.names),
        near=float(summary["near"]),
        far=float(summary["far"]),
        mode=summary.get("render_mode", "surfel"),
        alpha_threshold=summary.get("alpha_threshold", 0.001),
        antialiased=_antialiased(summary, summary_file),
        model=summary.get("model", ""),
        checkpoint=summary.get("checkpoint", ""),
        sources=[str(s) for s in summary["images"]],
        cameras_source=str(cameras_file),
        passes=[list(cams.names)],
        seconds={},
        compact_level=summary.get("compact_level"),
        holdout=holdout,
    )
    return scene, torch.stack(photos)


def _antialiased(summary: dict, summary_file: Path) -> bool:
    value = summary.get("antialiased", False)
    if not isinstance(value, bool):
        raise SurfSplatInputError(f"{summary_file}: 'antialiased' must be true or false, got {value!r}")
    return value


def optimize_saved(
    folder: str | Path,
    out_dir: str | Path,
    config: OptimizeConfig,
    *,
    formats: tuple[str, ...] = ("ply", "renders"),
    bake: bool = True,
    progress: bool = False,
    device: str | torch.device = "auto",
) -> tuple[Scene, dict[str, Path]]:
    """Load the reconstruction in `folder`, optimize it on `device` ("auto": CUDA when available),
    and save `formats` to `out_dir` (which `load_reconstruction` reads again; `bake` False writes
    surfels_3dgs.ply unbaked, as --raw-3dgs); returns the scene and {what: path}."""
    from ..export.bake import BakeConfig
    from ..export.flow import ExportOptions
    from .pipeline import resolve_device

    device = resolve_device(device)
    scene, images = load_reconstruction(folder)  # read on the host, then every step runs on the device
    scene, images = scene.to(device), images.to(device)
    tick = time.perf_counter()
    optimize_scene(scene, images, config, progress=progress)
    scene.seconds["total"] = time.perf_counter() - tick
    options = ExportOptions(
        formats=tuple(formats),
        mode=scene.mode,
        alpha_threshold=scene.alpha_threshold,
        antialiased=scene.antialiased,
        progress=progress,
        bake=BakeConfig() if bake else None,
    )
    return scene, scene.save(out_dir, options=options)
