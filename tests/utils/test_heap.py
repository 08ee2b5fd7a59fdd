"""`reuse_freed_memory`: inside it glibc serves a large block from the heap and keeps it when freed;
outside it (and after it) a large block is a fresh mapping again. The blocks are larger than all the
free memory in the heaps, so that no earlier test's freed memory can serve them."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

from surfsplat.utils import heap

BLOCK = 64 * 2**20  # above glibc's largest mmap threshold (32 MiB)


class _Mallinfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost".split()
    ]


def _mallinfo():
    libc = heap._glibc()
    if libc is None or not hasattr(libc, "mallinfo2"):
        pytest.skip("needs glibc 2.33 or later (mallinfo2); elsewhere the context changes nothing")
    libc.mallinfo2.restype = _Mallinfo2
    return libc.mallinfo2


def _mapped_and_heap(mallinfo) -> tuple[int, int]:
    info = mallinfo()
    return info.hblkhd, info.uordblks  # bytes in mmapped blocks, bytes in use from the heaps


def _beyond_the_free_heap(mallinfo) -> int:
    """A size no free chunk of the heaps can serve: glibc must map it or grow a heap for it."""
    return mallinfo().fordblks + BLOCK


def test_large_blocks_come_from_the_heap_inside_and_are_mapped_outside():
    mallinfo = _mallinfo()
    mapped, _ = _mapped_and_heap(mallinfo)
    size = _beyond_the_free_heap(mallinfo)
    outside = np.empty(size, dtype=np.uint8)
    assert _mapped_and_heap(mallinfo)[0] >= mapped + size  # a fresh mapping
    del outside

    with heap.reuse_freed_memory() as took:
        assert took
        mapped, in_use = _mapped_and_heap(mallinfo)
        size = _beyond_the_free_heap(mallinfo)
        first = np.empty(size, dtype=np.uint8)
        address = first.ctypes.data
        assert _mapped_and_heap(mallinfo)[0] == mapped  # no new mapping: the heap grew instead
        assert _mapped_and_heap(mallinfo)[1] >= in_use + size
        arena = mallinfo().arena
        del first
        assert mallinfo().arena == arena  # freed, but not trimmed back to the system
        second = np.empty(size, dtype=np.uint8)
        assert second.ctypes.data == address  # the same pages again
        assert mallinfo().arena == arena
        del second

    mapped, _ = _mapped_and_heap(mallinfo)
    size = _beyond_the_free_heap(mallinfo)
    after = np.empty(size, dtype=np.uint8)
    assert _mapped_and_heap(mallinfo)[0] >= mapped + size  # glibc's defaults are back
    del after


def test_nested_contexts_restore_only_at_the_outermost_exit():
    mallinfo = _mallinfo()
    with heap.reuse_freed_memory():
        with heap.reuse_freed_memory() as inner:
            assert inner
        mapped = _mapped_and_heap(mallinfo)[0]
        still = np.empty(_beyond_the_free_heap(mallinfo), dtype=np.uint8)
        assert _mapped_and_heap(mallinfo)[0] == mapped  # the inner exit restored nothing
        del still


def test_other_c_libraries_are_left_alone(monkeypatch):
    monkeypatch.setattr(heap, "_glibc", lambda: None)
    with heap.reuse_freed_memory() as took:
        assert took is False
