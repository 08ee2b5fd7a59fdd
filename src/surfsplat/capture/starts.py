"""Where a per-scene optimization starts: the network's surfels, points triangulated from the photos, or both.

    start = sfm_start(images, cameras)                            # 3DGS's start: SfM points as surfels
    start = network_start(fused, cameras, width, height, budget)  # the network's surfels, thinned
    start = combined_start(fused, points, cameras, ...)           # both, in one set of surfels

The optimization (`optimize.py`) takes any of them; `StartConfig.kind` picks one by name and the
reconstruction records which it used.

* "points": the sparse points COLMAP triangulates from the context photos with the context cameras
  held fixed (SIFT features, exhaustive matching up to 30 views, `pycolmap.triangulate_points`),
  the start of 3DGS, 2DGS and OpenSplat. Each point becomes a surfel as 2DGS's `create_from_pcd`
  makes one: its colour the photos' (COLMAP's mean over the point's observations) as the SH DC
  term, both tangent scales the root mean squared distance to its three nearest neighbours,
  opacity 0.1, and a rotation drawn at random (2DGS draws unnormalized uniform quaternions; a
  surfel's orientation is found by the fit, and a common one would make every surfel edge-on to
  some view).
* "network": the network's fused surfels, thinned to `budget` by keeping a seeded random sample
  (co-visibility does not help here: fusion has already merged what several views saw), each
  kept surfel's tangent scales grown by sqrt(N / budget) so the thinned set covers what the whole
  did.
* "both": the union of the two.
* "auto" (the default): the points, unless COLMAP finds fewer than `min_points` (photos too small or
  too plain for SIFT), then the network's surfels; the figures say which and why.
* "continue": the given surfels as they are, nothing thinned or grown (a saved fit continued: `surfsplat
  optimize FOLDER`'s default).

Which start a configuration makes is decided by `choose_start` from the photos alone (COLMAP's points
need no network), so `reconstruct` decides before the network's passes and runs them only where the
start uses their surfels.

Why pycolmap and not our own matcher: COLMAP's SIFT, matching and multi-view triangulation (with
its track merging, completion and reprojection filter) are what every per-scene method starts from.
"""

from __future__ import annotations

import logging
import math
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..geometry.sh import SH_C0
from ..utils.checks import SurfSplatInputError

logger = logging.getLogger(__name__)

StartKind = Literal["auto", "network", "points", "both", "continue"]
START_KINDS = ("auto", "network", "points", "both", "continue")
NETWORK_KINDS = ("network", "both")  # the starts made (in part) of the network's surfels


@dataclass(frozen=True)
class StartConfig:
    """The optimization's start."""

    # "points" (COLMAP's triangulated points), "network", "both", "auto": the points where COLMAP
    # triangulates at least `min_points` of them, else the network's surfels (and the reason is recorded),
    # or "continue": the given surfels as they are (a saved fit continued)
    kind: StartKind = "auto"
    min_points: int = 100  # "auto": fewer points than this start from the network instead
    budget: int = 30_000  # "network"/"both": the network's surfels kept at most
    initial_opacity: float = 0.1  # "points": every new surfel's opacity (3DGS, 2DGS)
    max_features: int = 4096  # SIFT features per photo
    max_reprojection_error: float = 2.0  # px: triangulated points beyond it are dropped (COLMAP's filter: 4)
    min_track_length: int = 2  # views a kept point is seen in
    two_view_tracks: bool = True  # keep points seen in two views only (COLMAP's mapper ignores them)
    min_angle: float = 1.0  # degrees: the least triangulation angle of a new point (COLMAP: 1.5)
    peak_threshold: float = 0.004  # SIFT's contrast threshold (COLMAP: 0.0067): more features on smooth photos
    seed: int = 0  # the network surfels' sample, the points' random rotations, COLMAP's RANSAC

    def __post_init__(self) -> None:
        if self.kind not in START_KINDS:
            raise SurfSplatInputError(
                f"optimize start (--optimize-start): expected one of {START_KINDS}, got {self.kind!r}"
            )
        if self.budget < 1:
            raise SurfSplatInputError(f"optimize start budget: expected at least 1 surfel, got {self.budget}")
        if not 0 < self.initial_opacity < 1:
            raise SurfSplatInputError(f"optimize start opacity: expected a value in (0, 1), got {self.initial_opacity}")


