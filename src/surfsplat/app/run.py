"""One run of the app, without the page: uploads -> `surfsplat.reconstruct` -> `Scene.save` -> what the
page shows (the baked 3DGS PLY, an x1/x4 render grid, the closure figures, the camera plot, the
fly-through, the downloads and a zip of the whole folder).

    result = run_capture(uploads, RunSettings(working_size=128), out_dir, report=print)

Progress follows the library's own stages: `surfsplat.utils.log.listen_progress` reports every progress
loop of the run (forward passes, refinement, the viewer bake, the renders of the export), and
`StageTracker` turns them into one fraction and a line naming the stage; the stages without a loop
(cameras, closure figures, mesh) are announced around them.

A shared server's limits: `RunSettings.max_seconds` is checked by the tracker at every one of those
steps and stages (a run past it raises RunOverTime; the page keeps nothing of it), and
`RunSettings.max_views` caps a video's frames (photos are counted before the run, in `prepare_uploads`).
What the page shows of a run (its lines, the library's warnings logged while it ran) and the text files of
its downloads pass through `PathScrubber`: no server folder in them.
"""

from __future__ import annotations

import json
import logging
import shutil
import threading
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

from ..capture.optimize import OptimizeConfig
from ..capture.refine import RefineConfig
from ..capture.video import FrameConfig
from ..utils.checks import SurfSplatInputError
from .files import PathScrubber, Uploads

logger = logging.getLogger(__name__)

DEMO_MODEL = "tiny-synthetic"
DEMO_NOTE = (
    "**tiny-synthetic** is the small demo model shipped with the package: trained for about seven CPU hours "
    "on procedural rooms at 64x64 pixels, never on photographs. On real photos expect the right layout and "
    "colours with soft, approximate geometry; it shows the whole flow, not the paper's quality. The released "
    "SurfSplat weights (RealEstate10K, 256 px) are what to use for real scenes."
)

# (what the page calls the stage, the library's progress loop that runs it or None, share of the bar at its end)
STAGES: tuple[tuple[str, str | None, float], ...] = (
    ("cameras", None, 0.10),
    ("network passes and fusion", "forward passes", 0.25),
    ("refinement", "refine", 0.40),
    ("per-scene optimization", "optimize", 0.44),
    ("closure figures", None, 0.48),
    ("export: baking the 3DGS PLY", "bake for 3DGS viewers", 0.68),
    ("export: renders", "render context views", 0.72),
    ("export: fly-through", "render camera path", 0.80),
    ("export: turntable", "render turntable", 0.88),
    ("export: mesh", None, 0.96),
    ("x4 renders and zip", None, 1.0),
)


class RunCancelled(Exception):
    """The person pressed Stop: the run ends at its next progress step."""


class RunOverTime(RunCancelled):
    """The run went past the server's limit on a run's seconds (`RunSettings.max_seconds`)."""

    def __init__(self, limit: float, stage: str) -> None:
        super().__init__(f"the run went past this server's limit of {limit:g} s for one run (during {stage})")
        self.limit = limit
        self.stage = stage


APP_OPTIMIZE_SECONDS = 60.0  # the page's default optimization budget: a web visitor waits a minute, not ten


@dataclass(frozen=True)
class RunSettings:
    """What the page lets a person choose, and the export the app writes."""

    weights: str = DEMO_MODEL  # a registry name (`surfsplat weights list`)
    working_size: int = 256  # long side of the network's input in pixels (`max_working_size`)
    refine_fits: float = RefineConfig.fits_per_view  # refinement of a fused scene: fits of each context view (0: none)
    # per-scene optimization of every surfel, a time budget in seconds (0: none; it runs where there are
    # more than two context views, as reconstruct's default)
    optimize_seconds: float = APP_OPTIMIZE_SECONDS
    device: str = "auto"
    path_frames: int = 48  # frames of the fly-through (the interpolated camera path)
    turntable_frames: int = 48
    mesh_resolution: int = 128  # TSDF voxels along the longest side
    bake_steps: int | None = None  # fitting steps of the 3DGS PLY (None: BakeConfig.steps_for the views)
    zoom: int = 4  # the grid's second row renders at this factor
    # a shared server's limits: a video's frames used at most (photos are counted by `prepare_uploads`), and
    # the seconds of one run, checked at every progress step of every stage (None: no limit)
    max_views: int | None = None
    max_seconds: float | None = None

    def __post_init__(self) -> None:
        if isinstance(self.working_size, bool) or not 16 <= self.working_size <= 2048:
            raise SurfSplatInputError(f"working size: expected 16 to 2048 pixels, got {self.working_size}")
        if not 0 <= self.refine_fits <= 1_000:
            raise SurfSplatInputError(f"refinement fits per view: expected 0 to 1000, got {self.refine_fits}")
        if isinstance(self.optimize_seconds, bool) or not 0 <= self.optimize_seconds <= 3_600:
            raise SurfSplatInputError(f"optimization seconds: expected 0 to 3600, got {self.optimize_seconds}")
        if self.max_views is not None and (isinstance(self.max_views, bool) or self.max_views < 2):
            raise SurfSplatInputError(f"max views: expected at least 2, got {self.max_views}")
        if self.max_seconds is not None and not self.max_seconds > 0:
            raise SurfSplatInputError(f"max seconds: expected a positive time, got {self.max_seconds}")
        if self.max_seconds is not None and self.optimize_seconds >= self.max_seconds:
            raise SurfSplatInputError(
                f"optimization seconds: {self.optimize_seconds:g} is not under this server's limit of "
                f"{self.max_seconds:g} s for a whole run; choose fewer"
            )


