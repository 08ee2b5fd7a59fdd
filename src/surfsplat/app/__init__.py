"""A browser app for the whole flow: photos, a video or a processed capture (a zip or folder of photos with
their transforms.json or COLMAP model) -> `surfsplat.reconstruct` -> the scene on a page.

    from surfsplat.app import AppConfig, build, launch
    demo = build(AppConfig(max_upload_mb=50, max_views=30))   # a gradio.Blocks: demo.launch(), or mount it
    launch(AppConfig(port=7860))                              # what `surfsplat app` runs

Needs the optional gradio dependency (`pip install "surfsplat[app]"`); without it `build` raises one
line saying so. `files` (uploads made safe, session folders, messages without server paths), `archive`
(zips and folder uploads unpacked safely), `run` (one run without the page) and `page.run_request`
(one press of Start, what the page gets) do not need gradio.
"""

from __future__ import annotations

import logging

from .config import AppConfig
from .files import PathScrubber, SessionFolders, Uploads, prepare_uploads, safe_name
from .page import build, require_gradio, run_request
from .run import RunOverTime, RunResult, RunSettings, run_capture

logger = logging.getLogger(__name__)

__all__ = [
    "AppConfig",
    "PathScrubber",
    "RunOverTime",
    "RunResult",
    "RunSettings",
    "SessionFolders",
    "Uploads",
    "build",
    "launch",
    "prepare_uploads",
    "require_gradio",
    "run_capture",
    "run_request",
    "safe_name",
]


def launch(config: AppConfig | None = None, *, block: bool = True, share: bool = False):
    """Serve the app (`build(config)`) at config.host:config.port; returns the Blocks (serving in
    the background when `block` is False). A host other than this machine's loopback is logged as
    a warning: anyone who can reach it can run reconstructions and read what they made."""
    config = config or AppConfig()
    if not config.local_only:
        logger.warning(
            "serving on %s: anyone who can reach this address can use the app and download its results", config.host
        )
    demo = build(config)
    stop_sweeping = demo.surfsplat_sessions.sweep_every(max(60.0, config.keep_minutes * 15))
    try:
        demo.launch(
            server_name=config.host,
            server_port=config.port,
            share=share,
            max_file_size=config.max_upload_bytes(),
            allowed_paths=[str(config.root())],
            show_error=False,
            ssr_mode=False,
            prevent_thread_lock=not block,
            quiet=False,
        )
    finally:
        if block:
            stop_sweeping.set()
    return demo