@dataclass
class Points:
    """Sparse points triangulated from the photos."""

    xyz: Tensor  # [P, 3] world
    rgb: Tensor  # [P, 3] in [0, 1]
    errors: Tensor  # [P] mean reprojection error, px
    track_lengths: Tensor  # [P] views each point is seen in
    seconds: float = 0.0


def triangulate(
    images: Tensor,  # [V, 3, H, W] in [0, 1]
    cameras: Cameras,  # [V] K in pixels of W x H
    config: StartConfig | None = None,
) -> Points:
    """COLMAP's sparse points of the photos with the cameras held fixed (features, matching, multi-view
    triangulation, the reprojection and track-length filters). Raises SurfSplatInputError where no
    point survives (photos that share nothing)."""
    import pycolmap

    config = config or StartConfig()
    v, _, h, w = images.shape
    if len(cameras) != v:
        raise SurfSplatInputError(f"triangulate: {v} photos for {len(cameras)} cameras")
    quiet, pycolmap.logging.minloglevel = pycolmap.logging.minloglevel, 3  # COLMAP's per-image log lines
    try:
        return _triangulate(pycolmap, images, cameras, config)
    finally:
        pycolmap.logging.minloglevel = quiet


def _triangulate(pycolmap, images: Tensor, cameras: Cameras, config: StartConfig) -> Points:
    from PIL import Image

    tick = time.perf_counter()
    v, _, h, w = images.shape
    pycolmap.set_random_seed(config.seed)
    K = cameras.K.detach().double().cpu().numpy()
    w2c = np.linalg.inv(cameras.c2w.detach().double().cpu().numpy())
    pixels = (images.detach().clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()
    with tempfile.TemporaryDirectory(prefix="surfsplat-points-") as root:
        root = Path(root)
        folder, database = root / "images", root / "database.db"
        folder.mkdir()
        files = [f"{i:06d}.png" for i in range(v)]
        for array, file in zip(pixels, files):
            Image.fromarray(array).save(folder / file)
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = 2
        extraction.sift.max_num_features = config.max_features
        extraction.sift.first_octave = -1  # twice the resolution: working-size photos are small
        extraction.sift.peak_threshold = config.peak_threshold
        pycolmap.extract_features(
            database,
            folder,
            image_names=files,
            camera_mode=pycolmap.CameraMode.PER_IMAGE,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = 2
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = config.seed
        if v <= 30:
            pycolmap.match_exhaustive(
                database, matching_options=matching, verification_options=verification, device=pycolmap.Device.cpu
            )
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = 10
            pycolmap.match_sequential(
                database,
                matching_options=matching,
                pairing_options=pairing,
                verification_options=verification,
                device=pycolmap.Device.cpu,
            )
        recon = pycolmap.Reconstruction()
        db = pycolmap.Database.open(database)
        try:
            by_name = {im.name: im for im in db.read_all_images()}
            for i, file in enumerate(files):
                entry = by_name[file]
                fx, fy, cx, cy = K[i, 0, 0], K[i, 1, 1], K[i, 0, 2], K[i, 1, 2]
                camera = pycolmap.Camera(
                    model="PINHOLE", width=w, height=h, params=[fx, fy, cx, cy], camera_id=entry.camera_id
                )
                db.update_camera(camera)
                recon.add_camera_with_trivial_rig(camera)
                keypoints = db.read_keypoints(entry.image_id)[:, :2].astype(np.float64)
                image = pycolmap.Image(
                    name=file, keypoints=keypoints, camera_id=entry.camera_id, image_id=entry.image_id
                )
                pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[i, :3, :3]), w2c[i, :3, 3])
                recon.add_image_with_trivial_frame(image, pose)
        finally:
            db.close()
        options = pycolmap.IncrementalPipelineOptions()
        options.num_threads = 2
        options.random_seed = config.seed
        # points seen in two views only are kept (COLMAP drops them while mapping, where they do not help
        # the poses; here the poses are given and they are half of what a forward-facing capture sees)
        options.triangulation.ignore_two_view_tracks = config.two_view_tracks is False
        options.triangulation.min_angle = config.min_angle
        recon = pycolmap.triangulate_points(recon, database, folder, root / "sparse", options=options)
        recon.extract_colors_for_all_images(folder)
        points = list(recon.points3D.values())
    xyz = np.array([p.xyz for p in points], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in points], dtype=np.float64).reshape(-1, 3) / 255
    errors = np.array([p.error for p in points], dtype=np.float64)
    tracks = np.array([p.track.length() for p in points], dtype=np.int64)
    # COLMAP's threads triangulate and number the points in an order that varies from run to run (the same
    # points): a canonical order (by x, then y, then z) makes the start, and the fit from it, repeat bit for bit
    key = xyz.astype(np.float32)  # the points' coordinates as they are returned
    order = np.lexsort((key[:, 2], key[:, 1], key[:, 0]))
    xyz, rgb, errors, tracks = xyz[order], rgb[order], errors[order], tracks[order]
    keep = (errors <= config.max_reprojection_error) & (tracks >= config.min_track_length)
    if not keep.any():
        raise SurfSplatInputError(
            f"triangulate: none of {len(points)} triangulated points passes the filters (reprojection error <= "
            f"{config.max_reprojection_error} px, seen in >= {config.min_track_length} views): the photos share too "
            "little; use the network's start (--optimize-start network)"
        )
    return Points(
        xyz=torch.from_numpy(xyz[keep]).float(),
        rgb=torch.from_numpy(rgb[keep]).float(),
        errors=torch.from_numpy(errors[keep]).float(),
        track_lengths=torch.from_numpy(tracks[keep]),
        seconds=time.perf_counter() - tick,
    )


