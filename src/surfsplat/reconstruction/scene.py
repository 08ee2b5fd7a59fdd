"""`Scene`: what `surfsplat.reconstruct` returns - the surfels, their context cameras, and how they came about.

scene.render()                       # RenderOutput at the context cameras
scene.render(cameras, scale=4)       # any cameras (K in pixels of width x height), 4x the resolution
scene.save("out/")                   # {what: path}: PLY, renders, videos, mesh, reconstruction.json, ...
scene.to("cuda")                     # the scene on another device: rendering and saving run there

A scene's tensors live on the device `reconstruct` ran on; every method computes there, and only
the files written (and the figures printed) reach the host.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
from torch import Tensor

from ..geometry.cameras import Cameras
from ..geometry.gaussians import Gaussians
from ..render.supersample import ZoomPlan, zoom_plan
from ..utils.checks import SurfSplatInputError


@dataclass
class HeldOut:
    """Views of the capture kept out of every forward pass, to see the scene from where no context view was."""

    names: list[str]
    cameras: Cameras  # K in pixels of the scene's width x height
    images: Tensor  # [H, 3, height, width] the photos at the network's size
    psnr: list[float] = field(default_factory=list)  # per view, of the scene's render (forced alpha blending)
    coverage: list[float] = field(default_factory=list)  # share of pixels with alpha >= 0.5
    ssim: list[float] = field(default_factory=list)  # per view, scikit-image's published call
    lpips: list[float] | None = None  # per view, LPIPS-VGG (None: its weights are unavailable, see lpips_note)
    lpips_note: str | None = None  # "LPIPS unavailable: <reason>" when it could not be computed
    before: dict | None = None  # the figures above before the per-scene optimization (None: not optimized)
    before_renders: Tensor | None = None  # [H, 3, height, width] the renders before the optimization
    sources: list = field(default_factory=list)  # the photos' files (paths; empty for arrays), to score them again
    # how a render is scored against its photo: "plain" (the whole photo as it is), or "exposure" (3DGS's
    # train_test_exp, for scenes fitted with per-photo exposure: each view's affine colour map fitted on
    # the photo's left half, the figures taken on the right half; capture/per_view.py)
    protocol: str = "plain"
    # with refined context cameras: how far test-time alignment moved each held-out camera (degrees, units)
    alignment: dict | None = None
    zoom: dict | None = None  # `metrics.zoom` scores of the optimized scene (None: not measured)

    def scores(self) -> dict:
        """Per-view and mean PSNR, SSIM, LPIPS and coverage."""

        def mean(values: list[float] | None) -> float | None:
            return sum(values) / len(values) if values else None

        return {
            "psnr": self.psnr,
            "ssim": self.ssim,
            "lpips": self.lpips,
            "coverage": self.coverage,
            "mean_psnr": mean(self.psnr),
            "mean_ssim": mean(self.ssim),
            "mean_lpips": mean(self.lpips),
            "mean_coverage": mean(self.coverage),
        }

    def to_dict(self) -> dict:
        out = {"names": self.names, **self.scores(), "protocol": self.protocol}
        if self.alignment is not None:
            out["camera_alignment"] = self.alignment
        if self.sources:
            out["sources"] = [str(s) for s in self.sources]
        if self.lpips_note is not None:
            out["lpips_note"] = self.lpips_note
        if self.before is not None:
            out["before_optimization"] = self.before
        if self.zoom is not None:
            out["zoom"] = self.zoom
        return out

    def score(self, out) -> None:
        """Fill the figures from the scene's RenderOutput at these cameras."""
        from ..metrics import psnr, ssim

        color = out.color.clamp(0, 1)
        truth = self.images.to(color)
        alpha = out.alpha
        if self.protocol == "exposure":
            from ..capture.per_view import exposure_protocol

            exposed, _ = exposure_protocol(out.color, truth)
            half = color.shape[-1] // 2
            color, truth, alpha = exposed[..., half:].clamp(0, 1), truth[..., half:], alpha[..., half:]
        elif self.protocol != "plain":
            raise SurfSplatInputError(f"held-out protocol: expected 'plain' or 'exposure', got {self.protocol!r}")
        views = range(len(self.names))
        # computed where the scene is and read back once (each read makes a GPU host wait)
        scores = torch.stack(
            [
                torch.cat([psnr(color[i : i + 1], truth[i : i + 1]) for i in views]),
                (alpha >= 0.5).float().mean(dim=(1, 2, 3)),
                torch.stack([ssim(color[i : i + 1].double(), truth[i : i + 1].double()).reshape(()) for i in views]).to(
                    color.dtype
                ),
            ]
        )
        self.psnr, self.coverage, self.ssim = scores.tolist()
        model = _lpips(color.device)
        if isinstance(model, str):
            self.lpips, self.lpips_note = None, model
        else:
            with torch.no_grad():
                self.lpips = [float(model(color[i : i + 1], truth[i : i + 1])) for i in range(len(self.names))]


