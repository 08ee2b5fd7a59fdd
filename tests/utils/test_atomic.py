"""Atomic writes meet a full disk: the earlier version of the file stays, no temporary is left."""

from __future__ import annotations

import errno

import pytest

from surfsplat.utils import atomic
from tests.helpers.files import no_temporaries


def test_full_disk_while_writing_a_text_file(tmp_path, monkeypatch):
    """ENOSPC from write() itself, part-way through: the earlier version of the file stays."""
    target = tmp_path / "metrics.json"
    atomic.write_text(target, '{"old": 1}')

    class FullFile:
        def __init__(self, *args, **kwargs):
            self.inner = open(*args, **kwargs)

        def write(self, data: bytes) -> int:
            self.inner.write(data[: len(data) // 2])
            raise OSError(errno.ENOSPC, "No space left on device")

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.inner.close()

    monkeypatch.setattr(atomic, "open", FullFile, raising=False)
    with pytest.raises(atomic.OutputError, match="metrics.json: cannot write .no space left"):
        atomic.write_text(target, '{"new": "a longer document"}')
    assert target.read_text() == '{"old": 1}'
    no_temporaries(tmp_path)
