"""What the viewer shows, read from a PLY or from a folder written by `reconstruct` / `export`.

    scene = load_viewer_scene("out/")            # surfels.ply + cameras.json + mesh.ply + ...
    scene = load_viewer_scene("out/surfels.ply")  # the surfels alone

A folder holds (see `surfsplat.commands.export`): surfels.ply (or surfels_3dgs.ply), cameras.json
(the context cameras), reconstruction.json (the forced-alpha-blending threshold and the input
photos), renders/viewNN_color.png (renders of the context views), path/frameNNN.png (the
interpolated camera path the video followed) and mesh.ply. A PLY given alone shows only its surfels:
the viewer serves nothing but the scene it was pointed at.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..export.mesh import load_mesh as read_mesh
from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..geometry.sh import SH_C0
from ..render import DEFAULT_ALPHA_THRESHOLD
from ..render.types import RenderMode
from ..utils.checks import SurfSplatInputError

PATH_FRAMES = 48  # ExportOptions.path_frames: the path's frame count when path/ holds no frames to count
FRUSTUM_IMAGE_SIZE = 256  # longest side of the images on the frustums (the browser gets them as JPEG/PNG)

Progress = Callable[[str, float], None]  # (what is being done, fraction done in [0, 1])


@dataclass
class SceneMesh:
    """A triangle mesh (the TSDF fusion `export` writes); viser's simple mesh node takes one colour,
    so vertex colours are not read."""

    vertices: np.ndarray  # [V, 3] float32
    faces: np.ndarray  # [F, 3] int32


@dataclass
class ViewerScene:
    """Everything the viewer shows: surfels, optionally the context cameras with their images, the
    reconstruction's camera path and its mesh."""

    gaussians: Gaussians  # unbatched, float32
    title: str  # shown in the page
    mode: RenderMode = "surfel"  # rasterization of the exact render ("ewa" for 3DGS-layout files)
    alpha_threshold: float | None = DEFAULT_ALPHA_THRESHOLD  # forced alpha blending tau of the exact render
    antialiased: bool = False  # the exact render with the antialiasing filter (a scene fitted with it)
    cameras: Cameras | None = None  # [C] context cameras, OpenCV c2w, K in pixels of width x height
    width: int | None = None  # image size the cameras' K is in pixels of
    height: int | None = None
    names: list[str] = field(default_factory=list)  # one per camera
    images: list[np.ndarray | None] = field(default_factory=list)  # one [h, w, 3] uint8 (or None) per camera
    path: Cameras | None = None  # the interpolated camera path of the reconstruction's video
    mesh: SceneMesh | None = None


def load_viewer_scene(path: str | os.PathLike, progress: Progress | None = None) -> ViewerScene:
    """Read a PLY (its surfels only) or an output folder (everything in it).

    Raises SurfSplatInputError naming the file for anything that is not what `reconstruct` writes.
    """
    from ..data.cameras import load_cameras
    from ..export.paths import interpolate_cameras
    from ..export.ply import load_ply

    def step(what: str, fraction: float) -> None:
        if progress is not None:
            progress(what, fraction)

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such PLY file or output folder")
    folder = path if path.is_dir() else None
    if folder is not None:
        candidates = [folder / "surfels.ply", folder / "surfels_3dgs.ply"]
        ply = next((p for p in candidates if p.is_file()), None)
        if ply is None:
            raise SurfSplatInputError(
                f"{folder}: no surfels.ply or surfels_3dgs.ply (expected a PLY file or a folder written by "
                "surfsplat reconstruct or export)"
            )
    else:
        ply = path
    step(f"reading {ply.name}", 0.0)
    try:
        gaussians = load_ply(ply)
    except SurfSplatInputError as err:  # values the Gaussians refuse (NaN, negative scale): name the file
        if str(err).startswith(str(ply)):
            raise
        raise SurfSplatInputError(f"{ply}: {err}") from None
    if len(gaussians) == 0:
        raise SurfSplatInputError(f"{ply}: the file holds no surfels")
    scene = ViewerScene(
        gaussians=gaussians,
        title=str(folder.name if folder is not None else ply.name),
        mode="ewa" if gaussians.explicit_covariances is not None else "surfel",
    )
    if folder is None:
        step("surfels read", 1.0)
        return scene

    summary_file = folder / "reconstruction.json"
    summary: dict = {}
    if summary_file.is_file():
        from ..utils.checks import read_json

        summary = read_json(summary_file)
        if not isinstance(summary, dict):
            raise SurfSplatInputError(f"{summary_file}: expected a JSON object")
        tau = summary.get("alpha_threshold", DEFAULT_ALPHA_THRESHOLD)
        if tau is not None and (not isinstance(tau, (int, float)) or isinstance(tau, bool) or not 0 < tau <= 1):
            raise SurfSplatInputError(f"{summary_file}: 'alpha_threshold' must be in (0, 1] or null, got {tau!r}")
        scene.alpha_threshold = None if tau is None else float(tau)
        antialiased = summary.get("antialiased", False)
        if not isinstance(antialiased, bool):
            raise SurfSplatInputError(f"{summary_file}: 'antialiased' must be true or false, got {antialiased!r}")
        scene.antialiased = antialiased
        if summary.get("render_mode") in ("surfel", "ewa") and gaussians.explicit_covariances is None:
            scene.mode = summary["render_mode"]

    cameras_file = folder / "cameras.json"
    if cameras_file.is_file():
        step("reading cameras.json", 0.3)
        cams = load_cameras(cameras_file)
        scene.cameras = cams.cameras.to(torch.float64)
        scene.width, scene.height, scene.names = cams.width, cams.height, list(cams.names)
        photos = summary.get("images") if isinstance(summary.get("images"), list) else []
        for i in range(len(cams.names)):
            step(f"reading the image of camera {i + 1} of {len(cams.names)}", 0.3 + 0.4 * i / len(cams.names))
            scene.images.append(_camera_image(folder, photos, i))
        if len(scene.cameras) >= 2:
            frames = len(list((folder / "path").glob("frame*.png"))) if (folder / "path").is_dir() else 0
            scene.path = interpolate_cameras(scene.cameras, frames if frames >= 2 else PATH_FRAMES)

    mesh_file = folder / "mesh.ply"
    if mesh_file.is_file():
        step("reading mesh.ply", 0.8)
        scene.mesh = load_mesh(mesh_file)
    step("scene read", 1.0)
    return scene


