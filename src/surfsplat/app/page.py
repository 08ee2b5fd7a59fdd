"""The page (gradio Blocks): uploads and settings on the left, the result on the right.

One reconstruction runs at a time (the queue's `concurrency_limit=1`; waiting people see their
place in the queue); Stop cancels a waiting run and ends a running one at its next progress step.
Each run's files live in their own folder (`SessionFolders`), removed `keep_minutes` later, and
gradio's own copies of uploads and results are removed on the same schedule (`delete_cache`).

No `from __future__ import annotations` here: gradio finds the `gr.Request` parameter by its
annotation, which must be the class itself.
"""

import logging
import shutil
import threading
from pathlib import Path

from ..utils.atomic import OutputError
from ..utils.checks import SurfSplatInputError
from .config import AppConfig
from .files import PathScrubber, SessionFolders, prepare_uploads
from .run import RunCancelled, RunOverTime, RunSettings, closure_table, run_capture, weights_choices, weights_note

logger = logging.getLogger(__name__)

INTRO = """# SurfSplat: photos to a surface of 2D Gaussian surfels

Drop **two or more photos** of one scene (taken a step apart; portrait and landscape may mix), **one video**
filmed while moving around it, or **a processed capture**: a zip (or a folder) of photos with the `transforms.json`
of nerfstudio / instant-ngp or a COLMAP model (`sparse/0`). Cameras are estimated from the pictures unless a camera file
comes with them. The result is a 3D scene you can turn in the viewer below, renders at x1 and x4, and files
to download.
"""


def limits_text(config: AppConfig) -> str:
    """What the page says about this server's limits (Markdown)."""
    return (
        f"This server takes up to {config.max_upload_mb:g} MB of uploads and {config.max_views} views a run "
        f"(photos; a video's frames are chosen up to that many), and stops a run after {config.max_seconds:g} s; "
        f"files are removed {config.keep_minutes:g} minutes after a run."
    )


def run_request(
    config: AppConfig,
    sessions: SessionFolders,
    files,
    camera_file,
    capture_folder,
    weights: str,
    working_size: float,
    refine_fits: float,
    optimize_seconds: float,
    report=lambda fraction, text: None,
    cancelled=lambda: False,
) -> tuple:
    """One press of Start, without gradio: the uploads checked against the server's limits, the run, and
    what the page's outputs get (status, 3D view, grid, closure table, camera plot, video, downloads).
    Every message it returns is one line with the server's folders taken out; a refused, stopped or
    over-time run keeps nothing in the session's outputs."""
    folder = sessions.new()
    scrub = PathScrubber(folder, config.root())
    try:
        paths = [_upload_path(f) for f in files or []]
        camera_path = _upload_path(camera_file) if camera_file else None
        capture_paths = [_upload_path(f) for f in capture_folder or []]
        settings = RunSettings(
            weights=weights,
            working_size=int(working_size),
            refine_fits=float(refine_fits),
            optimize_seconds=float(optimize_seconds),
            device=config.device,
            max_views=config.max_views,
            max_seconds=config.max_seconds,
            **config.export,
        )
        uploads = prepare_uploads(
            paths,
            camera_path,
            folder,
            config.max_upload_bytes(),
            max_views=config.max_views,
            capture_files=capture_paths,
        )
        result = run_capture(uploads, settings, folder / "outputs", report, cancelled)
    except (SurfSplatInputError, FileNotFoundError, OutputError) as err:
        _discard(folder)
        return _failed(_one_line(err, scrub))
    except RunOverTime as err:
        _discard(folder)
        return _failed(
            f"{err}; nothing was kept. Send fewer photos, or choose a smaller working size or less optimization",
            head="**Stopped:**",
        )
    except RunCancelled:
        _discard(folder)
        return _failed("stopped before the end; nothing was kept", head="**Stopped**")
    except BaseException:  # anything else (gradio shows a bare error): still nothing half-written kept
        _discard(folder)
        raise
    finally:
        sessions.release(folder)
    status = "**Done.** " + "  \n".join(result.lines)
    return (
        status,
        str(result.view_ply),
        str(result.grid),
        closure_table(result.summary["closure"]),
        str(result.camera_plot),
        str(result.video) if result.video else None,
        [str(p) for p in result.downloads],
    )


