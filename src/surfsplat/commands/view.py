"""`surfsplat view PLY|OUTPUT_DIR`: the surfels in the browser, on viser (Ctrl-C stops it).

    surfsplat view out/                   # a reconstruction: surfels, cameras with images, path, mesh
    surfsplat view out/surfels.ply        # a PLY alone (2DGS or 3DGS layout)

then open the printed http://127.0.0.1:8080/. It listens on this machine only unless --host says
otherwise, and serves the viewer's page and this one scene, nothing else.
"""

from __future__ import annotations

import argparse
import threading
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", type=Path, metavar="PLY|OUTPUT_DIR", help="surfels PLY or a reconstruct/export folder")
    parser.add_argument("--port", type=int, default=8080, help="port (the next free one when taken; 0 = any)")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default: this machine only)")


def run(args: argparse.Namespace) -> int:
    from ..viewer import SurfelViewer, load_viewer_scene
    from ..viewer.scene import summary_line

    if not args.path.exists():
        raise FileNotFoundError(f"{args.path}: no such PLY file or output folder")
    viewer = SurfelViewer(args.host, args.port, title=f"surfsplat: {args.path.name}")
    print(f"surfsplat viewer: loading {args.path} (progress at {viewer.url})", flush=True)
    try:
        scene = load_viewer_scene(args.path, viewer.progress)
        viewer.show(scene)
    except BaseException:
        viewer.stop()  # no page left serving half a scene
        raise
    print(f"surfsplat viewer: {summary_line(scene)} at {viewer.url} (Ctrl-C to stop)", flush=True)
    try:
        threading.Event().wait()  # serve until interrupted
    finally:
        viewer.stop()
    return 0