def _lpips(device: torch.device):
    """LPIPS-VGG on `device`, or "LPIPS unavailable: <reason>"; loaded once per device."""
    from ..metrics.lpips import LpipsUnavailable, try_load_lpips

    key = str(device)
    if key not in _LPIPS:
        found = try_load_lpips(device=device)
        _LPIPS[key] = str(found) if isinstance(found, LpipsUnavailable) else found
    return _LPIPS[key]


_LPIPS: dict = {}  # device -> the loaded LPIPS model or why it is unavailable


# Written beside the export's files; reconstruction.json last, so it marks a finished run.
SUMMARY_FILES = ("estimated_cameras.json", "poses.json", "report.html", "reconstruction.json")


@dataclass
class Scene:
    """One reconstruction: fused surfels and the cameras of the views they came from."""

    gaussians: Gaussians  # [N] unbatched, world frame
    cameras: Cameras  # the context cameras, K in pixels of width x height
    width: int
    height: int
    names: list[str]  # one per context camera (video frames: frame_000012, ...)
    near: float
    far: float
    mode: str  # rasterization the model's surfels are drawn with ("surfel" or "ewa")
    alpha_threshold: float | None  # forced alpha blending tau of the model (None: off)
    model: str  # label of the network
    checkpoint: str
    sources: list[str]  # what each context view came from (a file, an array, a video's frame)
    cameras_source: str  # where the cameras came from
    passes: list[list[str]]  # the context views of each forward pass
    seconds: dict[str, float] = field(default_factory=dict)  # poses, forward (all passes), fusion, total
    compact_level: int | None = None
    compact_stats: dict[str, int] = field(default_factory=dict)  # summed over passes
    fusion_stats: dict[str, int] = field(
        default_factory=dict
    )  # passes, predicted, duplicates, replaced (empty: one pass)
    refine_stats: dict[str, float] = field(default_factory=dict)  # steps, mse_before/after, kept (empty: none)
    optimize_stats: dict[str, float] = field(default_factory=dict)  # the per-scene optimization's (empty: none)
    poses: object | None = None  # PoseSummary when the cameras were estimated
    pose_cameras: object | None = None  # their CameraSet (K in pixels of the photos)
    photos: list = field(default_factory=list)  # every photo given to pose estimation (path or uint8 array)
    video: object | None = None  # VideoFrames when the capture was a video
    holdout: HeldOut | None = None
    precision: str = "fp32"  # what the forward passes ran in (surfels and rendering are float32)
    scale_multipliers: Tensor | None = None  # [N, 2] Eq. 9 multipliers (one uncompacted pass only)
    multiplier_range: float | None = None  # the clamp's r of those multipliers
    # "ran", or "skipped (why)" where no forward pass ran (the optimizer started from COLMAP's points:
    # then `model` is "", `passes` empty, `precision` "none", `mode` "surfel", and the surfels before the
    # optimization, which the held-out views' `before` figures score, are that start)
    network: str = "ran"
    # (width, height) of the photos the working crop was taken from (after undistortion; None: unknown)
    source_size: tuple[int, int] | None = None
    # each view's source lens by name, context and held-out (None: the photos were pinhole); the
    # photos were undistorted to `pinhole_of(lens)` before the working crop
    lenses: dict | None = None

    def lens_lines(self) -> list[str]:
        """One line per distinct source lens: its model and parameters, the pinhole its photos were
        undistorted to, and the working crop of that."""
        lines = []
        for group in self.lens_summary() or []:
            source, pinhole = group["source"], group["pinhole"]
            from ..geometry.lens import Lens

            if Lens.from_dict(source).is_pinhole:  # photos read as they are
                continue
            names = Lens.from_dict(source).param_names
            params = ", ".join(f"{n} {v:.6g}" for n, v in zip(names, source["params"]))
            fx, fy, cx, cy = pinhole["params"]
            turn = source.get("orientation", 1)
            stored = f" (the stored pixels of photos turned by EXIF orientation {turn})" if turn != 1 else ""
            lines.append(
                f"lens {source['model']} ({params}) at {source['width']}x{source['height']}{stored}, "
                f"{len(group['views'])} "
                f"view{'s' if len(group['views']) > 1 else ''}: photos undistorted to a {pinhole['width']}x"
                f"{pinhole['height']} pinhole (fx {fx:.6g}, fy {fy:.6g}, cx {cx:.6g}, cy {cy:.6g}), "
                f"then rescaled and cropped to the {self.width}x{self.height} working size"
            )
        return lines

    @property
    def crop(self):
        """The WorkingCrop from the photos (after undistortion) to the scene's width x height, or None."""
        if self.source_size is None:
            return None
        from ..data.transforms import working_crop

        return working_crop(*self.source_size, (self.height, self.width))

    def view_lenses(self, names: list[str]) -> list | None:
        """The source lens of each named view (None where the scene has no lenses)."""
        return None if self.lenses is None else [self.lenses[n] for n in names]

    def lens_summary(self) -> list[dict] | None:
        """What reconstruction.json records of the lenses: each distinct source lens (COLMAP model and
        parameters), the pinhole its photos were undistorted to, and the views that had it."""
        if self.lenses is None:
            return None
        from ..data.cameras import pinhole_of

        groups: dict = {}
        for name, lens in self.lenses.items():
            groups.setdefault(lens, []).append(name)
        return [
            {"source": lens.to_dict(), "pinhole": pinhole_of(lens).to_dict(), "views": names}
            for lens, names in groups.items()
        ]

    antialiased: bool = False  # rendered with the antialiasing filter (a scene optimized with it)

    @property
    def device(self) -> torch.device:
        """Where the surfels are, and where rendering, the closure figures and saving compute."""
        return self.gaussians.means.device

    def to(self, device: str | torch.device) -> Scene:
        """The scene with its surfels, cameras, held-out views and multipliers on `device` (this one
        when they are there already; fields other than tensors are shared)."""
        device = torch.device(device)
        holdout = self.holdout
        if holdout is not None:
            holdout = replace(holdout, cameras=holdout.cameras.to(device), images=holdout.images.to(device))
        multipliers = self.scale_multipliers
        return replace(
            self,
            gaussians=self.gaussians.to(device),
            cameras=self.cameras.to(device),
            holdout=holdout,
            scale_multipliers=multipliers.to(device) if multipliers is not None else None,
        )

    def closure(self, factors: tuple[int, ...] = (1, 2, 4), max_views: int = 4):
        """ClosureMetrics (`surfsplat.metrics.closure`) from the context cameras (at most `max_views`,
        evenly spread): does the surface keep its alpha when rendered at each factor?"""
        from ..geometry.pixels import views_of_pixels
        from ..metrics.closure import closure_metrics

        n = len(self.cameras)
        # which views: a few integers, chosen on the host and sent once
        picked = torch.linspace(0, n - 1, min(n, max_views)).round().long().unique().to(self.cameras.device)
        one_per_pixel = self.scale_multipliers is not None and len(self.gaussians) == n * self.width * self.height
        return closure_metrics(
            self.gaussians,
            self.cameras[picked],
            self.width,
            self.height,
            factors,
            source_cameras=self.cameras,
            views=views_of_pixels(n, self.height, self.width, self.device) if one_per_pixel else None,
            multipliers=self.scale_multipliers if one_per_pixel else None,
            multiplier_range=self.multiplier_range if one_per_pixel else None,
            mode=self.mode,
        )

    def render(self, cameras: Cameras | None = None, scale: float = 1.0):
        """RenderOutput of the scene from `cameras` (default: the context cameras; K in pixels of
        width x height) at scale times the resolution, K scaled exactly."""

        if not (math.isfinite(scale) and scale > 0):
            raise SurfSplatInputError(f"scale: expected a positive factor, got {scale}")
        cams = self.cameras if cameras is None else cameras
        if not isinstance(cams, Cameras):
            raise SurfSplatInputError(f"cameras: expected surfsplat.Cameras, got {type(cams).__name__}")
        w, h = max(1, round(self.width * scale)), max(1, round(self.height * scale))
        return self._draw(cams.to(self.gaussians.means).scaled(scale), w, h)

    def _draw(self, cams: Cameras, width: int, height: int, supersample: bool = True):
        """RenderOutput from `cams` (on the surfels' device) at width x height, as the scene renders: its mode,
        forced-alpha threshold, antialiasing, at the fitted zoom whichever way the view is zoomed
        (`zoom_plan`: zoomed out supersampled, zoomed in with the fitted pixels' filter); `supersample=False`:
        drawn as asked."""
        from ..render import render

        plan = self.zoom_plan(cams, width, height) if supersample else ZoomPlan(self.gaussians)
        with torch.inference_mode():
            return render(
                plan.gaussians,
                cams,
                width,
                height,
                mode=self.mode,
                alpha_threshold=self.alpha_threshold,
                antialiased=self.antialiased,
                supersample=plan.supersample,
                filter_zoom=plan.filter_zoom,
            )

    def zoom_plan(self, cameras: Cameras, width: int, height: int) -> ZoomPlan:
        """How a render from `cameras` at width x height is drawn at the zoom the scene was fitted at
        (`surfsplat.render.supersample.zoom_plan`): zoomed out 1.5 x or more supersampled, zoomed in 1.5 x or
        more with the fitted pixels' filter; as asked otherwise, or where the scene records no fitted views."""
        return zoom_plan(self.gaussians, self.cameras, self.width, self.height, cameras, width, height)

    def supersampling(self, cameras: Cameras, width: int, height: int) -> int:
        """How many times finer than width x height a render from `cameras` is drawn and averaged down
        (`surfsplat.render.supersample`): 1 at the zoom the scene was made at, up to 4 for views whose
        pixels are that much larger on its surfaces (a smaller image, a camera moved back)."""
        from ..render.supersample import supersampling

        return supersampling(self.gaussians, self.cameras, self.width, self.height, cameras, width, height)

    def summary(self) -> dict:
        """reconstruction.json without the written files."""
        out = {
            "checkpoint": self.checkpoint,
            "model": self.model,
            "images": self.sources,
            "size": [self.height, self.width],
            "near": self.near,
            "far": self.far,
            "surfels": len(self.gaussians),
            "compact_level": self.compact_level,
            "seconds_forward": self.seconds.get("forward", 0.0),
            "render_mode": self.mode,
            "alpha_threshold": self.alpha_threshold,
            "antialiased": self.antialiased,
            "cameras": self.cameras_source,
            "precision": self.precision,
            "network": self.network,
        }
        if self.crop is not None:
            out["working_crop"] = self.crop.to_dict()
        if self.lenses is not None:
            out["lenses"] = self.lens_summary()
        if self.optimize_stats:
            out["optimize"] = self.optimize_stats
            if "versus_input" in self.optimize_stats:  # a saved scene optimized again: is it the better one?
                out["worse_than_input"] = bool(self.optimize_stats["versus_input"]["worse"])
        if self.is_capture:
            out["capture"] = self.capture_summary()
        return out

    def zoom_scores(
        self,
        cameras: Cameras | None = None,
        images: Tensor | None = None,
        supersample: bool = True,
        up: tuple[int, ...] = (2, 4),
    ):
        """`metrics.zoom.ZoomScores` of the scene from `cameras` against `images` (default: the held-out
        views), rendered as the scene renders (its mode, forced-alpha threshold and antialiasing, and the
        zoomed-out views supersampled, `supersampling`; `supersample=False`: the renders at the sizes asked)."""
        from ..metrics.zoom import zoom_scores

        if cameras is None:
            if self.holdout is None:
                raise SurfSplatInputError("zoom_scores: the scene has no held-out views; give cameras and images")
            cameras, images = self.holdout.cameras, self.holdout.images

        def draw(cams: Cameras, w: int, h: int):
            return self._draw(cams.to(self.gaussians.means), w, h, supersample)

        return zoom_scores(
            draw, cameras.to(self.gaussians.means), images.to(self.gaussians.means), self.width, self.height, up=up
        )

    def score_holdout(self):
        """Score the held-out views (PSNR, SSIM, LPIPS where available, coverage); their RenderOutput."""
        out = self.render(self.holdout.cameras)
        self.holdout.score(out)
        return out

    @property
    def is_capture(self) -> bool:
        """More than one forward pass (or none: the optimizer started from points), a video or held-out
        views: the capture outputs are written."""
        many = len(self.passes) > 1 or self.network != "ran"
        return many or self.video is not None or self.holdout is not None

    def capture_summary(self) -> dict:
        return {
            "views": len(self.names),
            "passes": self.passes,
            "fusion": self.fusion_stats,
            "refine": self.refine_stats,
            "optimize": self.optimize_stats,
            "compaction": self.compact_stats,
            "seconds": self.seconds,
            "held_out": self.holdout.to_dict() if self.holdout is not None else None,
            "video": self.video.to_dict() if self.video is not None else None,
        }

    def save(
        self,
        out_dir: str | Path,
        formats: tuple[str, ...] | None = None,
        options=None,  # surfsplat.export.flow.ExportOptions; default: `formats` with the model's rendering
    ) -> dict[str, Path]:
        """Write the reconstruction (see `export_reconstruction`), the cameras' report when they were
        estimated, the capture's report and reconstruction.json; returns {what: path}."""
        from ..export.figures import write_text
        from ..export.flow import FORMATS, ExportOptions, export_reconstruction, output_names
        from ..utils.checks import check_output_dir

        if options is None:
            options = ExportOptions(
                formats=tuple(formats) if formats is not None else FORMATS,
                mode=self.mode,
                alpha_threshold=self.alpha_threshold,
                antialiased=self.antialiased,
            )
        elif formats is not None:
            options = replace(options, formats=tuple(formats))
        out = check_output_dir(
            out_dir, "out_dir", inputs=self.input_files(), writes=[*output_names(options.formats), *SUMMARY_FILES]
        )
        tick = time.perf_counter()
        closure = self.closure()  # before any file is written: a failure here leaves nothing behind
        seconds = {"closure": time.perf_counter() - tick}
        written = export_reconstruction(
            self.gaussians,
            self.cameras,
            self.width,
            self.height,
            out,
            options,
            names=self.names,
            near=self.near,
            far=self.far,
            seconds=seconds,
            crop=self.crop,
            lenses=self.view_lenses(self.names),
        )
        tick = time.perf_counter()
        if self.poses is not None:
            written.update(self._pose_outputs(out, written))
        if self.is_capture:
            from .report import write_capture_outputs

            written.update(write_capture_outputs(self, out, options))
        seconds["reports"] = time.perf_counter() - tick
        summary = self.summary()
        summary["seconds"] = {**self.seconds, **{f"save: {k}": v for k, v in seconds.items()}}
        summary["closure"] = closure.to_json()
        summary["files"] = {k: str(v) for k, v in written.items()}
        written["summary"] = write_text(out / "reconstruction.json", json.dumps(summary, indent=1) + "\n")
        return written

    def input_files(self) -> list[Path]:
        """The files the scene was made from (images, a video), which saving must never overwrite."""
        out = [Path(p) for p in self.sources if isinstance(p, (str, Path)) and Path(p).exists()]
        if self.video is not None and getattr(self.video, "path", None) is not None:
            out.append(Path(self.video.path))
        return out

    def _pose_outputs(self, out: Path, written: dict[str, Path]) -> dict[str, Path]:
        from ..export.images import write_png
        from ..poses.report import write_pose_outputs

        photos = []
        for k, item in enumerate(self.photos):  # frames and arrays are written so the report can show them
            if isinstance(item, (str, Path)):
                photos.append(Path(item))
            else:
                image = torch.from_numpy(item).permute(2, 0, 1).float() / 255
                photos.append(write_png(out / "frames" / f"{self.poses.images[k]}.png", image))
        renders = None
        if "context renders" in written and list(self.pose_cameras.names) == list(self.names):
            renders = [out / "renders" / f"view{i:02d}_color.png" for i in range(len(self.names))]
        return write_pose_outputs(out, self.pose_cameras, self.poses, photos, renders)
