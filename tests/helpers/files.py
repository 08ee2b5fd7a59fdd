"""Checks on what a run left in a folder."""

from __future__ import annotations

from pathlib import Path

from surfsplat.utils import atomic


def no_temporaries(folder: Path) -> None:
    """No file under `folder` is a temporary of an atomic write or a checkpoint being written."""
    left = [p for p in folder.rglob("*") if atomic.is_temporary(p) or p.name.startswith(".tmp-")]
    assert not left, left
