"""The `surfsplat` command line.

Each sub-command lives in its own module exposing `add_arguments(parser)` and `run(args) -> int`;
modules are imported only when their command runs, so `surfsplat --help` stays fast.
-q/--quiet and -v/--verbose (see `surfsplat.utils.log`) are accepted before or after the command;
`surfsplat --version` prints the installed version.

Exit codes: 0 done; 2 bad input (one line naming the file or option, nothing written); 1 an output
could not be written (full disk, one line naming the file) or training diverged; 130 / 143 stopped
by Ctrl-C / SIGTERM (one line; files already complete are kept, a file being written is not left).
"""

from __future__ import annotations

import argparse
import errno
import importlib
import logging
import signal
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from . import _openmp  # noqa: F401  (first of the package: before torch loads)
from .utils import log
from .utils.atomic import OutputError, output_error
from .utils.checks import SurfSplatInputError

logger = logging.getLogger(__name__)

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
    "optimize": (
        "surfsplat.commands.optimize",
        "optimize every surfel of a saved reconstruction on its context photos (per-scene fit)",
    ),
    "poses": ("surfsplat.commands.poses", "camera file (poses, focal, near/far) estimated from photos alone"),
    "eval": (
        "surfsplat.commands.eval",
        "standard and HRRC metrics over an evaluation index, in the paper's table layout",
    ),
    "render": ("surfsplat.commands.render", "render a saved PLY from cameras at any scale"),
    "export": ("surfsplat.commands.export", "PLY, mesh (TSDF) and videos from a saved reconstruction"),
    "view": (
        "surfsplat.commands.view",
        "a PLY or reconstruction folder in the browser (viser, localhost): splats, cameras, exact render",
    ),
    "train": ("surfsplat.commands.train", "train a SurfSplat model (single process or torchrun data-parallel)"),
    "convert": (
        "surfsplat.commands.convert",
        "convert a dataset (dtu, llff, blender, colmap, dl3dv, scannet) into chunks",
    ),
    "weights": ("surfsplat.commands.weights", "pretrained weights by name: list, download, path, info"),
    "app": ("surfsplat.commands.app", "a browser app (gradio): photos or a video -> the scene on a page, downloads"),
}


def package_version() -> str:
    """The installed distribution's version; the source tree's when it is not installed."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("surfsplat")
    except PackageNotFoundError:
        from . import __version__

        return __version__


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="surfsplat", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"surfsplat {package_version()}")
    log.add_options(parser)
    messages = argparse.ArgumentParser(add_help=False)
    log.add_options(messages, subcommand=True)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text, parents=[messages])
        p.set_defaults(_module=module_name)
        importlib.import_module(module_name).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    log.configure(args.log_level)
    logger.debug(
        "surfsplat %s on Python %s: %s",
        package_version(),
        sys.version.split()[0],
        sys.argv[1:] if argv is None else argv,
    )
    module = importlib.import_module(args._module)
    return run_command(args.command, lambda: module.run(args))


def run_command(command: str, run: Callable[[], int | None]) -> int:
    """`run()` with the command line's endings: its exit code, or one stderr line and 2 (bad input),
    1 (an output could not be written, training diverged) or 128 + signal (Ctrl-C, SIGTERM)."""
    try:
        with terminate_as_interrupt():
            return int(run() or 0)
    except (SurfSplatInputError, FileNotFoundError) as err:
        print(f"surfsplat {command}: error: {err}", file=sys.stderr)
        return 2
    except (OutputError, FloatingPointError) as err:
        print(f"surfsplat {command}: error: {_one_line(err)}", file=sys.stderr)
        return 1
    except OSError as err:
        if err.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        # A full disk outside the atomic writers (TensorBoard's event log, metrics.jsonl): still one line.
        print(f"surfsplat {command}: error: {output_error(err.filename or '(unnamed file)', err)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as err:
        signum = err.signum if isinstance(err, Terminated) else signal.SIGINT
        print(
            f"surfsplat {command}: interrupted ({signal.Signals(signum).name}); "
            "files already complete were kept, none is left half-written",
            file=sys.stderr,
        )
        return 128 + signum


class Terminated(KeyboardInterrupt):
    """SIGTERM (a scheduler, `kill`) delivered as an interrupt, so cleanup runs as for Ctrl-C."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


@contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """Within: SIGTERM raises `Terminated` in the main thread (Python's default would end the
    process without running any `finally`, leaving temporary files behind)."""

    def handler(signum: int, frame: object) -> None:
        raise Terminated(signum)

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread (an embedding application): leave its handling alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _one_line(err: BaseException) -> str:
    """The first line of an error's message: the command's error is always one line."""
    lines = str(err).strip().splitlines()
    return lines[0] if lines else type(err).__name__