def _camera_image(folder: Path, photos: list, index: int) -> np.ndarray | None:
    """The photo of context camera `index` (from reconstruction.json) when it can still be found,
    else the reconstruction's render of that view, else None; downscaled for the frustum."""
    candidates: list[Path] = []
    if index < len(photos) and isinstance(photos[index], str):
        photo = Path(photos[index])
        candidates += [photo] if photo.is_absolute() else [photo, folder / photo, folder / photo.name]
    candidates.append(folder / "renders" / f"view{index:02d}_color.png")
    for candidate in candidates:
        if candidate.is_file():
            from ..data.images import read_image

            rgb, _ = read_image(candidate, background=(1.0, 1.0, 1.0))
            return _thumbnail(rgb)
    return None


def _thumbnail(rgb: torch.Tensor) -> np.ndarray:
    """[3, H, W] in [0, 1] -> [h, w, 3] uint8 with the longest side at most FRUSTUM_IMAGE_SIZE (area average)."""
    from ..export.images import to_uint8

    h, w = rgb.shape[1:]
    factor = max(h, w) / FRUSTUM_IMAGE_SIZE
    if factor > 1:
        size = (max(1, round(h / factor)), max(1, round(w / factor)))
        rgb = torch.nn.functional.interpolate(rgb[None], size=size, mode="area")[0]
    return to_uint8(rgb)


def load_mesh(path: Path) -> SceneMesh:
    """A triangle mesh PLY (vertex x y z, face vertex_indices) as `save_mesh` writes it."""
    mesh = read_mesh(path)
    return SceneMesh(mesh.vertices.numpy(), mesh.faces.numpy().astype(np.int32))


@dataclass
class SplatArrays:
    """Surfels as viser's Gaussian splat node takes them, in units of `unit` world lengths.

    viser sends covariances as float16, whose normal range starts at 6e-5: a surfel of a scene in
    millimetres (variance 1e-6) would lose its shape. Dividing lengths by `unit` (the median surfel
    size over 0.1) brings variances near 1e-2; the node's scale multiplies them back in the browser.
    """

    centers: np.ndarray  # [N, 3] float32, world / unit
    covariances: np.ndarray  # [N, 3, 3] float32, world covariance / unit^2
    rgbs: np.ndarray  # [N, 3] float32 in [0, 1]: the view-independent colour 0.5 + C0 * SH DC
    opacities: np.ndarray  # [N, 1] float32
    unit: float  # world length of one node unit


def splat_arrays(gaussians: Gaussians) -> SplatArrays:
    """The full 3D covariance of every surfel, R diag(su^2, sv^2, eps^2) R^T (the thin third axis of
    a surfel) or the file's explicit covariance for 3DGS layouts, its DC colour and opacity."""
    g = gaussians.detach().to("cpu", torch.float64)
    cov = g.covariances
    size = g.scales.amax(-1) if g.explicit_covariances is None else torch.linalg.eigvalsh(cov)[:, -1].sqrt()
    median = float(size.median())
    unit = median / 0.1 if median > 0 else 1.0
    rgb = (0.5 + SH_C0 * g.sh[:, :, 0]).clamp(0, 1)
    return SplatArrays(
        centers=(g.means / unit).numpy().astype(np.float32),
        covariances=(cov / unit**2).numpy().astype(np.float32),
        rgbs=rgb.numpy().astype(np.float32),
        opacities=g.opacities[:, None].numpy().astype(np.float32),
        unit=unit,
    )


def scene_bounds(gaussians: Gaussians) -> tuple[np.ndarray, float]:
    """(centre [3], radius) of the bulk of the surfels: the 2nd-98th percentile box, so a few stray
    surfels far away do not decide where the camera looks."""
    means = gaussians.means.detach().to("cpu", torch.float64)
    lo, hi = torch.quantile(means, torch.tensor([0.02, 0.98], dtype=torch.float64), dim=0)
    return ((lo + hi) / 2).numpy(), max(float((hi - lo).norm() / 2), 1e-6)


def summary_line(scene: ViewerScene) -> str:
    """One line saying what is shown."""
    parts = [f"{len(scene.gaussians):,} surfels"]
    if scene.cameras is not None:
        parts.append(f"{len(scene.cameras)} cameras")
    if scene.path is not None:
        parts.append(f"a {len(scene.path)}-frame camera path")
    if scene.mesh is not None:
        parts.append(f"a mesh of {len(scene.mesh.faces):,} triangles")
    return ", ".join(parts)