def build(config: AppConfig | None = None, **overrides):
    """The app as a `gradio.Blocks`, queued (one reconstruction at a time), ready to `launch()` or
    to mount in another server (`gradio.mount_gradio_app`). Keyword arguments override `config`'s
    fields (e.g. `build(max_upload_mb=50)`)."""
    from dataclasses import replace

    gr = require_gradio()
    config = replace(config or AppConfig(), **overrides)
    sessions = SessionFolders(config.root(), config.keep_minutes * 60)
    stops: dict[str, threading.Event] = {}
    lock = threading.Lock()
    choices = weights_choices()
    keep = int(config.keep_minutes * 60)
    tracked = gr.Progress()  # gradio finds the bar by this default and hands each call its own

    def run(
        files,
        camera_file,
        capture_folder,
        weights,
        working_size,
        refine_fits,
        optimize_seconds,
        request: gr.Request,
        progress=tracked,
    ):
        key = _session_key(request)
        with lock:
            stop = stops.setdefault(key, threading.Event())
        stop.clear()
        return run_request(
            config,
            sessions,
            files,
            camera_file,
            capture_folder,
            weights,
            working_size,
            refine_fits,
            optimize_seconds,
            lambda f, text: progress(f, desc=text),
            stop.is_set,
        )

    def request_stop(request: gr.Request):
        with lock:
            event = stops.get(_session_key(request))
        if event is not None:
            event.set()
        return "**Stopping** at the next step..."

    with gr.Blocks(title="SurfSplat", delete_cache=(max(60, keep // 4), keep)) as demo:
        gr.Markdown(INTRO)
        with gr.Row():
            with gr.Column(scale=2, min_width=320):
                photos = gr.File(
                    label="Photos (two or more), one video, or a zip of a processed capture",
                    file_count="multiple",
                    elem_id="photos",
                    height=160,
                )
                capture_folder = gr.File(
                    label="Or a folder: photos with their transforms.json or COLMAP model",
                    file_count="directory",
                    elem_id="capture-folder",
                    height=160,
                )
                cameras = gr.File(label="Camera file (optional, JSON)", elem_id="cameras", height=120)
                weights = gr.Dropdown(choices=choices, value=choices[0][1], label="Weights", elem_id="weights")
                about = gr.Markdown(weights_note(choices[0][1]), elem_id="weights-note")
                working_size = gr.Slider(
                    64,
                    512,
                    value=config.working_size,
                    step=16,
                    label="Working size (long side, pixels)",
                    elem_id="working-size",
                )
                refine_fits = gr.Slider(
                    0,
                    60,
                    value=config.refine_fits,
                    step=1,
                    label="Refinement: fits of each photo (captures of more than one forward pass; 0: none)",
                    elem_id="refine-fits",
                )
                optimize_seconds = gr.Slider(
                    0,
                    _optimize_max(config),
                    value=min(config.optimize_seconds, _optimize_max(config)),
                    step=10,
                    label="Per-scene optimization: seconds fitting, growing and pruning the surfels on the photos "
                    "(three photos or more; 0: none; replaces the refinement)",
                    elem_id="optimize-seconds",
                )
                with gr.Row():
                    start = gr.Button("Start", variant="primary", elem_id="start")
                    stop = gr.Button("Stop", variant="stop", elem_id="stop")
            with gr.Column(scale=3):
                status = gr.Markdown(limits_text(config), elem_id="status")
                view = gr.Model3D(
                    label="3D view: the baked 3DGS PLY (drag to turn, scroll to zoom)",
                    elem_id="view3d",
                    height=420,
                )
                grid = gr.Image(
                    label="Colour, depth, normals: x1 (top) and x4 (bottom)",
                    type="filepath",
                    elem_id="grid",
                    height=300,
                )
                with gr.Row():
                    closure = gr.Markdown(elem_id="closure")
                    plot = gr.Image(label="Cameras from above", type="filepath", elem_id="camera-plot", height=220)
                video = gr.Video(label="Fly-through", elem_id="video", height=260)
                downloads = gr.File(
                    label="Downloads: 3DGS PLY, surfel PLY, mesh, cameras, everything (zip)",
                    file_count="multiple",
                    elem_id="downloads",
                )
        weights.change(weights_note, inputs=weights, outputs=about, queue=False)
        started = start.click(
            run,
            inputs=[photos, cameras, capture_folder, weights, working_size, refine_fits, optimize_seconds],
            outputs=[status, view, grid, closure, plot, video, downloads],
            concurrency_limit=1,
            concurrency_id="reconstruct",
        )
        stop.click(request_stop, outputs=status, cancels=[started], queue=False)
    demo.queue(default_concurrency_limit=1, max_size=config.max_queue)
    demo.surfsplat_sessions = sessions  # for `launch` (periodic cleanup) and tests
    return demo


def require_gradio():
    """The gradio module, or one line saying how to install it."""
    try:
        import gradio
    except ImportError:
        raise SurfSplatInputError('the app needs gradio: pip install "surfsplat[app]"') from None
    return gradio


def _session_key(request) -> str:
    return getattr(request, "session_hash", None) or "local"


def _upload_path(item) -> str:
    """The server-side file of an upload (gradio gives a path, or an object with `.name` / `.path`)."""
    if isinstance(item, (str, Path)):
        return str(item)
    for attribute in ("path", "name"):
        value = getattr(item, attribute, None)
        if isinstance(value, str):
            return value
    raise SurfSplatInputError(f"upload: expected a file, got {type(item).__name__}")


def _one_line(err: BaseException, scrub) -> str:
    """The error's first line, without the server's folders (the uploads' own names stay)."""
    lines = str(err).strip().splitlines()
    return scrub(lines[0] if lines else type(err).__name__)


def _discard(folder: Path) -> None:
    """Nothing half-written is kept or shown: the session's outputs and its zip go."""
    shutil.rmtree(folder / "outputs", ignore_errors=True)
    (folder / "surfsplat_result.zip").unlink(missing_ok=True)


def _optimize_max(config: AppConfig) -> float:
    """The optimization slider's top: 600 s, or half the server's limit for a whole run (the export
    after it needs its time too), in steps of 10 s."""
    return float(max(0, min(600, (config.max_seconds // 20) * 10)))


def _failed(message: str, head: str = "**Cannot reconstruct:**"):
    return f"{head} {message}", None, None, "", None, None, None
