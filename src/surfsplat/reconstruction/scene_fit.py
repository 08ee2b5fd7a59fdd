"""Per-scene optimization of a reconstruction: in `reconstruct`, or on a folder it saved.

    scene = optimize_scene(scene, context_images, OptimizeConfig(steps=300))   # in place
    scene, images = load_reconstruction("out/")                                # what reconstruct saved
    scene, written = optimize_saved("out/", "out_optimized/")                  # the saved fit continued

The held-out views (`CaptureOptions.holdout_every`) are scored before and after and never enter
the fit: it is given the context cameras and photos only.

A saved scene is continued by default (the start "continue": its surfels as they were saved), or
restarted from another start (`StartConfig.kind`). Either way the result is compared with what was
read, on the held-out views where the reconstruction kept some (else on the context views), and
`optimize_stats["versus_input"]` says which scored better: a result worse than its input is still
written where asked (so it can be looked at), never over its input, and it says so in its
reconstruction.json (`worse_than_input`) and on the terminal.
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
    choice=None,
) -> Scene:
    """`scene` with its surfels optimized on its context views (changed in place and returned):
    `optimize_stats`, `seconds["optimize"]`, the forced-alpha threshold the fit rendered with, and, with
    held-out views, their figures and renders before the fit in `holdout.before` /
    `holdout.before_renders`, after it in `holdout`, and along it in `optimize_stats["held_out_curve"]`.
    `choice`: the start decided already (`surfsplat.capture.starts.choose_start`; None: decided here)."""
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
    estimated = scene.poses is not None  # cameras from the photos: "auto" refines them
    per_view: dict = {}
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
        choice=choice,
        estimated_cameras=estimated,
        per_view_out=per_view,
    )
    scene.alpha_threshold = scene.optimize_stats["alpha_threshold"]  # the surfels render as they were fitted
    scene.antialiased = scene.optimize_stats["antialiased"]
    if curve:
        scene.optimize_stats["held_out_curve"] = curve
    scene.seconds["optimize"] = time.perf_counter() - tick
    if "cameras" in per_view:  # the refined context cameras are the scene's from now on
        scene.cameras = per_view["cameras"].to(scene.cameras.c2w.dtype)
    if held is not None:
        terms = config.per_view_for(estimated)
        if "cameras" in per_view and terms is not None and terms.cameras:
            _align_held_out(scene, terms)
        if per_view.get("exposure") is not None:
            held.protocol = "exposure"
        scene.score_holdout()
        # smaller and larger renders of the held-out views
        # (zoomed-out views drawn at the fitted zoom and averaged down, zoomed-in views with the fitted pixels'
        # filter; beside them, the renders drawn as asked, what the antialiasing filter alone gives)
        held.zoom = {**scene.zoom_scores().to_dict(), "antialiased": scene.antialiased}
        cams = scene.holdout.cameras.to(scene.gaussians.means)
        held.zoom["supersample"] = {
            f"x1/{s}": scene.supersampling(cams.scaled(1 / s), scene.width // s, scene.height // s) for s in (2, 4)
        }
        asked = scene.zoom_scores(supersample=False).to_dict()
        held.zoom["drawn_at_size"] = {k: asked[k] for k in ("x1/2", "x1/4", "x2", "x4") if k in asked}
    return scene


def _align_held_out(scene: Scene, terms) -> None:
    """The held-out cameras fitted to their photos with the scene frozen (test-time pose alignment), as
    the context cameras were refined: the held-out poses were estimated alike and carry the same error."""
    from ..capture.optimize import scene_extent
    from ..capture.per_view import align_held_out
    from ..render import render

    held = scene.holdout

    def draw(surfels, cameras):
        out = render(
            surfels, cameras, scene.width, scene.height, mode=scene.mode, alpha_threshold=scene.alpha_threshold
        )
        return out.color

    before = held.cameras
    held.cameras = align_held_out(draw, scene.gaussians, before, held.images, scene_extent(scene.cameras), terms)
    delta = torch.linalg.solve(before.c2w.double(), held.cameras.c2w.double())  # E_v per view
    cos = ((delta[:, 0, 0] + delta[:, 1, 1] + delta[:, 2, 2] - 1) / 2).clamp(-1, 1)
    held.alignment = {
        "steps": terms.align_steps,
        "rotation_deg": torch.rad2deg(torch.acos(cos)).tolist(),
        "translation": delta[:, :3, 3].norm(dim=-1).tolist(),
    }


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

    def photo(source: str, what: str, lens) -> Tensor:
        path = Path(source)
        if not path.is_absolute() and not path.is_file():
            path = folder / path
        if not path.is_file():
            raise SurfSplatInputError(
                f"{summary_file}: {what} photo {source!r} not found (the optimization fits and scores the photos "
                "the reconstruction was made from)"
            )
        rgb, _ = read_image(path, background=(0.0, 0.0, 0.0))  # as reconstruct composites them
        if lens is not None:  # undistorted to its pinhole first, as reconstruct read it
            from ..data.formats.common import undistort_photo
            from ..geometry.orientation import displayed_size

            shown = displayed_size(lens.orientation, lens.width, lens.height)  # a lens of stored pixels turns
            if (rgb.shape[2], rgb.shape[1]) != shown:
                raise SurfSplatInputError(
                    f"{path}: photo is {rgb.shape[2]}x{rgb.shape[1]} but its {lens.model} lens in {cameras_file} "
                    f"is for {shown[0]}x{shown[1]}"
                )
            rgb = undistort_photo(rgb, lens)
        resized, _, _ = rescale_and_crop(rgb[None].float(), torch.eye(3)[None], (height, width))
        return resized[0].clamp(0, 1)

    context_lenses = cams.lenses or [None] * len(cams.names)
    if len(summary["images"]) != len(context_lenses):
        raise SurfSplatInputError(f"{summary_file}: {len(summary['images'])} photos for {len(cams.names)} cameras")
    photos = [photo(source, "context", lens) for source, lens in zip(summary["images"], context_lenses)]
    gaussians = load_ply(ply)
    lenses = dict(zip(cams.names, cams.lenses)) if cams.lenses is not None else {}
    holdout = None
    held = (summary.get("capture") or {}).get("held_out") or {}
    held_cameras = folder / "capture" / "held_out_cameras.json"
    if held.get("sources") and held_cameras.is_file():
        from .scene import HeldOut

        held_set = load_cameras(held_cameras)
        held_lenses = held_set.lenses or [None] * len(held_set.names)
        if len(held["sources"]) != len(held_lenses):
            raise SurfSplatInputError(
                f"{summary_file}: {len(held['sources'])} held-out photos for {len(held_lenses)} cameras"
            )
        holdout = HeldOut(
            list(held_set.names),
            held_set.cameras.to(torch.float32),
            torch.stack([photo(source, "held-out", lens) for source, lens in zip(held["sources"], held_lenses)]),
            sources=list(held["sources"]),
        )
        if held_set.lenses is not None:
            lenses.update(zip(held_set.names, held_set.lenses))
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
        network=summary.get("network", "ran"),
        source_size=None if cams.crop is None else (cams.crop.source_width, cams.crop.source_height),
        lenses=lenses or None,
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
    config: OptimizeConfig | None = None,
    *,
    formats: tuple[str, ...] = ("ply", "renders"),
    bake: bool = True,
    progress: bool = False,
    device: str | torch.device = "auto",
) -> tuple[Scene, dict[str, Path]]:
    """Load the reconstruction in `folder`, optimize it on `device` ("auto": CUDA when available),
    and save `formats` to `out_dir` (which `load_reconstruction` reads again; `bake` False writes
    surfels_3dgs.ply unbaked, as --raw-3dgs); returns the scene and {what: path}.

    `config` None continues the saved fit (`OptimizeConfig` with the start "continue"); another start
    restarts it. The result is compared with the input (`versus_input`, module docstring)."""
    from ..capture.starts import StartConfig
    from ..export.bake import BakeConfig
    from ..export.flow import ExportOptions
    from .pipeline import resolve_device

    config = config if config is not None else OptimizeConfig(start=StartConfig(kind="continue"))
    device = resolve_device(device)
    scene, images = load_reconstruction(folder)  # read on the host, then every step runs on the device
    scene, images = scene.to(device), images.to(device)
    tick = time.perf_counter()
    # the input's figure: the held-out views' mean PSNR (scored by `optimize_scene` before the fit) where
    # the reconstruction kept some, else the context views'
    held = scene.holdout
    before = _context_psnr(scene, images) if held is None else None
    optimize_scene(scene, images, config, progress=progress)
    if held is not None:
        measure, before, after = "held-out PSNR", held.before["mean_psnr"], held.scores()["mean_psnr"]
    else:
        measure, after = "context-view PSNR", _context_psnr(scene, images)
    scene.optimize_stats["versus_input"] = {
        "input": str(folder),
        "measure": measure,
        "input_psnr": before,
        "psnr": after,
        "worse": after < before,
    }
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


def _context_psnr(scene: Scene, images: Tensor) -> float:
    """Mean PSNR of the scene's renders at its context cameras against their photos."""
    from ..metrics import psnr

    colour = scene.render().color.clamp(0, 1)
    return float(psnr(colour, images.to(colour)).mean())


def versus_input_line(stats: dict) -> str | None:
    """One line comparing an optimized saved scene with the scene it read (None: not compared)."""
    versus = stats.get("versus_input")
    if not versus:
        return None
    figures = f"{versus['measure']} {versus['input_psnr']:.2f} dB read, {versus['psnr']:.2f} dB now"
    if versus["worse"]:
        return f"WORSE than its input ({figures}): {versus['input']} stays the better scene"
    return (
        f"better than its input ({figures})"
        if versus["psnr"] > versus["input_psnr"]
        else f"as good as its input ({figures})"
    )
