"""`python -m surfsplat.train [options]`: the `surfsplat train` command, also under torchrun
(`torchrun --nproc_per_node 2 -m surfsplat.train --preset tiny`)."""

from __future__ import annotations

import argparse
import sys

from ..checks import SurfSplatInputError
from ..commands import train as command


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="surfsplat train", description=(command.__doc__ or "").splitlines()[0])
    command.add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return command.run(args)
    except (SurfSplatInputError, FileNotFoundError) as err:
        print(f"surfsplat train: error: {err}", file=sys.stderr)
        return 2


raise SystemExit(main())
