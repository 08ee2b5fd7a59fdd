"""Cameras from the photos themselves: COLMAP's SIFT, matching, verification and mapping via pycolmap.

    camera_set, summary = estimate_cameras(["a.jpg", "b.jpg"])       # K, c2w, near/far, names
    print("\\n".join(summary.lines()))

Pipeline (every estimator is pycolmap's; this module only chooses options and glues them):
1. Images are written at the extraction size: small photos are upscaled so their long side is
   `PoseConfig.min_extraction_size` (SIFT on a 2x upscaled 400x300 DTU view finds about 5x more
   verified matches and halves the rotation error), large ones downscaled to `max_size`. The
   keypoints are then mapped back to the original pixels, so everything after sees the real images.
2. SIFT extraction, matching and geometric verification (E/F/H with RANSAC) into a temporary
   COLMAP database. Pairs: all of them (exhaustive) for small sets, each image with its next
   `sequential_overlap` images in input order (sequential) for sets over `exhaustive_max_images`.
   By default (`quadratic_overlap`, COLMAP's default too) those are the images 1, 2, 4, 8, ...
   ahead instead of the next ones: on a slow video the next ten frames barely move (300 frames of
   a 2 m walk: 21 registered, 25 points), and the wider baselines let the mapper start and
   triangulate (all 300 registered).
3. Two images: the dedicated two-view path. COLMAP's incremental mapper refuses most two-image
   models (its initial pair needs 100 inliers and a 16 degree triangulation angle), and two views
   is the model's main setting: a calibrated relative pose (LO-RANSAC, 5-point) on the verified
   matches, its non-linear refinement on the inliers, triangulation of the inliers, then a two-view
   bundle adjustment with a Cauchy loss (first camera and the baseline length fixed: the gauge).
   Three or more: COLMAP's incremental mapper, then one more global bundle adjustment with a
   Cauchy loss. If the mapper registers fewer than two images, the two-view path runs on the
   pair with most inliers. Degenerate pairs (a camera that only turned, a single plane) are
   refused with the cause named (`_Workspace._check_not_homography`).
4. Intrinsics: one shared pinhole camera per image size (SIMPLE_PINHOLE: f, principal point at the
   centre, no distortion, so the images need no undistortion): COLMAP's PER_FOLDER camera mode with
   the images of each size in a folder of their own, so portrait and landscape photos of one phone,
   or photos of two cameras, each get theirs (focal lengths from EXIF, the prior or bundle adjustment
   per size; a given --focal needs photos of one size). f comes from `focal`, else EXIF, else the
   prior 1.2 x the long side (COLMAP's default guess, a 45 degree field of view on the long side).
   With 3+ views bundle adjustment refines the prior always and an EXIF value only when the
   optical axes span `focal_observable_angle` (20 degrees): with nearly parallel views (LLFF fern
   views 0-3 span 11 degrees) focal length and depth trade off, and refining a correct EXIF focal
   moved it by 16 % and the rotations by 1.8 degrees. With two views f is not observable and stays
   at its source; a given f is never changed.
5. Frame and scale: world = the first registered camera (identity rotation, centre at the
   origin), OpenCV axes. Scale: the median depth of the triangulated points seen from that camera
   is `PoseConfig.median_depth` (4 by default: the room scale RealEstate10K-trained checkpoints and
   the synthetic rooms see, so near and far land well inside their trained range 1..100). near
   and far are the 2nd and 98th percentiles of every registered view's point depths divided and
   multiplied by `depth_margin`.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from PIL import Image

from ..data.cameras import CameraSet
from ..geometry.cameras import Cameras
from ..utils.checks import SurfSplatInputError
from .exif import exif_focal

FOCAL_PRIOR_FACTOR = 1.2  # COLMAP's default focal guess: 1.2 x the long side of the image
MAX_PAIRS_SHOWN = 20  # pairs listed one per line in the summary; above this only the weakest


@dataclass
class PoseConfig:
    """How cameras are estimated (pixel sizes are of the input images unless said otherwise)."""

    focal: float | None = None  # focal length in pixels of the input images; None: EXIF, else the prior
    max_size: int = 1600  # long side above which images are downscaled for feature extraction
    min_extraction_size: int = 800  # long side below which images are upscaled for feature extraction
    max_features: int = 8192  # SIFT features per image
    sift_upsample_below: int = 1000  # long side (extraction pixels) below which SIFT's first octave is upsampled
    min_inliers: int = 30  # verified matches a pair needs to define a relative pose
    focal_observable_angle: float = 20.0  # degrees of optical-axis spread needed to refine an EXIF focal
    min_triangulation_angle: float = 1.0  # degrees: median angle below this is a (near) pure rotation
    max_homography_share: float = 0.95  # two views: degenerate if H explains this share of E's inliers ...
    min_parallax_share: float = 0.04  # ... and fewer than this share of them move parallax_px off the homography
    parallax_px: float = 3.0  # offset from the homography that counts as parallax (pixels)
    min_homography_translation: float = 0.02  # below this (x the plane's distance) a homography is a pure rotation
    max_reprojection_error: float = 4.0  # px: points worse than this after two-view BA are dropped
    median_depth: float = 4.0  # scale convention: median point depth seen from the first camera
    depth_margin: float = 1.5  # near = p2 / margin, far = p98 * margin of the points' depths
    near: float | None = None  # overrides the near bound from the points
    far: float | None = None  # overrides the far bound from the points
    matching: Literal["auto", "exhaustive", "sequential"] = "auto"  # which image pairs are matched (see below)
    sequential_overlap: int = 10  # sequential matching: each image is matched with this many following ones
    quadratic_overlap: bool = True  # sequential: the images 2^k ahead (k < overlap) instead, COLMAP's default
    exhaustive_max_images: int = 30  # auto: exhaustive matching up to this many images, sequential above
    threads: int = -1  # CPU threads for pycolmap (-1: all)
    seed: int = 0  # RANSAC and mapper seed (COLMAP's threads can still change the outcome between runs)
    # Incremental mapping is run again (seed + 1, + 2, ...) while the best model so far leaves out an
    # image that has a verified pair: with several threads a run can stop after its first two images.
    mapping_attempts: int = 5
    colmap_log: bool = False  # let COLMAP log its stages to stderr

    def __post_init__(self) -> None:
        if self.matching not in ("auto", "exhaustive", "sequential"):
            raise SurfSplatInputError(f"matching: expected 'auto', 'exhaustive' or 'sequential', got {self.matching!r}")
        if self.sequential_overlap < 1:
            raise SurfSplatInputError(f"sequential_overlap: expected at least 1, got {self.sequential_overlap}")
        if self.mapping_attempts < 1:
            raise SurfSplatInputError(f"mapping_attempts: expected at least 1, got {self.mapping_attempts}")
        if self.focal is not None and not (math.isfinite(self.focal) and self.focal > 0):
            raise SurfSplatInputError(f"--focal: expected a positive focal length in pixels, got {self.focal}")
        if self.max_size < 64:
            raise SurfSplatInputError(f"--max-size: expected at least 64 pixels, got {self.max_size}")
        for name in ("near", "far"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise SurfSplatInputError(f"--{name}: expected a positive depth, got {value}")
        if self.near is not None and self.far is not None and not self.near < self.far:
            raise SurfSplatInputError(f"--near/--far: expected near < far, got {self.near}, {self.far}")


@dataclass
class PairStats:
    """Matching result of one image pair."""

    first: str
    second: str
    matches: int  # putative SIFT matches (ratio test, cross check)
    inliers: int  # matches consistent with the verified two-view geometry
    geometry: str  # COLMAP's verdict: CALIBRATED, UNCALIBRATED, PLANAR, PANORAMIC, ...


@dataclass
class PoseSummary:
    """What the estimation did, for the console, the output folder and the report."""

    images: list[str]  # every input image, in input order
    registered: list[str]  # the images that got a camera, in input order
    pairs: list[PairStats]
    method: str  # "two-view", or "incremental" (with how many mapping runs when more than one)
    points: int  # triangulated 3D points
    reprojection_error: float  # mean, in pixels of the input images
    focal: float  # pixels of the input images
    focal_source: str  # where the focal length came from
    width: int
    height: int
    extraction_size: tuple[int, int]  # (width, height) at which SIFT ran
    near: float
    far: float
    median_depth: float  # the scale convention (see the module docstring)
    seconds: float
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage: read, extract, match, reconstruct
    notes: list[str] = field(default_factory=list)  # what the user should know (dropped images, ...)
    # (width, height) of every input image; the photos may differ, each size with a camera of its own
    sizes: dict[str, tuple[int, int]] = field(default_factory=dict)

    @property
    def one_size(self) -> bool:
        return len(set(self.sizes.values())) <= 1

    @property
    def unregistered(self) -> list[str]:
        return [n for n in self.images if n not in self.registered]

    def lines(self) -> list[str]:
        """The human-readable summary printed by `surfsplat poses` and `reconstruct`."""
        out = [
            f"registered {len(self.registered)} of {len(self.images)} images ({self.method}) in {self.seconds:.1f} s",
            f"focal {self.focal:.1f} px for {self.width}x{self.height} images ({self.focal_source})",
            f"{self.points} 3D points, mean reprojection error {self.reprojection_error:.3f} px",
            f"world: first camera at the origin, median point depth {self.median_depth:g}; "
            f"near {self.near:.3f}, far {self.far:.3f}",
        ]
        shown = self.pairs
        if len(self.pairs) > MAX_PAIRS_SHOWN:  # hundreds of frames: the count and the weakest pairs
            shown = sorted(self.pairs, key=lambda p: p.inliers)[:MAX_PAIRS_SHOWN]
            out.append(f"{len(self.pairs)} pairs matched; the {len(shown)} with fewest inliers:")
        for p in shown:
            out.append(f"  {p.first} - {p.second}: {p.matches} matches, {p.inliers} inliers ({p.geometry})")
        out.extend(self.notes)
        return out

    def to_dict(self) -> dict:
        return {
            "images": self.images,
            "registered": self.registered,
            "unregistered": self.unregistered,
            "method": self.method,
            "points": self.points,
            "reprojection_error_px": self.reprojection_error,
            "focal_px": self.focal,
            "focal_source": self.focal_source,
            "width": self.width,
            "height": self.height,
            "extraction_size": list(self.extraction_size),
            "near": self.near,
            "far": self.far,
            "scale_convention": f"median depth of the points seen from the first camera = {self.median_depth:g}",
            "frame_convention": "OpenCV camera-to-world; the first registered camera is the world frame",
            "seconds": self.seconds,
            "timings": self.timings,
            "pairs": [vars(p) for p in self.pairs],
            "notes": self.notes,
            "image_sizes": {name: list(size) for name, size in self.sizes.items()},
        }


ImageInput = str | os.PathLike | np.ndarray | torch.Tensor


def estimate_cameras(
    images_or_paths: Sequence[ImageInput],
    focal: float | None = None,
    config: PoseConfig | None = None,
    names: Sequence[str] | None = None,
) -> tuple[CameraSet, PoseSummary]:
    """Cameras of two or more photos of one scene, estimated from the photos alone.

    images_or_paths: image files, or arrays ([H, W, 3] uint8 / float in [0, 1], or tensors
        [3, H, W] in [0, 1]); all of one size.
    focal: focal length in pixels of these images (overrides EXIF and the prior).
    names: a name per image (default: the file names, or view_000, ... for arrays).
    Returns the cameras of the registered images (OpenCV c2w, K in pixels of the images, near/far)
    in input order, and the summary. Photos may differ in size: each size gets a camera of its own,
    every K is in pixels of its own image, and the CameraSet's width x height is the first
    registered image's (with several sizes not one camera file's size: `summary.sizes` gives each
    image's). Raises SurfSplatInputError naming the cause when the photos do not define cameras (too
    few matches, pure rotation, a plane, unreadable files).
    """
    config = config or PoseConfig()
    if focal is not None:
        config = PoseConfig(**{**vars(config), "focal": float(focal)})
    start = time.perf_counter()
    arrays, names, paths = _load_images(images_or_paths, names)
    import pycolmap

    # COLMAP logs every stage to stderr; its failures reach the user as this module's errors instead
    quiet, pycolmap.logging.minloglevel = pycolmap.logging.minloglevel, 0 if config.colmap_log else 3
    try:
        camera_set, summary = _estimate(arrays, names, paths, config, start)
    finally:
        pycolmap.logging.minloglevel = quiet
    return camera_set, summary


def _estimate(arrays, names, paths, config: PoseConfig, start: float) -> tuple[CameraSet, PoseSummary]:
    sizes = [(a.shape[1], a.shape[0]) for a in arrays]
    distinct = list(dict.fromkeys(sizes))  # one camera per image size, in order of first appearance
    groups = [distinct.index(size) for size in sizes]
    if config.focal is not None and len(distinct) > 1:
        listing = ", ".join(f"{w}x{h}" for w, h in distinct)
        raise SurfSplatInputError(
            f"--focal: one focal length in pixels fits one image size, the photos have {len(distinct)} ({listing}); "
            "leave it out (EXIF or bundle adjustment finds one per size)"
        )
    focals = [
        _initial_focal(config, [p for p, g in zip(paths, groups) if g == k], *distinct[k]) for k in range(len(distinct))
    ]
    # one origin for bundle adjustment: an EXIF focal is refined only where every size has one
    origins = {origin for _, _, origin in focals}
    focal_origin = origins.pop() if len(origins) == 1 else "prior"
    ext_sizes = [_extraction_size(size, config) for size in distinct]
    ext_size = ext_sizes[0]
    with tempfile.TemporaryDirectory(prefix="surfsplat-poses-") as tmp:
        work = _Workspace(Path(tmp), names, distinct, groups, [f for f, _, _ in focals], focal_origin, config)
        timings = {"read": time.perf_counter() - start}
        work.extract(arrays, ext_sizes)
        timings["extract"] = time.perf_counter() - start - sum(timings.values())
        pairs = work.match()
        timings["match"] = time.perf_counter() - start - sum(timings.values())
        focal_note = None
        if len(names) == 2:
            recon = work.two_view(pairs[0])
            method = "two-view"
        else:
            recon, method, focal_note = work.incremental(pairs)
        timings["reconstruct"] = time.perf_counter() - start - sum(timings.values())
        cameras, K, registered, depths = _export(recon, work.ids, names)
    focal_source = focals[groups[names.index(registered[0])]][1]  # the summary's focal: K[0]'s camera
    if focal_note is not None:
        focal_source = focal_note.format(source=focal_source)
    notes = []
    dropped = [n for n in names if n not in registered]
    if dropped:
        notes.append(
            f"not registered (no reliable matches to the others): {', '.join(dropped)}; "
            f"continuing with the {len(registered)} registered images"
        )
    if len(distinct) > 1:
        for k, (w, h) in enumerate(distinct):
            members = [n for n, g in zip(names, groups) if g == k and n in registered]
            if members:
                fk = float(K[registered.index(members[0]), 0, 0])
                notes.append(
                    f"camera {k + 1} ({w}x{h}, {len(members)} images): focal {fk:.1f} px (initial: {focals[k][1]})"
                )
    cameras, depths = _normalize(cameras, depths, config.median_depth)
    near, far = _depth_range(depths, config)
    pinhole = Cameras(cameras, K)
    width, height = sizes[names.index(registered[0])]  # the size K[0] (and summary.focal) is in pixels of
    camera_set = CameraSet(pinhole, width, height, registered, near, far)
    summary = PoseSummary(
        images=list(names),
        registered=registered,
        pairs=pairs,
        method=method,
        points=int(recon.num_points3D()),
        reprojection_error=float(recon.compute_mean_reprojection_error()),
        focal=float(K[0, 0, 0]),
        focal_source=focal_source,
        width=width,
        height=height,
        extraction_size=ext_size,
        near=near,
        far=far,
        median_depth=config.median_depth,
        seconds=time.perf_counter() - start,
        timings=timings,
        notes=notes,
        sizes=dict(zip(names, sizes)),
    )
    return camera_set, summary


# ----------------------------------------------------------------------------------------- inputs
def _load_images(items: Sequence[ImageInput], names: Sequence[str] | None) -> tuple[list[np.ndarray], list[str], list]:
    """uint8 [H, W, 3] arrays, unique names and the source paths (None for arrays)."""
    from ..data.images import read_image

    if isinstance(items, (str, os.PathLike, np.ndarray, torch.Tensor)):
        raise SurfSplatInputError("images: expected a list of images or paths, got a single item")
    if len(items) < 2:
        raise SurfSplatInputError(f"images: poses need at least 2 images of one scene, got {len(items)}")
    arrays, auto_names, paths = [], [], []
    for i, item in enumerate(items):
        if isinstance(item, (str, os.PathLike)):
            path = Path(item)
            rgb, _ = read_image(path, background=(1.0, 1.0, 1.0))
            arrays.append(_to_uint8(rgb.permute(1, 2, 0).numpy(), str(path)))
            auto_names.append(path.name)
            paths.append(path)
        elif isinstance(item, (np.ndarray, torch.Tensor)):
            array = item.detach().cpu().permute(1, 2, 0).numpy() if isinstance(item, torch.Tensor) else item
            arrays.append(_to_uint8(array, f"images[{i}]"))
            auto_names.append(f"view_{i:03d}")
            paths.append(None)
        else:
            raise SurfSplatInputError(f"images[{i}]: expected a path or an image array, got {type(item).__name__}")
    names = list(names) if names is not None else auto_names
    if len(names) != len(arrays):
        raise SurfSplatInputError(f"names: expected {len(arrays)} names, got {len(names)}")
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise SurfSplatInputError(
            f"images: file names must be unique (cameras are keyed by name), repeated: {repeated}"
        )
    return arrays, names, paths


def _to_uint8(array: np.ndarray, source: str) -> np.ndarray:
    if array.ndim != 3 or array.shape[2] != 3:
        raise SurfSplatInputError(f"{source}: expected an RGB image [H, W, 3], got shape {tuple(array.shape)}")
    if array.shape[0] < 16 or array.shape[1] < 16:
        raise SurfSplatInputError(f"{source}: image of {array.shape[1]}x{array.shape[0]} is too small for features")
    if array.dtype == np.uint8:
        return np.ascontiguousarray(array)
    if not np.issubdtype(array.dtype, np.floating) or not np.isfinite(array).all():
        raise SurfSplatInputError(f"{source}: expected uint8 or finite float values in [0, 1], got {array.dtype}")
    return np.round(np.clip(array, 0, 1) * 255).astype(np.uint8)


def _extraction_size(size: tuple[int, int], config: PoseConfig) -> tuple[int, int]:
    """(width, height) SIFT runs at: the long side brought into [min_extraction_size, max_size]."""
    width, height = size
    long_side = max(width, height)
    s = min(max(long_side, config.min_extraction_size), config.max_size) / long_side
    return max(1, round(width * s)), max(1, round(height * s))


def _initial_focal(config: PoseConfig, paths: list, width: int, height: int) -> tuple[float, str, str]:
    """(focal in pixels, where it came from in words, "given" | "exif" | "prior")."""
    if config.focal is not None:
        return config.focal, "given (--focal)", "given"
    found = [exif_focal(p, width, height) for p in paths if p is not None]
    found = [f for f in found if f is not None]
    if found:
        focals = [f for f, _ in found]
        median = float(np.median(focals))
        spread = "" if max(focals) - min(focals) <= 1e-6 * median else f", median of {len(focals)} differing values"
        return median, f"{found[0][1]}{spread}", "exif"
    prior = FOCAL_PRIOR_FACTOR * max(width, height)
    return prior, f"prior {FOCAL_PRIOR_FACTOR:g} x the long side (no EXIF)", "prior"


# ----------------------------------------------------------------------------------------- engine
class _Workspace:
    """A temporary COLMAP database and image folder for one estimation."""

    def __init__(
        self,
        root: Path,
        names: list[str],
        sizes: list[tuple[int, int]],
        groups: list[int],
        focals: list[float],
        focal_origin: str,
        config: PoseConfig,
    ):
        import pycolmap

        self.pycolmap = pycolmap
        self.root = root
        self.names = names  # user names; files inside are s0/000000.png, ... (one folder per image size)
        self.files = [f"s{g}/{i:06d}.png" for i, g in enumerate(groups)]
        self.sizes = sizes  # (width, height) of each camera, one per image size
        self.groups = dict(zip(names, groups))  # user name -> its camera (index into sizes)
        self.focals = focals  # initial focal length of each camera, pixels of its images
        self.focal_origin = focal_origin  # "given", "exif" or "prior"
        self.config = config
        self.database = root / "database.db"
        self.images = root / "images"
        for g in range(len(sizes)):
            (self.images / f"s{g}").mkdir(parents=True)
        self.ids: dict[str, int] = {}  # user name -> database image id
        pycolmap.set_random_seed(config.seed)

    def camera(self, group: int = 0):
        """The pinhole camera of the images of one size (camera_id = group + 1)."""
        w, h = self.sizes[group]
        f = self.focals[group]
        return self.pycolmap.Camera(
            model="SIMPLE_PINHOLE", width=w, height=h, params=[f, w / 2, h / 2], camera_id=group + 1
        )

    def extract(self, arrays: list[np.ndarray], ext_sizes: list[tuple[int, int]]) -> None:
        pycolmap = self.pycolmap
        scales = [(e[0] / s[0], e[1] / s[1]) for e, s in zip(ext_sizes, self.sizes)]
        for array, file, name in zip(arrays, self.files, self.names):
            image = Image.fromarray(array)
            ext_size = ext_sizes[self.groups[name]]
            if image.size != ext_size:
                image = image.resize(ext_size, Image.Resampling.LANCZOS)
            image.save(self.images / file)
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "SIMPLE_PINHOLE"
        # every camera is replaced below by its size's, in the input images' pixels
        (sx, _), ext0 = scales[0], ext_sizes[0]
        reader.camera_params = f"{self.focals[0] * sx},{ext0[0] / 2},{ext0[1] / 2}"
        options = pycolmap.FeatureExtractionOptions()
        options.num_threads = self.config.threads
        options.sift.max_num_features = self.config.max_features
        # SIFT's first octave at twice the resolution (COLMAP's default) finds the fine features small
        # photos need; at 1000 px and more it costs 4x the time for features the photo already has.
        options.sift.first_octave = -1 if max(ext_size) < self.config.sift_upsample_below else 0
        pycolmap.extract_features(
            self.database,
            self.images,
            image_names=self.files,
            camera_mode=pycolmap.CameraMode.PER_FOLDER,  # one camera per image size (a folder each)
            reader_options=reader,
            extraction_options=options,
            device=pycolmap.Device.cpu,
        )
        # Back to the pixels of the input images: matching thresholds, the camera and every
        # reprojection error are then in the user's pixels. Pixel centres sit at +0.5 in both
        # COLMAP and this package, so a resize maps coordinates by a plain scale.
        db = pycolmap.Database.open(self.database)
        try:
            records = {im.name: im for im in db.read_all_images()}
            by_file = {name: im.image_id for name, im in records.items()}
            camera_group = {}  # database camera id -> image size group
            for name, file in zip(self.names, self.files):
                if file not in by_file:
                    raise SurfSplatInputError(f"{name}: feature extraction produced no entry for this image")
                self.ids[name] = by_file[file]
                camera_group[records[file].camera_id] = self.groups[name]
                sx, sy = scales[self.groups[name]]
                keypoints = db.read_keypoints(by_file[file]).copy()
                keypoints[:, 0] /= sx
                keypoints[:, 1] /= sy
                if keypoints.shape[1] == 6:  # affine shape [a11 a12; a21 a22] of each keypoint
                    keypoints[:, 2:4] /= sx
                    keypoints[:, 4:6] /= sy
                db.update_keypoints(by_file[file], keypoints)
            for cam in db.read_all_cameras():
                fixed = self.camera(camera_group[cam.camera_id])
                fixed.camera_id = cam.camera_id
                fixed.has_prior_focal_length = True
                db.update_camera(fixed)
        finally:
            db.close()

    def sequential(self) -> bool:
        """Whether only neighbours in input order are matched (ordered frames, large sets)."""
        cfg = self.config
        if cfg.matching == "auto":
            return len(self.names) > cfg.exhaustive_max_images
        return cfg.matching == "sequential"

    def match(self) -> list[PairStats]:
        """Match and verify pairs: every pair (exhaustive), or each image with its `sequential_overlap`
        successors in input order (sequential: frames of a video or an ordered walk, where matching
        all N^2 / 2 pairs of hundreds of frames costs hours and adds only pairs that share nothing)."""
        pycolmap = self.pycolmap
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = self.config.threads
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = self.config.seed
        sequential = self.sequential()
        if sequential:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = self.config.sequential_overlap
            pairing.quadratic_overlap = self.config.quadratic_overlap
            pycolmap.match_sequential(
                self.database,
                matching_options=matching,
                pairing_options=pairing,
                verification_options=verification,
                device=pycolmap.Device.cpu,
            )
        else:
            pycolmap.match_exhaustive(
                self.database, matching_options=matching, verification_options=verification, device=pycolmap.Device.cpu
            )
        db = pycolmap.Database.open(self.database)
        pairs = []
        try:
            for i in range(len(self.names)):
                for j in self._partners(i, sequential):
                    a, b = self.ids[self.names[i]], self.ids[self.names[j]]
                    matches = len(db.read_matches(a, b)) if db.exists_matches(a, b) else 0
                    inliers, geometry = 0, "no geometry"
                    if db.exists_two_view_geometry(a, b):
                        tvg = db.read_two_view_geometry(a, b)
                        inliers = len(tvg.inlier_matches)
                        geometry = pycolmap.TwoViewGeometryConfiguration(int(tvg.config)).name
                    pairs.append(PairStats(self.names[i], self.names[j], matches, inliers, geometry))
        finally:
            db.close()
        return pairs

    def _partners(self, i: int, sequential: bool) -> list[int]:
        """Indices after image i that it was matched with (COLMAP's sequential pairing rule)."""
        n, overlap = len(self.names), self.config.sequential_overlap
        if not sequential:
            return list(range(i + 1, n))
        offsets = [2**k for k in range(overlap)] if self.config.quadratic_overlap else range(1, overlap + 1)
        return [i + d for d in offsets if i + d < n]

    # ---- two views
    def two_view(self, pair: PairStats):
        """Calibrated relative pose, refinement, triangulation and a two-view bundle adjustment."""
        pycolmap = self.pycolmap
        cfg = self.config
        what = f"{pair.first} - {pair.second}"
        if pair.inliers < cfg.min_inliers:
            raise SurfSplatInputError(
                f"{what}: only {pair.inliers} verified matches ({pair.matches} putative), at least "
                f"{cfg.min_inliers} are needed: take the photos closer together (more overlap) or add images"
            )
        if pair.geometry == "PANORAMIC":
            raise _rotation_error(what, None)
        a, b = self.ids[pair.first], self.ids[pair.second]
        db = pycolmap.Database.open(self.database)
        try:
            kp1 = db.read_keypoints(a)[:, :2].astype(np.float64)
            kp2 = db.read_keypoints(b)[:, :2].astype(np.float64)
            inlier_matches = db.read_two_view_geometry(a, b).inlier_matches
        finally:
            db.close()
        camera1, camera2 = self.camera(self.groups[pair.first]), self.camera(self.groups[pair.second])
        p1, p2 = kp1[inlier_matches[:, 0]], kp2[inlier_matches[:, 1]]
        ransac = pycolmap.RANSACOptions()
        ransac.max_error = 1.0  # px; the verified matches are already consistent to 4 px
        ransac.random_seed = cfg.seed
        estimate = pycolmap.estimate_relative_pose(camera1, p1, camera2, p2, ransac)
        if estimate is None:
            raise SurfSplatInputError(
                f"{what}: no relative pose fits the {len(p1)} verified matches; give the focal length "
                "(--focal) or take photos with more overlap"
            )
        mask = np.asarray(estimate["inlier_mask"], dtype=bool).reshape(-1)
        self._check_not_homography(what, camera1, camera2, p1, p2, mask, ransac)
        pose = pycolmap.refine_relative_pose(estimate["cam2_from_cam1"], camera1, p1, camera2, p2, mask)
        if isinstance(pose, dict):
            pose = pose["cam2_from_cam1"]
        recon = pycolmap.Reconstruction()
        for camera in {camera1.camera_id: camera1, camera2.camera_id: camera2}.values():
            recon.add_camera_with_trivial_rig(camera)
        for image_id, kp, cam_from_world, camera in ((a, kp1, pycolmap.Rigid3d(), camera1), (b, kp2, pose, camera2)):
            name = pair.first if image_id == a else pair.second
            image = pycolmap.Image(name=name, keypoints=kp, camera_id=camera.camera_id, image_id=image_id)
            recon.add_image_with_trivial_frame(image, cam_from_world)
        self._triangulate(recon, a, b, inlier_matches[mask])
        angles = self._triangulation_angles(recon, a, b)
        if len(angles) < cfg.min_inliers:
            raise SurfSplatInputError(
                f"{what}: only {len(angles)} of {len(p1)} verified matches triangulate in front of both cameras; "
                "take photos with more overlap or give the focal length (--focal)"
            )
        median_angle = float(np.degrees(np.median(angles)))
        if median_angle < cfg.min_triangulation_angle:
            raise _rotation_error(what, median_angle)
        self._bundle_adjust(recon, refine_focal=False)
        self._filter(recon, cfg.max_reprojection_error)
        self._bundle_adjust(recon, refine_focal=False)
        return recon

    def _check_not_homography(
        self, what: str, camera1, camera2, p1: np.ndarray, p2: np.ndarray, e_mask: np.ndarray, ransac
    ) -> None:
        """Refuse pairs that one homography explains: a camera that only turned (any translation then
        fits E) or a single plane (two poses fit). COLMAP's own verdict (PLANAR_OR_PANORAMIC when H
        explains 80 % of what E does at 4 px) also fires on rooms whose floor dominates and on small
        baselines, so two measurements at the pose threshold decide instead: the share of E's inliers
        the homography also explains, and the share that moves more than `parallax_px` off it (what
        depth shows as). Measured: pure rotations and planes 98 % / 1-2 %; a room pair 0.2 m apart at
        2-6 m 93 % / 6 %; DTU and LLFF neighbours at most 52 % / at least 17 %."""
        pycolmap = self.pycolmap
        cfg = self.config
        # The homography's transfer error is a 2-D distance, the Sampson error of E a 1-D one: at
        # sqrt(2) times the threshold both accept the same isotropic noise.
        options = pycolmap.RANSACOptions()
        options.max_error = math.sqrt(2) * ransac.max_error
        options.random_seed = ransac.random_seed
        homography = pycolmap.estimate_homography_matrix(p1, p2, options)
        if homography is None:
            return
        inliers = np.asarray(homography["inlier_mask"], dtype=bool).reshape(-1)
        explained = float((inliers & e_mask).sum() / max(e_mask.sum(), 1))
        mapped = np.concatenate([p1, np.ones((len(p1), 1))], 1) @ np.asarray(homography["H"]).T
        offset = np.linalg.norm(mapped[:, :2] / mapped[:, 2:] - p2, axis=1)[e_mask]
        parallax = float((offset > cfg.parallax_px).mean())
        if explained < cfg.max_homography_share or parallax >= cfg.min_parallax_share:
            return
        rays1 = np.concatenate([camera1.cam_from_img(p1[inliers]), np.ones((inliers.sum(), 1))], 1)
        rays2 = np.concatenate([camera2.cam_from_img(p2[inliers]), np.ones((inliers.sum(), 1))], 1)
        K1, K2 = camera1.calibration_matrix(), camera2.calibration_matrix()
        decomposed = pycolmap.pose_from_homography_matrix(homography["H"], K1, K2, rays1, rays2)
        # H = R - t n^T / d: the translation comes out in units of the plane's distance d
        moved = float(np.linalg.norm(decomposed["cam2_from_cam1"].translation))
        if moved < cfg.min_homography_translation:
            raise _rotation_error(what, None)
        raise SurfSplatInputError(
            f"{what}: one homography explains {explained:.0%} of the matches and only {parallax:.1%} show "
            f"parallax (> {cfg.parallax_px:g} px): the scene is (nearly) one plane, or the camera mostly turned; "
            "two different camera poses fit such photos. Include objects at other depths, step sideways "
            "between photos, add a third photo, or give --focal"
        )

    def _triangulate(self, recon, a: int, b: int, matches: np.ndarray) -> None:
        pycolmap = self.pycolmap
        image_a, image_b = recon.images[a], recon.images[b]
        camera_a, camera_b = recon.cameras[image_a.camera_id], recon.cameras[image_b.camera_id]
        P1, P2 = image_a.cam_from_world().matrix(), image_b.cam_from_world().matrix()
        xy1 = camera_a.cam_from_img(np.array([image_a.points2D[i].xy for i in matches[:, 0]]))
        xy2 = camera_b.cam_from_img(np.array([image_b.points2D[i].xy for i in matches[:, 1]]))
        c1, c2 = image_a.projection_center(), image_b.projection_center()
        for (i, j), u, v in zip(matches, xy1, xy2):
            point = pycolmap.triangulate_point(P1, P2, u, v)
            if point is None:
                continue
            point = np.asarray(point).reshape(3)
            depth1 = (P1[:, :3] @ point + P1[:, 3])[2]
            depth2 = (P2[:, :3] @ point + P2[:, 3])[2]
            if depth1 <= 0 or depth2 <= 0 or pycolmap.calculate_triangulation_angle(c1, c2, point) <= 0:
                continue
            track = pycolmap.Track()
            track.add_element(a, int(i))
            track.add_element(b, int(j))
            recon.add_point3D(point, track)

    def _triangulation_angles(self, recon, a: int, b: int) -> np.ndarray:
        c1, c2 = recon.images[a].projection_center(), recon.images[b].projection_center()
        return np.array([self.pycolmap.calculate_triangulation_angle(c1, c2, p.xyz) for p in recon.points3D.values()])

    def _bundle_adjust(self, recon, refine_focal: bool) -> None:
        """Global BA with a Cauchy loss (outliers the verification let through weigh little); gauge:
        the first camera's pose and the distance to the second are fixed."""
        pycolmap = self.pycolmap
        options = pycolmap.BundleAdjustmentOptions()
        options.print_summary = False
        options.refine_focal_length = refine_focal
        options.refine_principal_point = False
        options.refine_extra_params = False
        options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
        options.ceres.solver_options.num_threads = self.config.threads
        options.ceres.min_num_residuals_for_cpu_multi_threading = 1000
        config = pycolmap.BundleAdjustmentConfig()
        for image_id in recon.reg_image_ids():
            config.add_image(image_id)
        config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
        pycolmap.create_default_bundle_adjuster(options, config, recon).solve()
        recon.update_point_3d_errors()

    @staticmethod
    def _filter(recon, max_error: float) -> None:
        recon.update_point_3d_errors()
        for point_id in list(recon.point3D_ids()):
            if recon.points3D[point_id].error > max_error:
                recon.delete_point3D(point_id)

    # ---- three or more views
    def incremental(self, pairs: list[PairStats]):
        pycolmap = self.pycolmap
        cfg = self.config
        usable = [p for p in pairs if p.inliers >= cfg.min_inliers]
        if not usable:
            best = max(pairs, key=lambda p: p.inliers)
            raise SurfSplatInputError(
                f"no image pair has {cfg.min_inliers} verified matches (best: {best.first} - {best.second} with "
                f"{best.inliers}): the photos do not overlap enough; take them closer together"
            )
        options = pycolmap.IncrementalPipelineOptions()
        options.num_threads = cfg.threads
        options.random_seed = cfg.seed
        options.min_num_matches = cfg.min_inliers
        options.multiple_models = False
        options.extract_colors = False
        options.ba_refine_focal_length = self.focal_origin == "prior"  # an EXIF focal is only refined below
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = False
        # COLMAP threads BA only above 50,000 residuals; a few thousand points of 8 photos are below
        # that and then take 30 % longer (measured: 8 views at 1000 px, 28.7 s -> 20.1 s mapping)
        options.ba_min_num_residuals_for_cpu_multi_threading = 1000
        connected = len({p.first for p in usable} | {p.second for p in usable})
        best = None
        for runs in range(1, cfg.mapping_attempts + 1):
            options.random_seed = cfg.seed + runs - 1
            out = self.root / "sparse" / str(runs - 1)
            out.mkdir(parents=True, exist_ok=True)
            models = pycolmap.incremental_mapping(self.database, self.images, out, options)
            largest = max(models.values(), key=lambda r: r.num_reg_images(), default=None)
            if largest is not None and (best is None or largest.num_reg_images() > best.num_reg_images()):
                best = largest
            if best is not None and best.num_reg_images() >= connected:
                break
        if best is None or best.num_reg_images() < 2:
            recon = self.two_view(max(usable, key=lambda p: p.inliers))
            return recon, "two-view (the incremental mapper registered fewer than 2 images)", None
        spread = _axis_spread(best)
        refine = self.focal_origin == "prior" or (self.focal_origin == "exif" and spread >= cfg.focal_observable_angle)
        self._bundle_adjust(best, refine_focal=refine)
        if self.focal_origin == "given":
            note = None
        elif refine and spread >= cfg.focal_observable_angle:
            note = "estimated by bundle adjustment from {source}"
        elif refine:
            note = (
                "estimated by bundle adjustment from {source}, weakly: the viewing directions span only "
                f"{spread:.1f} deg (focal length and depth trade off); give --focal if it is known"
            )
        else:
            note = (
                f"{{source}}, kept: the viewing directions span only {spread:.1f} deg, too little to refine it "
                f"(at least {cfg.focal_observable_angle:g} deg)"
            )
        return best, "incremental" if runs == 1 else f"incremental (the largest of {runs} mapping runs)", note


def _axis_spread(recon) -> float:
    """Largest angle in degrees between the optical axes of two registered cameras."""
    axes = np.array([recon.images[i].cam_from_world().rotation.matrix()[2] for i in recon.reg_image_ids()])
    cosines = np.clip(axes @ axes.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cosines.min())))