@dataclass
class RunResult:
    """What the page shows; every path inside the run's folder."""

    out: Path  # the output folder (Scene.save)
    viewer_ply: Path  # surfels_3dgs.ply, baked for 3DGS viewers
    view_ply: Path  # its copy placed for the page's 3D view (`surfsplat.app.view`)
    downloads: list[Path]  # both PLYs, the mesh, the cameras, the zip
    grid: Path  # colour, depth, normal at x1 (top) and x`zoom` (bottom)
    camera_plot: Path  # the context cameras from above (SVG)
    video: Path | None  # the fly-through
    summary: dict  # reconstruction.json
    seconds: float
    lines: list[str] = field(default_factory=list)  # what happened, one line each


class StageTracker:
    """A listener for `surfsplat.utils.log.listen_progress` that reports (fraction, text) to `report` as
    the run goes through STAGES, raises RunCancelled once `cancelled()` says so, and RunOverTime at the
    first step or stage after `max_seconds` (on `clock`) have passed since it was made."""

    def __init__(
        self,
        report: Callable[[float, str], None],
        cancelled: Callable[[], bool] = lambda: False,
        max_seconds: float | None = None,
        clock: Callable[[], float] = time.perf_counter,
    ):
        self.report = report
        self.cancelled = cancelled
        self.index = 0
        self.loops = {loop: i for i, (_, loop, _) in enumerate(STAGES) if loop is not None}
        self.max_seconds = max_seconds
        self.clock = clock
        self.start = clock()

    def enter(self, label: str) -> None:
        """Announce a stage without a progress loop (by its label in STAGES)."""
        self._check()
        self.index = next(i for i, (name, _, _) in enumerate(STAGES) if name == label)
        self.report(self._start(self.index), label)

    def __call__(self, desc: str, done: float, total: float | None) -> None:
        self._check()
        i = self.loops.get(desc)
        if i is None:  # a loop inside a stage (none at present): it counts for the stage it is in
            return
        self.index = i
        start, end = self._start(i), STAGES[i][2]
        share = min(1.0, done / total) if total else 0.0
        self.report(start + (end - start) * share, f"{STAGES[i][0]}: {done:g}/{total:g}" if total else STAGES[i][0])
        if total and done >= total and i + 1 < len(STAGES) and STAGES[i + 1][1] is None:
            self.enter(STAGES[i + 1][0])  # e.g. the mesh follows the turntable without a loop of its own

    @staticmethod
    def _start(i: int) -> float:
        return STAGES[i - 1][2] if i > 0 else 0.0

    def _check(self) -> None:
        if self.cancelled():
            raise RunCancelled("stopped")
        if self.max_seconds is not None and self.clock() - self.start > self.max_seconds:
            raise RunOverTime(self.max_seconds, STAGES[self.index][0])


