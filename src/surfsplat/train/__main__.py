"""`python -m surfsplat.train [options]`: the `surfsplat train` command, also under torchrun
(`torchrun --nproc_per_node 2 -m surfsplat.train --preset tiny`)."""

from __future__ import annotations

import argparse

from ..cli import run_command
from ..commands import train as command
from ..utils import log


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="surfsplat train", description=(command.__doc__ or "").splitlines()[0])
    command.add_arguments(parser)
    log.add_options(parser)
    args = parser.parse_args(argv)
    log.configure(args.log_level)
    return run_command("train", lambda: command.run(args))


raise SystemExit(main())
