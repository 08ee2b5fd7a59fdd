"""Freed memory kept in the process while a loop of equal steps runs (glibc's malloc).

A fit or training step on the CPU allocates and frees the same large buffers every time: the
activated surfels, the renderer's per-surfel and per-pair arrays, the gradients. glibc serves an
allocation above its mmap threshold (32 MiB at most, whatever it is set to) with fresh pages
from the kernel and hands them back on free, so every step pays a page fault and the kernel's
zeroing for each page of each such buffer: at 530k surfels (368x496) a quarter of the fit step, at
100k surfels a tenth. Inside `reuse_freed_memory()` glibc takes no new mappings for large blocks
(M_MMAP_MAX 0) and keeps what is freed (M_TRIM_THRESHOLD raised), so the next step's buffers
reuse the last step's pages; on exit glibc's default limits come back and `malloc_trim` returns the
free memory. The heap then holds at most one step's worth of buffers beyond what is live.

Written here because no library does it from inside a running process: jemalloc or tcmalloc need
LD_PRELOAD at start, and neither NumPy nor PyTorch's CPU allocator caches blocks. With another C
library (musl, macOS, Windows) the context changes nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import platform
import threading
from collections.abc import Iterator
from contextlib import contextmanager

logger = logging.getLogger(__name__)

# mallopt parameters and glibc's defaults for them (malloc/malloc.c).
M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4
DEFAULT_TRIM_THRESHOLD = 128 * 1024
DEFAULT_MMAP_MAX = 65536
KEPT_TRIM_THRESHOLD = 2**31 - 1  # mallopt takes an int: about 2 GiB of free top-of-heap kept

_lock = threading.Lock()
_depth = 0  # nested contexts: only the outermost one sets and restores


def _glibc() -> ctypes.CDLL | None:
    """glibc's handle, or None on another C library."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    name = ctypes.util.find_library("c")
    return ctypes.CDLL(name) if name else None


def _set(libc: ctypes.CDLL, trim_threshold: int, mmap_max: int) -> bool:
    return bool(libc.mallopt(M_TRIM_THRESHOLD, trim_threshold)) and bool(libc.mallopt(M_MMAP_MAX, mmap_max))


@contextmanager
def reuse_freed_memory() -> Iterator[bool]:
    """Keep freed memory in the heap for reuse while inside (glibc); yields whether it took effect.

    Nested uses are one: the outermost sets the limits and restores glibc's defaults on exit.
    """
    global _depth
    libc = _glibc()
    if libc is None:
        yield False
        return
    with _lock:
        _depth += 1
        took = _depth > 1 or _set(libc, KEPT_TRIM_THRESHOLD, 0)
    if not took:
        logger.debug("mallopt refused the heap limits; allocations stay as they were")
    try:
        yield took
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                _set(libc, DEFAULT_TRIM_THRESHOLD, DEFAULT_MMAP_MAX)
                libc.malloc_trim(0)