def weights_choices() -> list[tuple[str, str]]:
    """(label, name) of every whole-network weights name: released weights already in the cache
    first, then the shipped demo model, then released weights that would be downloaded (with
    their licence)."""
    from ..model.pretrained import cached_file
    from ..model.registry import REGISTRY

    cached, download = [], []
    for entry in REGISTRY.values():
        if entry.role != "model" or entry.name == DEMO_MODEL:
            continue
        if cached_file(entry) is not None:
            cached.append((f"{entry.name} (released, in the cache; {entry.licence})", entry.name))
        else:
            download.append((f"{entry.name} (released, downloads on first use; {entry.licence})", entry.name))
    demo = REGISTRY[DEMO_MODEL]
    shipped = [(f"{demo.name} (shipped demo model: procedural rooms at 64 px)", demo.name)]
    return cached + shipped + download


def weights_note(name: str) -> str:
    """What the page says about the chosen weights (Markdown)."""
    from ..model.pretrained import cached_file
    from ..model.registry import lookup

    entry = lookup(name)
    if entry.name == DEMO_MODEL:
        return DEMO_NOTE
    size = "x".join(map(str, entry.resolution)) if entry.resolution else "?"
    where = (
        "in this server's cache"
        if cached_file(entry) is not None
        else f"not in this server's cache: the first run downloads it from `{entry.source.describe()}`"
    )
    return f"**{entry.name}**: {entry.description}; trained at {size} (HxW); {where}. Licence: {entry.licence}."


def run_capture(
    uploads: Uploads,
    settings: RunSettings,
    out_dir: str | Path,
    report: Callable[[float, str], None] = lambda fraction, text: None,
    cancelled: Callable[[], bool] = lambda: False,
) -> RunResult:
    """Reconstruct the uploads with `surfsplat.reconstruct`, save everything with `Scene.save` into
    `out_dir`, and add the page's grid, camera plot and zip. Bad input raises SurfSplatInputError
    (the library's one line); `cancelled()` turning true raises RunCancelled at the next step."""
    from ..capture import RefineConfig
    from ..export.bake import BakeConfig
    from ..export.flow import ExportOptions
    from ..reconstruction import CaptureOptions, reconstruct
    from ..utils.log import listen_progress
    from .view import write_view_ply

    start = time.perf_counter()
    out = Path(out_dir)
    tracker = StageTracker(report, cancelled, settings.max_seconds)
    capture = CaptureOptions(
        frames=FrameConfig(max_frames=settings.max_views),
        refine=replace(RefineConfig(), fits_per_view=settings.refine_fits),
        optimize=replace(OptimizeConfig(), steps=0)
        if settings.optimize_seconds == 0
        else replace(OptimizeConfig(), seconds=settings.optimize_seconds),
    )
    scrub = PathScrubber(uploads.folder.parent)
    with listen_progress(tracker), _warnings() as warned:
        tracker.enter("cameras")
        scene = reconstruct(
            uploads.capture,
            checkpoint=settings.weights,
            cameras=uploads.cameras,  # None: estimated; a processed capture: its own folder
            device=settings.device,
            max_working_size=settings.working_size,
            capture=capture,
            progress=False,
        )
        tracker.enter("closure figures")
        options = ExportOptions(
            path_frames=settings.path_frames,
            turntable_frames=settings.turntable_frames,
            mesh_resolution=settings.mesh_resolution,
            mode=scene.mode,
            alpha_threshold=scene.alpha_threshold,
            antialiased=scene.antialiased,
            progress=False,
            bake=replace(BakeConfig(), steps=settings.bake_steps),
        )
        written = scene.save(out, options=options)
        tracker.enter("x4 renders and zip")
        view = write_view_ply(out / "surfels_3dgs.ply", out / "app" / "view.ply", scene.cameras.c2w[0])
        grid = write_grid(scene, out / "app" / "grid.png", settings.zoom)
        plot = write_camera_plot(scene, out / "app" / "cameras.svg")
        scrub_text_files(out, scrub)
        tracker.enter("x4 renders and zip")  # the limit once more before the result is kept
        archive = Path(shutil.make_archive(str(out.parent / "surfsplat_result"), "zip", root_dir=out))
    summary = json.loads(written["summary"].read_text())
    report(1.0, "done")
    seconds = time.perf_counter() - start
    notes = [scrub(line) for line in [*uploads.notes, *(f"warning: {m}" for m in warned)]]
    downloads = [out / "surfels_3dgs.ply", out / "surfels.ply", out / "mesh.ply", out / "cameras.json", archive]
    return RunResult(
        out=out,
        viewer_ply=out / "surfels_3dgs.ply",
        view_ply=view,
        downloads=[p for p in downloads if p.is_file()],
        grid=grid,
        camera_plot=plot,
        video=out / "path.mp4" if (out / "path.mp4").is_file() else None,
        summary=summary,
        seconds=seconds,
        lines=[scrub(line) for line in summary_lines(scene, summary, seconds)] + notes,
    )


