"""Run the command line with one file write held open, so a test can interrupt it mid-write.

    python tests/helpers/slow_writer.py NAME READY surfsplat-args...

The first time a file whose temporary name contains NAME has been written in full (and before it
is flushed to disk and renamed), this process creates the file READY and sleeps; the test then
sends SIGINT or SIGTERM. Nothing else about the command changes.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from surfsplat.cli import main
from surfsplat.utils import atomic

name, ready, argv = sys.argv[1], Path(sys.argv[2]), sys.argv[3:]
real_fsync = atomic._fsync


def held_fsync(path: Path) -> None:
    if name in path.name and not ready.exists():
        ready.write_text(str(path))
        time.sleep(120)  # the test's signal arrives here
    real_fsync(path)


atomic._fsync = held_fsync
sys.exit(main(argv))
