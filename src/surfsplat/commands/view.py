"""`surfsplat view PLY`: an interactive browser viewer on localhost (Ctrl-C stops it).

    surfsplat view out/surfels.ply                 # then open the printed http://127.0.0.1:8080/

The page is self-contained (no network access, no WebGL needed); the reconstruction's
cameras.json beside the PLY, when present, sets the first view.
"""

from __future__ import annotations

import argparse
import threading
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("ply", type=Path, help="surfels (2DGS or 3DGS layout PLY)")
    parser.add_argument("--port", type=int, default=8080, help="port on localhost (0 = any free port)")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default: this machine only)")
    parser.add_argument("--cameras", type=Path, default=None, help="camera file whose first camera is the initial view")
    parser.add_argument(
        "--max-splats", type=int, default=300_000, help="subsample larger files to keep the page interactive"
    )
    parser.add_argument(
        "--alpha-threshold",
        type=float,
        default=None,
        help="forced alpha blending tau (default: the reconstruction's, else 0.001); negative turns it off",
    )


def run(args: argparse.Namespace) -> int:
    from ..viewer import ViewerServer

    if not args.ply.is_file():
        raise FileNotFoundError(f"{args.ply}: no such PLY file")
    tau = "auto" if args.alpha_threshold is None else (None if args.alpha_threshold < 0 else args.alpha_threshold)
    server = ViewerServer.from_ply(args.ply, args.host, args.port, args.cameras, args.max_splats, tau).start()
    print(
        f"surfsplat viewer: {server.meta['count']:,} splats of {args.ply} at {server.url} (Ctrl-C to stop)", flush=True
    )
    try:
        threading.Event().wait()  # serve until interrupted
    finally:
        server.shutdown()
    return 0