class _Collect(logging.Handler):
    """The package's warnings logged by this thread (the run's), for the page."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.thread = threading.get_ident()
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.thread == self.thread:
            self.messages.append(record.getMessage().strip().splitlines()[0] if record.getMessage().strip() else "")


@contextmanager
def _warnings():
    """Collect the package's warnings while the run goes (shown on the page, paths scrubbed)."""
    from ..utils.log import ROOT

    handler = _Collect()
    package = logging.getLogger(ROOT)
    package.addHandler(handler)
    try:
        yield handler.messages
    finally:
        package.removeHandler(handler)


TEXT_SUFFIXES = (".json", ".html", ".txt", ".md", ".svg", ".csv")  # outputs that may quote an input's path


def scrub_text_files(folder: Path, scrub: Callable[[str], str]) -> None:
    """Rewrite the text outputs of `folder` (reconstruction.json's sources, the pose report) without the
    server's folders: the downloads name the uploads by their own names."""
    for path in sorted(folder.rglob("*")):
        if path.is_file() and path.suffix.lower() in TEXT_SUFFIXES:
            text = path.read_text(encoding="utf-8", errors="surrogateescape")
            clean = scrub(text)
            if clean != text:
                path.write_text(clean, encoding="utf-8", errors="surrogateescape")


def write_grid(scene, path: Path, zoom: int) -> Path:
    """Colour, depth and normals of the first context view at x1 (top row) and x`zoom` (bottom),
    the x1 row enlarged with nearest neighbours so its pixels stay visible beside the x`zoom` render."""
    from ..export.figures import image_grid
    from ..export.images import colorize_depth, normal_to_rgb, write_png

    tau = scene.alpha_threshold if scene.alpha_threshold is not None else 0.5
    rows = []
    for scale in (1, zoom):
        r = scene.render(scene.cameras[0:1], scale=scale)
        shown = (r.alpha[0] >= tau).float()
        rows.append([r.color[0].clamp(0, 1), colorize_depth(r.depth[0], shown), normal_to_rgb(r.normal[0])])
    return write_png(path, image_grid(rows, size=tuple(rows[1][0].shape[1:]), padding=4))


def write_camera_plot(scene, path: Path) -> Path:
    """The context cameras seen from above (the plot of the capture report), as an SVG file."""
    from ..data.cameras import CameraSet
    from ..export.figures import write_text
    from ..poses.report import top_view_svg

    cameras = CameraSet(scene.cameras, scene.width, scene.height, list(scene.names))
    return write_text(path, top_view_svg(cameras))


def summary_lines(scene, summary: dict, seconds: float) -> list[str]:
    """The run in a few lines for the page."""
    lines = [
        f"{summary['surfels']:,} surfels from {len(scene.names)} views at {scene.width}x{scene.height} "
        f"({summary['model']}), {seconds:.0f} s in all",
        f"cameras: {summary['cameras']}",
    ]
    if scene.video is not None:
        lines.append(f"video: {len(scene.video.frames)} frames used of {len(scene.video.records)}")
    return lines


def closure_table(closure: dict) -> str:
    """The closure figures of reconstruction.json as a Markdown table."""
    mean = closure.get("mean_alpha", {})
    cover = closure.get("coverage", {})
    rows = [
        "| factor | mean alpha | alpha >= 0.5 | alpha >= 0.9 |",
        "|---|---|---|---|",
    ]
    for key in sorted(mean, key=lambda k: int(k.lstrip("x"))):
        c = cover.get(key, {})
        rows.append(f"| {key} | {mean[key]:.3f} | {c.get('alpha>=0.5', 0):.1%} | {c.get('alpha>=0.9', 0):.1%} |")
    value = closure.get("closure")
    verdict = "closed" if closure.get("closed") else "not closed: " + "; ".join(closure.get("problems", []))
    head = f"**Closure** {value:.3f} (alpha x4 / x1), {verdict}" if value is not None else f"**Closure**: {verdict}"
    tail = (
        f"{closure.get('undersized_share', 0):.1%} of surfels under half their pixel footprint; "
        f"median opacity {closure.get('opacity_quantiles', {}).get('p50', float('nan')):.2f}"
    )
    return "\n".join([head, "", *rows, "", tail])
