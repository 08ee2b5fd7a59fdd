"""`python -m surfsplat.train [options]`: `surfsplat train` under the name torchrun runs
(`torchrun --nproc_per_node 2 -m surfsplat.train --preset tiny`)."""

import sys

from ..cli import main

raise SystemExit(main(["train", *sys.argv[1:]]))
