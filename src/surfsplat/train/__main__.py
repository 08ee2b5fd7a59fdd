"""`python -m surfsplat.train [options]`: the `surfsplat train` command, also under torchrun
(`torchrun --nproc_per_node 2 -m surfsplat.train --preset tiny`)."""

from __future__ import annotations

import argparse
import sys

from .. import log
from ..checks import SurfSplatInputError
from ..commands import train as command


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="surfsplat train", description=(command.__doc__ or "").splitlines()[0])
    command.add_arguments(parser)
    log.add_options(parser)
    args = parser.parse_args(argv)
    log.configure(args.log_level)
    try:
        return command.run(args)
    except (SurfSplatInputError, FileNotFoundError) as err:
        print(f"surfsplat train: error: {err}", file=sys.stderr)
        return 2


raise SystemExit(main())