def nearest_neighbour_scale(xyz: Tensor, k: int = 3) -> Tensor:
    """Root mean squared distance of each point to its k nearest others (3DGS's `distCUDA2`, k = 3). [P]"""
    from scipy.spatial import cKDTree

    points = xyz.detach().double().cpu().numpy()
    k = min(k, len(points) - 1)
    if k < 1:
        return torch.ones(len(points), dtype=xyz.dtype, device=xyz.device)
    distances, _ = cKDTree(points).query(points, k=k + 1)
    squared = np.square(distances[:, 1:]).mean(1)
    # coincident points (squared 0) get the smallest positive spacing found, never a zero scale
    floor = squared[squared > 0].min() if (squared > 0).any() else 1e-6
    return torch.from_numpy(np.sqrt(np.maximum(squared, floor))).to(xyz)


def points_to_surfels(points: Points, opacity: float = 0.1, sh_degree: int = 3, seed: int = 0) -> Gaussians:
    """Surfels at the points as 2DGS's `create_from_pcd` makes them (module docstring)."""
    n = len(points.xyz)
    generator = torch.Generator().manual_seed(seed)
    quats = torch.rand(n, 4, generator=generator) + 1e-3  # 2DGS's torch.rand((N, 4)); never all zero
    scale = nearest_neighbour_scale(points.xyz)
    sh = torch.zeros(n, 3, (sh_degree + 1) ** 2)
    sh[..., 0] = (points.rgb - 0.5) / SH_C0
    return Gaussians(
        means=points.xyz.clone(),
        quats=torch.nn.functional.normalize(quats, dim=-1),
        scales=scale[:, None].expand(n, 2).clone(),
        opacities=torch.full((n,), opacity),
        sh=sh,
    )


def thin(gaussians: Gaussians, budget: int, seed: int = 0) -> Gaussians:
    """At most `budget` of the surfels, a seeded random sample, their tangent scales grown by
    sqrt(N / budget) so the sample covers the area the whole did."""
    n = len(gaussians)
    if n <= budget:
        return gaussians
    generator = torch.Generator().manual_seed(seed)
    keep = torch.randperm(n, generator=generator)[:budget].sort().values.to(gaussians.means.device)
    kept = gaussians.subset(keep)
    grow = math.sqrt(n / budget)
    return Gaussians(kept.means, kept.quats, kept.scales * grow, kept.opacities, kept.sh)