def _rotation_error(what: str, angle: float | None) -> SurfSplatInputError:
    measured = f" (median triangulation angle {angle:.2f} deg)" if angle is not None else ""
    return SurfSplatInputError(
        f"{what}: the camera turned without moving, or moved too little for depth{measured}; "
        "step sideways between photos (a baseline of about a tenth of the distance to the scene) or add images"
    )


# ----------------------------------------------------------------------------------------- outputs
def _export(recon, ids: dict[str, int], names: list[str]):
    """(c2w [R, 4, 4] float64, K [R, 3, 3], registered names, per-view point depths) in input order."""
    registered = [n for n in names if ids[n] in recon.images and recon.images[ids[n]].has_pose]
    Ks = []
    for name in registered:  # each image's camera: one per image size
        f, cx, cy = (float(v) for v in recon.cameras[recon.images[ids[name]].camera_id].params)
        Ks.append(torch.tensor([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]], dtype=torch.float64))
    K = torch.stack(Ks)
    w2c = np.tile(np.eye(4), (len(registered), 1, 1))
    for k, name in enumerate(registered):
        w2c[k, :3, :4] = recon.images[ids[name]].cam_from_world().matrix()
    c2w = np.linalg.inv(w2c)
    xyz = np.array([p.xyz for p in recon.points3D.values()]).reshape(-1, 3)
    depths = [(xyz @ w[:3, :3].T + w[:3, 3])[:, 2] for w in w2c]
    return torch.from_numpy(c2w), K, registered, depths


def _normalize(c2w: torch.Tensor, depths: list[np.ndarray], median_depth: float):
    """World = the first camera; lengths scaled so the median depth of the points it sees is `median_depth`."""
    first = c2w[0]
    c2w = torch.linalg.inv(first)[None] @ c2w
    seen = depths[0][depths[0] > 0]
    if len(seen) == 0:
        raise SurfSplatInputError("no triangulated point lies in front of the first camera")
    scale = median_depth / float(np.median(seen))
    c2w[:, :3, 3] *= scale
    return c2w, [d * scale for d in depths]


def _depth_range(depths: list[np.ndarray], config: PoseConfig) -> tuple[float, float]:
    every = np.concatenate([d[d > 0] for d in depths])
    near = float(np.percentile(every, 2)) / config.depth_margin
    far = float(np.percentile(every, 98)) * config.depth_margin
    near = config.near if config.near is not None else near
    far = config.far if config.far is not None else far
    if not near < far:
        raise SurfSplatInputError(f"--near/--far: expected near < far, got {near:.4g}, {far:.4g}")
    return near, far
