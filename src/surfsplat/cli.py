"""The `surfsplat` command line.

Each sub-command lives in its own module exposing `add_arguments(parser)` and `run(args) -> int`;
modules are imported only when their command runs, so `surfsplat --help` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from .checks import SurfSplatInputError

# command name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "render-scene": ("surfsplat.commands.render_scene", "render the built-in procedural surfel scene to images"),
    "demo": (
        "surfsplat.commands.demo",
        "train, evaluate (HRRC x1/x2/x4) and export on synthetic data: report.html in minutes",
    ),
    "reconstruct": (
        "surfsplat.commands.reconstruct",
        "posed images -> surfels (PLY), renders, depth/normal maps, videos, mesh",
    ),
    "poses": ("surfsplat.commands.poses", "camera file (poses, focal, near/far) estimated from photos alone"),
    "eval": (
        "surfsplat.commands.eval",
        "standard and HRRC metrics over an evaluation index, in the paper's table layout",
    ),
    "render": ("surfsplat.commands.render", "render a saved PLY from cameras at any scale"),
    "export": ("surfsplat.commands.export", "PLY, mesh (TSDF) and videos from a saved reconstruction"),
    "view": ("surfsplat.commands.view", "interactive browser viewer of a PLY on localhost"),
    "train": ("surfsplat.commands.train", "train a SurfSplat model (single process or torchrun data-parallel)"),
    "convert": (
        "surfsplat.commands.convert",
        "convert a dataset (dtu, llff, blender, colmap, dl3dv, scannet) into chunks",
    ),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="surfsplat", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module_name)
        importlib.import_module(module_name).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    module = importlib.import_module(args._module)
    try:
        return int(module.run(args) or 0)
    except (SurfSplatInputError, FileNotFoundError) as err:
        print(f"surfsplat {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"surfsplat {args.command}: interrupted", file=sys.stderr)
        return 130
