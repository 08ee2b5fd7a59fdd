"""Compiled CPU renderer: numba kernels for both modes, forward and backward, on every core.

Importing this package compiles nothing and does not need numba: the kernels load on first use of
`render_cpu` and are compiled once per machine (numba's on-disk cache). `backend_unavailable()`
tells the dispatcher whether the backend can load at all.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .settings import CpuRenderSettings

if TYPE_CHECKING:
    from .backend import contributing_pairs, render_cpu

__all__ = ["backend_unavailable", "CpuRenderSettings", "contributing_pairs", "render_cpu"]


def backend_unavailable() -> str | None:
    """None when the compiled backend can load, else the reason in one line."""
    try:
        import numba  # noqa: F401
    except ImportError as err:
        return f"numba is not importable ({err})"
    return None


def __getattr__(name: str):
    if name in ("render_cpu", "contributing_pairs"):
        from . import backend

        return getattr(backend, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
