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
4. Intrinsics: one shared camera with a lens model, as COLMAP's automatic reconstruction fits
   (`PoseConfig.camera_model`): SIMPLE_RADIAL (f, principal point at the centre, one radial
   coefficient k) by default, OPENCV (fx, fy, k1, k2, p1, p2) where it pays (`_Workspace.choose_model`:
   SIMPLE_RADIAL leaves at least `opencv_min_excess` (0.1 px) of reprojection error that OPENCV
   explains, in quadrature; a mild lens of DTU's field of view leaves 0.02 px), or the
   model asked for (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV; RADIAL and OPENCV are
   mapped as SIMPLE_RADIAL and refined from its fit at the end, `MAPPING_MODEL`). The principal point
   stays at the centre (COLMAP's default: it is poorly observable without a calibration target).
   The distortion is refined by every bundle adjustment (the mapper's, the two-view one, the final
   one), and the cameras returned are the pinhole the photos are undistorted to
   (`surfsplat.geometry.lens.undistorted_pinhole`, COLMAP's image_undistorter), with the fitted
   lens of every view in `CameraSet.lenses`. f comes from `focal`, else EXIF, else the
   prior 1.2 x the long side (COLMAP's default guess, a 45 degree field of view on the long side).
   With 3+ views bundle adjustment refines the prior always and an EXIF value only when the
   optical axes span `focal_observable_angle` (20 degrees): with nearly parallel views (LLFF fern
   views 0-3 span 11 degrees) focal length and depth trade off, and refining a correct EXIF focal
   moved it by 16 % and the rotations by 1.8 degrees. With two views f is not observable and stays
   at its source; a given f is never changed.
   Photos of several sizes (a phone's portrait and landscape photos, two phones, resized copies) get a
   camera each per distinct (width, height), as COLMAP's automatic reconstruction does (its AUTO
   camera mode shares a camera between photos whose EXIF make, model, focal length and size agree;
   here every photo of one size shares its size's camera, EXIF or not, with its EXIF focal the
   median of that size's). Each size has its own extraction size (step 1), focal source and lens,
   mapped back to its own pixels; each view's K is its own size's pinhole, and `CameraSet.lenses`
   gives every view its lens (pinhole models too: the lens's size says which pixels its K is in).
   The lens model is chosen once for all cameras (the mapper fits one model; auto's OPENCV trial
   refines every camera and is judged on their pooled reprojection error): the sizes are most
   often one lens, and a size with a few photos alone would decide on too few observations. An
   EXIF focal is kept (narrow spreads) only where every size has one, and `focal` (pixels of one
   size) is refused for photos of several.
5. Frame and scale: world = the first registered camera (identity rotation, centre at the
   origin), OpenCV axes. Scale: the median depth of the triangulated points seen from that camera
   is `PoseConfig.median_depth` (4 by default: the room scale RealEstate10K-trained checkpoints and
   the synthetic rooms see, so near and far land well inside their trained range 1..100). near
   and far are the 2nd and 98th percentiles of every registered view's point depths divided and
   multiplied by `depth_margin`.
6. Repeatability: the same photos give the same cameras bit for bit. Every RANSAC and the mapper
   take `seed`; the images enter the database in input order (ids independent of the extraction
   threads); the mapper and every bundle adjustment run on `mapping_threads` (1) threads, since
   Ceres with several threads sums in the order the threads finish. Extraction and matching keep
   `threads` (all cores): SIFT gives each image the same keypoints on any number of threads.
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
from ..geometry.lens import Lens
from ..utils.checks import SurfSplatInputError
from .exif import exif_focal

FOCAL_PRIOR_FACTOR = 1.2  # COLMAP's default focal guess: 1.2 x the long side of the image
MAX_PAIRS_SHOWN = 20  # pairs listed one per line in the summary; above this only the weakest
# The lens models that can be fitted (COLMAP's perspective models of its automatic reconstruction)
FITTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
CameraModel = Literal["auto", "SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"]
# The model the mapper works with, where it is not the one fitted: RADIAL and OPENCV are mapped with
# SIMPLE_RADIAL and refined from its fit by the last bundle adjustment. Mapped with OPENCV from the start,
# distorted DTU views 12-26 registered 3 of 15 (k2 ran to 0.5 on a field of view too narrow to show it).
MAPPING_MODEL = {"auto": "SIMPLE_RADIAL", "RADIAL": "SIMPLE_RADIAL", "OPENCV": "SIMPLE_RADIAL"}


@dataclass
class PoseConfig:
    """How cameras are estimated (pixel sizes are of the input images unless said otherwise)."""

    focal: float | None = None  # focal length in pixels of the input images; None: EXIF, else the prior
    # lens model fitted: "auto" = SIMPLE_RADIAL, or OPENCV where it explains opencv_min_excess more (see choose_model)
    camera_model: CameraModel = "auto"
    opencv_min_excess: float = 0.1  # px: auto takes OPENCV when SIMPLE_RADIAL leaves this much error it explains
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
    threads: int = -1  # CPU threads of feature extraction and matching (-1: all)
    # CPU threads of the mapper and bundle adjustment: 1 repeats bit for bit (with more, Ceres sums in thread order)
    mapping_threads: int = 1
    seed: int = 0  # RANSAC and mapper seed; with mapping_threads 1 the same photos give the same cameras bit for bit
    # Incremental mapping is run again (seed + 1, + 2, ...) while the best model so far leaves out an
    # image that has a verified pair: with several threads a run can stop after its first two images.
    mapping_attempts: int = 5
    colmap_log: bool = False  # let COLMAP log its stages to stderr

    def __post_init__(self) -> None:
        if self.camera_model not in ("auto", *FITTED_MODELS):
            raise SurfSplatInputError(
                f"--camera-model: expected 'auto' or one of {', '.join(FITTED_MODELS)}, got {self.camera_model!r}"
            )
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
    lens: Lens | None = None  # the fitted camera: COLMAP model and parameters, in pixels of the input images
    pinhole: Lens | None = None  # the PINHOLE camera the photos are undistorted to (the K returned)
    model_choice: str = ""  # why this model (the rule of camera_model "auto", or "asked for")
    model_errors: dict[str, float] = field(default_factory=dict)  # mean reprojection error (px) per model fitted
    # auto: the largest distance (px) between the pixels SIMPLE_RADIAL's and OPENCV's fits give one ray, over the image
    model_difference_px: float | None = None
    model_excess_px: float | None = None  # auto: the reprojection error SIMPLE_RADIAL leaves that OPENCV explains
    # (width, height) of every input image: photos of several sizes get a camera each (see PoseCamera)
    sizes: dict[str, tuple[int, int]] = field(default_factory=dict)
    # one per image size with a registered image, in order of first appearance; lens, pinhole, width, height,
    # focal and extraction_size above are the first registered image's camera's
    cameras: list[PoseCamera] = field(default_factory=list)

    @property
    def unregistered(self) -> list[str]:
        return [n for n in self.images if n not in self.registered]

    def lens_of(self, name: str) -> Lens | None:
        """The fitted lens of a registered image (its size's camera), in pixels of that image."""
        for camera in self.cameras:
            if name in camera.images:
                return camera.lens
        return self.lens if name in self.registered else None

    def lines(self) -> list[str]:
        """The human-readable summary printed by `surfsplat poses` and `reconstruct`."""
        several = len(self.cameras) > 1
        out = [
            f"registered {len(self.registered)} of {len(self.images)} images ({self.method}) in {self.seconds:.1f} s",
            f"focal {self.focal:.1f} px for {self.width}x{self.height} images ({self.focal_source})"
            if not several
            else f"{len(self.cameras)} cameras, one per image size (the lens model chosen once for all: "
            f"{self.model_choice})",
            *(self._lens_lines() if not several else [line for c in self.cameras for line in c.lines()]),
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

    def _lens_lines(self) -> list[str]:
        if self.lens is None:
            return []
        values = ", ".join(f"{n} {_format_param(n, v)}" for n, v in zip(self.lens.param_names, self.lens.params))
        out = [f"camera {self.lens.model}: {values} ({self.model_choice})"]
        if self.pinhole is not None and not self.lens.is_pinhole:
            fx, fy, cx, cy = self.pinhole.params
            out.append(
                f"photos undistorted to PINHOLE {self.pinhole.width}x{self.pinhole.height}: "
                f"fx {fx:.1f}, fy {fy:.1f}, cx {cx:.1f}, cy {cy:.1f}"
            )
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
            "camera_model": None if self.lens is None else self.lens.model,
            "camera_params": None if self.lens is None else dict(zip(self.lens.param_names, self.lens.params)),
            "lens": None if self.lens is None else self.lens.to_dict(),
            "pinhole": None if self.pinhole is None else self.pinhole.to_dict(),
            "model_choice": self.model_choice,
            "reprojection_error_px_by_model": self.model_errors,
            "model_difference_px": self.model_difference_px,
            "model_excess_px": self.model_excess_px,
            "image_sizes": {name: list(size) for name, size in self.sizes.items()},
            "cameras": [c.to_dict() for c in self.cameras],
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
        }


@dataclass
class PoseCamera:
    """The camera of the photos of one size: COLMAP's automatic reconstruction gives photos of another
    size (a portrait photo among landscape ones, a second phone) a camera of their own."""

    width: int
    height: int
    images: list[str]  # the registered images of this size, in input order
    lens: Lens  # the fitted camera, in pixels of this size
    pinhole: Lens  # the PINHOLE its photos are undistorted to
    focal_source: str  # where its initial focal length came from
    extraction_size: tuple[int, int]  # (width, height) at which SIFT ran on these photos

    def lines(self) -> list[str]:
        values = ", ".join(f"{n} {_format_param(n, v)}" for n, v in zip(self.lens.param_names, self.lens.params))
        shown = ", ".join(self.images[:4]) + (", ..." if len(self.images) > 4 else "")
        out = [
            f"camera {self.width}x{self.height} ({len(self.images)} image{'s' if len(self.images) != 1 else ''}: "
            f"{shown}): {self.lens.model} {values} (initial focal: {self.focal_source})"
        ]
        if not self.lens.is_pinhole:
            fx, fy, cx, cy = self.pinhole.params
            out.append(
                f"  photos undistorted to PINHOLE {self.pinhole.width}x{self.pinhole.height}: "
                f"fx {fx:.1f}, fy {fy:.1f}, cx {cx:.1f}, cy {cy:.1f}"
            )
        return out

    def to_dict(self) -> dict:
        return {
            "width": self.width,
            "height": self.height,
            "images": self.images,
            "lens": self.lens.to_dict(),
            "pinhole": self.pinhole.to_dict(),
            "focal_source": self.focal_source,
            "extraction_size": list(self.extraction_size),
        }


def _format_param(name: str, value: float) -> str:
    """Pixels to 0.1 px, distortion coefficients to four significant digits."""
    return f"{value:.1f}" if name in ("f", "fx", "fy", "cx", "cy") else f"{value:.4g}"


ImageInput = str | os.PathLike | np.ndarray | torch.Tensor


def estimate_cameras(
    images_or_paths: Sequence[ImageInput],
    focal: float | None = None,
    config: PoseConfig | None = None,
    names: Sequence[str] | None = None,
    colmap_model: str | os.PathLike | None = None,
) -> tuple[CameraSet, PoseSummary]:
    """Cameras of two or more photos of one scene, estimated from the photos alone.

    images_or_paths: image files, or arrays ([H, W, 3] uint8 / float in [0, 1], or tensors
        [3, H, W] in [0, 1]); of one size, or of several (portrait and landscape photos, two
        phones): each size gets a camera of its own (see the module doc, 4).
    focal: focal length in pixels of these images (overrides EXIF and the prior); photos of one size only.
    names: a name per image (default: the file names, or view_000, ... for arrays).
    colmap_model: a folder to write the reconstruction to as a COLMAP model (pycolmap's binary
        cameras/images/points3D files, the images by these names, the fitted lens in the input
        pixels, the world of the returned cameras: first camera at the origin, their scale).
    Returns the cameras of the registered images (OpenCV c2w, each K in pixels of the pinhole its
    photo is undistorted to, near/far) in input order, and the summary. With several sizes
    `CameraSet.lenses` holds every view's lens (pinhole models too), whose sizes say which pixels each
    K is in; width x height are then the first registered image's. Raises SurfSplatInputError naming the cause when the photos
    do not define cameras (too few matches, pure rotation, a plane, unreadable files).
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
        camera_set, summary = _estimate(arrays, names, paths, config, start, colmap_model)
    finally:
        pycolmap.logging.minloglevel = quiet
    return camera_set, summary


def _estimate(arrays, names, paths, config: PoseConfig, start: float, colmap_model) -> tuple[CameraSet, PoseSummary]:
    sizes = [(a.shape[1], a.shape[0]) for a in arrays]
    distinct = list(dict.fromkeys(sizes))  # one camera per (width, height), in order of first appearance
    groups = [distinct.index(size) for size in sizes]
    if config.focal is not None and len(distinct) > 1:
        listing = ", ".join(f"{w}x{h}" for w, h in distinct)
        raise SurfSplatInputError(
            f"--focal: one focal length in pixels fits photos of one size, these have {len(distinct)} ({listing}); "
            "leave it out (EXIF, else bundle adjustment, finds one per size)"
        )
    focals = [
        _initial_focal(config, [p for p, g in zip(paths, groups) if g == k], *distinct[k]) for k in range(len(distinct))
    ]
    # one rule for bundle adjustment: an EXIF focal is kept (narrow spreads) only where every size has one
    origins = {origin for _, _, origin in focals}
    focal_origin = origins.pop() if len(origins) == 1 else "prior"
    ext_sizes = [_extraction_size(size, config) for size in distinct]
    model = MAPPING_MODEL.get(config.camera_model, config.camera_model)
    with tempfile.TemporaryDirectory(prefix="surfsplat-poses-") as tmp:
        work = _Workspace(Path(tmp), names, distinct, groups, [f for f, _, _ in focals], focal_origin, model, config)
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
        recon, choice = work.choose_model(recon)
        timings["reconstruct"] = time.perf_counter() - start - sum(timings.values())
        cameras, K, registered, depths, view_lenses, view_pinholes = _export(recon, work.ids, names)
    first = groups[names.index(registered[0])]  # the summary's size, focal and lens: the first registered image's
    lens, pinhole = view_lenses[0], view_pinholes[0]
    focal_source = focals[first][1]
    if focal_note is not None:
        focal_source = focal_note.format(source=focal_source)
    notes = []
    dropped = [n for n in names if n not in registered]
    if dropped:
        notes.append(
            f"not registered (no reliable matches to the others): {', '.join(dropped)}; "
            f"continuing with the {len(registered)} registered images"
        )
    first_w2c = torch.linalg.inv(cameras[0]).numpy()
    cameras, depths, scale = _normalize(cameras, depths, config.median_depth)
    if colmap_model is not None:
        _write_colmap_model(recon, work.ids, Path(colmap_model), scale * first_w2c[:3, :4])
    near, far = _depth_range(depths, config)
    # one size: the lens of every view where it has distortion (none: K says it all); several sizes: every
    # view's lens, pinhole models too, since each lens's size says which pixels its view's K is in
    several = len(distinct) > 1
    lenses = list(view_lenses) if several or not lens.is_pinhole else None
    camera_set = CameraSet(Cameras(cameras, K), pinhole.width, pinhole.height, registered, near, far, lenses)
    per_size = []
    for k, (w, h) in enumerate(distinct):
        members = [i for i, n in enumerate(registered) if groups[names.index(n)] == k]
        if members:
            per_size.append(
                PoseCamera(
                    w, h, [registered[i] for i in members], view_lenses[members[0]], view_pinholes[members[0]],
                    focals[k][1], ext_sizes[k],
                )
            )  # fmt: skip
    summary = PoseSummary(
        images=list(names),
        registered=registered,
        pairs=pairs,
        method=method,
        points=int(recon.num_points3D()),
        reprojection_error=float(recon.compute_mean_reprojection_error()),
        focal=float(lens.params[0]),
        focal_source=focal_source,
        width=distinct[first][0],
        height=distinct[first][1],
        extraction_size=ext_sizes[first],
        near=near,
        far=far,
        median_depth=config.median_depth,
        seconds=time.perf_counter() - start,
        timings=timings,
        notes=notes,
        lens=lens,
        pinhole=pinhole,
        model_choice=choice.reason,
        model_errors=choice.errors,
        model_difference_px=choice.difference_px,
        model_excess_px=choice.excess_px,
        sizes=dict(zip(names, sizes)),
        cameras=per_size,
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
    """(width, height) SIFT runs at for photos of `size`: the long side brought into
    [min_extraction_size, max_size] (step 1 of the module doc)."""
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
        model: str,
        config: PoseConfig,
    ):
        import pycolmap

        self.pycolmap = pycolmap
        self.root = root
        self.names = names  # user names; files inside are 000000.png, ... (s0/000000.png, ... for several sizes)
        # photos of several sizes: a folder per size, for COLMAP's camera per folder (CameraMode.PER_FOLDER)
        several = len(sizes) > 1
        self.files = [f"s{g}/{i:06d}.png" if several else f"{i:06d}.png" for i, g in enumerate(groups)]
        self.sizes = sizes  # (width, height) of each camera, one per image size
        self.groups = dict(zip(names, groups))  # user name -> its camera (index into sizes; camera_id = index + 1)
        self.focals = focals  # initial focal length of each camera, in pixels of its images
        self.focal_origin = focal_origin  # "given", "exif" or "prior"
        self.model = model  # COLMAP camera model the mapper fits (MAPPING_MODEL of the one asked for)
        self.refine_focal = False  # whether the final bundle adjustment refined the focal length
        self.config = config
        self.database = root / "database.db"
        self.images = root / "images"
        self.images.mkdir()
        for g in range(len(sizes) if several else 0):
            (self.images / f"s{g}").mkdir()
        self.ids: dict[str, int] = {}  # user name -> database image id
        pycolmap.set_random_seed(config.seed)

    def camera(self, group: int = 0):
        """The starting camera of the photos of one size (camera_id = group + 1), at that size: COLMAP's
        initial parameters for the model (principal point at the centre, distortion zero) with its focal length."""
        w, h = self.sizes[group]
        return self.pycolmap.Camera.create_from_model_name(group + 1, self.model, self.focals[group], w, h)

    def extract(self, arrays: list[np.ndarray], ext_sizes: list[tuple[int, int]]) -> None:
        """SIFT on every photo at its size's extraction size, keypoints mapped back to its own pixels."""
        pycolmap = self.pycolmap
        for array, file, name in zip(arrays, self.files, self.names):
            image = Image.fromarray(array)
            ext_size = ext_sizes[self.groups[name]]
            if image.size != ext_size:
                image = image.resize(ext_size, Image.Resampling.LANCZOS)
            image.save(self.images / file)
        scales = [(e[0] / s[0], e[1] / s[1]) for e, s in zip(ext_sizes, self.sizes)]
        # the camera at the extraction size: focal length and principal point scale with the image, the
        # distortion coefficients act on normalized coordinates and do not (pycolmap's Camera.rescale).
        # With several sizes the reader starts every folder's camera from the first one's; each is replaced
        # by its own size's below.
        at_extraction = self.camera()
        at_extraction.rescale(*ext_sizes[0])
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = self.model
        reader.camera_params = at_extraction.params_to_string()
        # COLMAP's automatic reconstruction (CameraMode.AUTO) shares a camera between photos whose EXIF make,
        # model, focal length and width x height agree, and gives every other photo one of its own; here the
        # photos of one size share one (a folder each: PER_FOLDER), EXIF or not, so that a size's few photos
        # still pin its focal length and distortion together.
        mode = pycolmap.CameraMode.PER_FOLDER if len(self.sizes) > 1 else pycolmap.CameraMode.SINGLE
        # The images enter the database one by one in input order first, so their ids are 1, 2, ... in
        # that order: feature extraction on several threads numbers them as they finish (measured: of
        # two runs on six DTU photos, one gave the first photo id 2), the mapper breaks ties by id,
        # and the same photos then gave other cameras in one run of three.
        pycolmap.Database.open(self.database).close()
        pycolmap.import_images(self.database, self.images, mode, self.files, reader)
        # SIFT's first octave at twice the resolution (COLMAP's default) finds the fine features small
        # photos need; at 1000 px and more it costs 4x the time for features the photo already has. One
        # extraction per setting (sizes on both sides of sift_upsample_below), in input order within each.
        octaves = [-1 if max(ext_sizes[self.groups[n]]) < self.config.sift_upsample_below else 0 for n in self.names]
        for octave in dict.fromkeys(octaves):
            options = pycolmap.FeatureExtractionOptions()
            options.num_threads = self.config.threads
            options.sift.max_num_features = self.config.max_features
            options.sift.first_octave = octave
            pycolmap.extract_features(
                self.database,
                self.images,
                image_names=[f for f, o in zip(self.files, octaves) if o == octave],
                camera_mode=mode,
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
            camera_group = {}  # database camera id -> image size group
            for name, file in zip(self.names, self.files):
                if file not in records:
                    raise SurfSplatInputError(f"{name}: feature extraction produced no entry for this image")
                self.ids[name] = records[file].image_id
                camera_group[records[file].camera_id] = self.groups[name]
                sx, sy = scales[self.groups[name]]
                keypoints = db.read_keypoints(self.ids[name]).copy()
                keypoints[:, 0] /= sx
                keypoints[:, 1] /= sy
                if keypoints.shape[1] == 6:  # affine shape [a11 a12; a21 a22] of each keypoint
                    keypoints[:, 2:4] /= sx
                    keypoints[:, 4:6] /= sy
                db.update_keypoints(self.ids[name], keypoints)
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
        for camera in {camera1.camera_id: camera1, camera2.camera_id: camera2}.values():  # one, or one per size
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
        self.refine_focal = False  # not observable from two views: the focal stays at its source
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
        the first camera's pose and the distance to the second are fixed. The distortion parameters
        of the camera's model (none for the pinhole models) are always refined."""
        pycolmap = self.pycolmap
        options = pycolmap.BundleAdjustmentOptions()
        options.print_summary = False
        options.refine_focal_length = refine_focal
        options.refine_principal_point = False
        options.refine_extra_params = any(len(c.extra_params_idxs()) for c in recon.cameras.values())
        options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
        options.ceres.solver_options.num_threads = self.config.mapping_threads
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
        options.num_threads = cfg.mapping_threads
        options.random_seed = cfg.seed
        options.min_num_matches = cfg.min_inliers
        options.multiple_models = False
        options.extract_colors = False
        options.ba_refine_focal_length = self.focal_origin == "prior"  # an EXIF focal is only refined below
        options.ba_refine_principal_point = False
        options.ba_refine_extra_params = self.model not in ("SIMPLE_PINHOLE", "PINHOLE")
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
        self.refine_focal = refine
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

    # ---- the lens model
    def choose_model(self, recon) -> tuple[object, _ModelChoice]:
        """The model asked for as fitted; or, for camera_model "auto", SIMPLE_RADIAL's fit against
        OPENCV's. OPENCV starts from SIMPLE_RADIAL's fit (fx = fy = f, k1 = k) and one more bundle
        adjustment refines it on the same points and observations, with the same focal rule. The
        error SIMPLE_RADIAL leaves that OPENCV explains is the difference of their mean reprojection
        errors in quadrature, sqrt(e_SR^2 - e_OPENCV^2) (the noise of the keypoints is in both and
        cancels; a relative gain would hide a real misfit behind noisy keypoints). OPENCV replaces
        SIMPLE_RADIAL when that is at least `opencv_min_excess` pixels and its parameters pass COLMAP's
        sanity check (the mapper's focal ratio and distortion bounds). Measured: OPENCV's four more
        parameters explain 0.02 px of DTU photos through a mild OPENCV lens (its k2 and p terms move
        the corners by 0.3 px) and 0.06 px of a ray-cast room through a lens with fy = 0.97 fx, where
        forcing OPENCV gave worse rotations (1.03 against 0.32 degrees); 0.14 px with decentring
        (p1 0.01, p2 -0.01), where its k1, k2, p1, p2 came out within 0.021 of the truth."""
        errors = {self.model: float(recon.compute_mean_reprojection_error())}
        asked = self.config.camera_model
        if asked == self.model:
            return recon, _ModelChoice(f"{asked} asked for", errors, None)
        if asked != "auto":  # RADIAL or OPENCV: refined from the SIMPLE_RADIAL the mapper fitted
            recon = self._refined_as(recon, asked)
            errors[asked] = float(recon.compute_mean_reprojection_error())
            return recon, _ModelChoice(f"{asked} asked for (mapped as {self.model}, then refined)", errors, None)
        pycolmap = self.pycolmap
        radial = {}
        for camera_id, camera in recon.cameras.items():
            radial[camera_id] = pycolmap.Camera.create_from_model_name(
                camera_id, "SIMPLE_RADIAL", 1.0, camera.width, camera.height
            )
            radial[camera_id].params = camera.params
        trial = self._refined_as(recon, "OPENCV")
        errors["OPENCV"] = float(trial.compute_mean_reprojection_error())
        difference = max(_lens_difference(radial[i], c) for i, c in trial.cameras.items())
        excess = math.sqrt(max(errors["SIMPLE_RADIAL"] ** 2 - errors["OPENCV"] ** 2, 0.0))
        bogus = any(c.has_bogus_params(0.1, 10.0, 1.0) for c in trial.cameras.values())
        measured = (
            f"OPENCV's reprojection error {errors['OPENCV']:.3f} px against SIMPLE_RADIAL's "
            f"{errors['SIMPLE_RADIAL']:.3f} px explains {excess:.3f} px more"
        )
        threshold = self.config.opencv_min_excess
        if excess >= threshold and not bogus:
            return trial, _ModelChoice(f"auto: {measured}, at least {threshold:g} px", errors, difference, excess)
        why = "but its parameters are implausible" if bogus else f"less than the {threshold:g} px it must"
        return recon, _ModelChoice(f"auto: {measured}, {why}", errors, difference, excess)

    def _refined_as(self, recon, model: str):
        """A copy of a SIMPLE_RADIAL reconstruction with its cameras turned into `model` (RADIAL: k1 = k,
        k2 = 0; OPENCV: fx = fy = f, k1 = k, the rest 0: the same lens) and one more bundle adjustment,
        with the focal rule of the last."""
        pycolmap = self.pycolmap
        out = pycolmap.Reconstruction(recon)
        for camera in out.cameras.values():
            f, cx, cy, k = (float(v) for v in camera.params)
            camera.model = getattr(pycolmap.CameraModelId, model)
            camera.params = [f, cx, cy, k, 0.0] if model == "RADIAL" else [f, f, cx, cy, k, 0.0, 0.0, 0.0]
        self._bundle_adjust(out, refine_focal=self.refine_focal)
        return out


@dataclass
class _ModelChoice:
    reason: str  # in words, for the summary
    errors: dict[str, float]  # mean reprojection error (px) per model fitted
    difference_px: float | None  # auto: SIMPLE_RADIAL's and OPENCV's lenses, farthest apart over the image
    excess_px: float | None = None  # auto: the error SIMPLE_RADIAL leaves that OPENCV explains (in quadrature)


def _lens_difference(a, b, samples: int = 17) -> float:
    """Largest distance in pixels between where lenses a and b put one ray, over a grid of the image
    (corners included): a's pixel -> a's ray -> b's pixel. Pixels a strong barrel distortion cannot
    invert (COLMAP's iterative undistortion returns NaN beyond the radial map's turning point) are
    left out."""
    u = np.linspace(0.0, a.width, samples)
    v = np.linspace(0.0, a.height, samples)
    pixels = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
    rays = np.concatenate([a.cam_from_img(pixels), np.ones((len(pixels), 1))], 1)
    distance = np.linalg.norm(b.img_from_cam(rays) - pixels, axis=1)
    finite = np.isfinite(distance)
    return float(distance[finite].max()) if finite.any() else float("nan")


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
    """(c2w [R, 4, 4] float64, K [R, 3, 3], registered names, per-view point depths, each view's fitted
    lens, each view's pinhole its photo is undistorted to) in input order. Each K is its view's pinhole's
    (the lens's own for the pinhole models and for a distortion that came out exactly zero); views of one
    size share their camera's lens."""
    registered = [n for n in names if ids[n] in recon.images and recon.images[ids[n]].has_pose]
    by_camera: dict[int, tuple[Lens, Lens]] = {}
    lenses, pinholes = [], []
    for name in registered:
        camera_id = recon.images[ids[name]].camera_id
        if camera_id not in by_camera:
            by_camera[camera_id] = _lens_and_pinhole(recon.cameras[camera_id])
        lenses.append(by_camera[camera_id][0])
        pinholes.append(by_camera[camera_id][1])
    K = torch.stack([p.intrinsics() for p in pinholes])
    w2c = np.tile(np.eye(4), (len(registered), 1, 1))
    for k, name in enumerate(registered):
        w2c[k, :3, :4] = recon.images[ids[name]].cam_from_world().matrix()
    c2w = np.linalg.inv(w2c)
    xyz = np.array([p.xyz for p in recon.points3D.values()]).reshape(-1, 3)
    depths = [(xyz @ w[:3, :3].T + w[:3, 3])[:, 2] for w in w2c]
    return torch.from_numpy(c2w), K, registered, depths, lenses, pinholes


def _lens_and_pinhole(camera) -> tuple[Lens, Lens]:
    """A pycolmap camera as the fitted Lens and the PINHOLE its photos are undistorted to."""
    from ..geometry.lens import undistorted_pinhole

    lens = Lens(camera.model.name, int(camera.width), int(camera.height), tuple(float(v) for v in camera.params))
    if not lens.is_pinhole:
        return lens, undistorted_pinhole(lens)
    M = camera.calibration_matrix()
    params = tuple(float(M[i, j]) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))
    return lens, Lens("PINHOLE", lens.width, lens.height, params)


def _normalize(c2w: torch.Tensor, depths: list[np.ndarray], median_depth: float):
    """World = the first camera; lengths scaled so the median depth of the points it sees is `median_depth`."""
    first = c2w[0]
    c2w = torch.linalg.inv(first)[None] @ c2w
    seen = depths[0][depths[0] > 0]
    if len(seen) == 0:
        raise SurfSplatInputError("no triangulated point lies in front of the first camera")
    scale = median_depth / float(np.median(seen))
    c2w[:, :3, 3] *= scale
    return c2w, [d * scale for d in depths], scale


def _write_colmap_model(recon, ids: dict[str, int], folder: Path, new_from_old: np.ndarray) -> None:
    """The reconstruction as a COLMAP model in `folder`: in the returned cameras' world (the similarity
    new_from_old, 3x4: scale times the first camera's world-to-camera) and with the user's image names."""
    import pycolmap

    model = pycolmap.Reconstruction(recon)
    model.transform(pycolmap.Sim3d(new_from_old))
    for name, image_id in ids.items():
        if image_id in model.images:
            model.images[image_id].name = name
    folder.mkdir(parents=True, exist_ok=True)
    model.write(folder)


def _depth_range(depths: list[np.ndarray], config: PoseConfig) -> tuple[float, float]:
    every = np.concatenate([d[d > 0] for d in depths])
    near = float(np.percentile(every, 2)) / config.depth_margin
    far = float(np.percentile(every, 98)) * config.depth_margin
    near = config.near if config.near is not None else near
    far = config.far if config.far is not None else far
    if not near < far:
        raise SurfSplatInputError(f"--near/--far: expected near < far, got {near:.4g}, {far:.4g}")
    return near, far