def with_sh_degree(gaussians: Gaussians, degree: int) -> Gaussians:
    """The surfels with SH of `degree` (higher coefficients zero-padded or dropped)."""
    have = gaussians.sh.shape[-1]
    want = (degree + 1) ** 2
    if have == want:
        return gaussians
    if have > want:
        sh = gaussians.sh[..., :want]
    else:
        pad = torch.zeros(*gaussians.sh.shape[:-1], want - have, dtype=gaussians.sh.dtype, device=gaussians.sh.device)
        sh = torch.cat((gaussians.sh, pad), -1)
    return Gaussians(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities, sh)


@dataclass
class StartChoice:
    """What a start is made of, decided before any surfel is: `choose_start`."""

    kind: str  # "points", "network", "both" or "continue" ("auto" resolved)
    points: Points | None = None  # COLMAP's points where the start uses them
    reason: str | None = None  # why "auto" took the network's surfels (None: it did not)
    seconds: float = 0.0  # the triangulation's

    @property
    def needs_network(self) -> bool:
        """Whether the start is made (in part) of the network's surfels."""
        return self.kind in NETWORK_KINDS

    def figures(self) -> dict:
        out: dict = {"start": self.kind}
        if self.points is not None:
            out["points"] = len(self.points.xyz)
            out["points_seconds"] = self.points.seconds
        if self.reason is not None:
            out["start_reason"] = self.reason
        return out


def choose_start(
    config: StartConfig,
    images: Tensor,  # [V, 3, H, W] the context photos
    cameras: Cameras,  # [V]
    *,
    network_available: bool = True,
) -> StartChoice:
    """The start `config` names, resolved from the photos alone: COLMAP's points are triangulated for
    "points", "both" and "auto", and "auto" becomes "network" where they are too few (or none pass the
    filters). Without network surfels to fall back on (`network_available` False) "auto" keeps the
    points it found and raises where there are none."""
    tick = time.perf_counter()
    kind = config.kind
    if kind in ("network", "continue"):
        return StartChoice(kind)
    try:
        points = triangulate(images, cameras, config)
    except SurfSplatInputError as error:
        if kind != "auto" or not network_available:
            raise
        return StartChoice("network", reason=str(error), seconds=time.perf_counter() - tick)
    if kind == "auto" and len(points.xyz) < config.min_points and network_available:
        reason = f"COLMAP triangulated {len(points.xyz)} points, fewer than {config.min_points}"
        return StartChoice("network", reason=reason, seconds=time.perf_counter() - tick)
    return StartChoice("points" if kind == "auto" else kind, points, seconds=time.perf_counter() - tick)


def make_start(
    config: StartConfig,
    network: Gaussians | None,  # [N] the network's fused surfels, or a saved fit's (None where there are none)
    images: Tensor,  # [V, 3, H, W] the context photos
    cameras: Cameras,  # [V]
    sh_degree: int = 3,
    choice: StartChoice | None = None,  # decided already (`choose_start`); None: decided here
) -> tuple[Gaussians, dict]:
    """The start `config` names, with its figures {"start" (the kind used), "start_surfels", "points",
    "start_seconds", and "start_reason" where "auto" fell back to the network's surfels}."""
    tick = time.perf_counter()
    if choice is None:
        choice = choose_start(config, images, cameras, network_available=network is not None)
    parts, figures = [], choice.figures()
    device = images.device
    if choice.points is not None:
        parts.append(points_to_surfels(choice.points, config.initial_opacity, sh_degree, config.seed).to(device))
    if choice.reason is not None:
        logger.warning("optimize: starting from the network's surfels (%s)", choice.reason)
    if choice.kind in ("network", "both", "continue"):
        if network is None:
            what = "saved" if choice.kind == "continue" else "network"
            raise SurfSplatInputError(f"optimize start {config.kind!r}: there are no {what} surfels to start from")
        given = network.detach() if choice.kind == "continue" else thin(network.detach(), config.budget, config.seed)
        parts.append(with_sh_degree(given, sh_degree).to(device))
    start = parts[0] if len(parts) == 1 else Gaussians.cat([p.to(torch.float32) for p in parts])
    figures["start_surfels"] = len(start)
    figures["start_seconds"] = choice.seconds + time.perf_counter() - tick
    return start.to(torch.float32), figures
