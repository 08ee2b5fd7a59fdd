"""`surfsplat app`: the browser app (photos or a video -> a scene on a page) on this machine.

    surfsplat app                                  # http://127.0.0.1:7860, this machine only
    surfsplat app --port 8080 --max-upload-mb 50 --keep-minutes 30
    surfsplat app --max-views 30 --max-run-seconds 300     # a shared server's limits on one run
    surfsplat app --host 0.0.0.0                   # the network too (a warning says so)

The page is `surfsplat.app.build` (a gradio.Blocks); this module only parses the options.
"""

from __future__ import annotations

import argparse

from ..app.config import AppConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    default = AppConfig()
    parser.add_argument(
        "--host",
        default=default.host,
        help=f"address to listen on (default {default.host}: this machine only; another prints a warning)",
    )
    parser.add_argument("--port", type=int, default=default.port, help=f"port (default {default.port}; 0: any free)")
    parser.add_argument(
        "--max-upload-mb",
        type=float,
        default=default.max_upload_mb,
        help=f"one run's uploads together at most (default {default.max_upload_mb:g} MB)",
    )
    parser.add_argument(
        "--max-views",
        type=int,
        default=default.max_views,
        help=f"views of one run at most: photos, or a video's frames used (default {default.max_views})",
    )
    parser.add_argument(
        "--max-run-seconds",
        type=float,
        default=default.max_seconds,
        help=f"a run stops after this many seconds, keeping nothing (default {default.max_seconds:g})",
    )
    parser.add_argument(
        "--keep-minutes",
        type=float,
        default=default.keep_minutes,
        help=f"each run's files are removed this long after it started (default {default.keep_minutes:g})",
    )
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default=default.device)
    parser.add_argument(
        "--share",
        action="store_true",
        help="also open a temporary public gradio.live link (off by default; see docs/app.md for hosting)",
    )


def run(args: argparse.Namespace) -> int:
    from ..app import launch, require_gradio

    require_gradio()  # one line naming the extra before anything else
    config = AppConfig(
        host=args.host,
        port=args.port,
        max_upload_mb=args.max_upload_mb,
        max_views=args.max_views,
        max_seconds=args.max_run_seconds,
        keep_minutes=args.keep_minutes,
        device=args.device,
    )
    launch(config, share=args.share)  # another host than loopback: a warning on stderr
    return 0
