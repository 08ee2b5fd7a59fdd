"""The reduced fixtures in tests/data are what `tests/data/make_fixtures.py` derives from the full data.

Runs where the full data is present (../shared): every file is rebuilt into a temporary folder and
compared by content (decoded pixels, arrays, parsed JSON, tensors and metadata), so a change to the
full data or to the reduction cannot leave the repository's copies silently out of date.
"""

from __future__ import annotations

import gzip
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from safetensors import safe_open

FIXTURES = Path(__file__).resolve().parent
NOT_BUILT = {"README.md", "make_fixtures.py"}  # and the data package's tests beside the fixtures (*.py)
OWN_BUILDER = {"distorted"}  # folders built by their own script from the fixtures here (make_distorted.py)


def _load_builder():
    spec = importlib.util.spec_from_file_location("make_fixtures", FIXTURES / "make_fixtures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _content(path: Path):
    """A comparable form of a fixture file's content."""
    if path.suffix == ".png":
        with Image.open(path) as image:
            return image.mode, np.asarray(image)
    if path.suffix == ".npy":
        return np.load(path)
    if path.suffix == ".npz":
        with np.load(path) as npz:
            return {k: npz[k] for k in npz.files}
    if path.suffix == ".json":
        return json.loads(path.read_text())
    if path.suffix == ".gz":
        return json.loads(gzip.decompress(path.read_bytes()))
    if path.suffix == ".safetensors":
        with safe_open(str(path), framework="np") as f:
            return f.metadata(), {k: f.get_tensor(k) for k in f.keys()}
    raise AssertionError(f"{path}: no comparison for this kind of file")


def _equal(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b)
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, tuple):
        return isinstance(b, tuple) and len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    return a == b


@pytest.mark.slow
def test_repository_fixtures_are_the_reduction_of_the_full_data(shared_dir: Path, tmp_path: Path) -> None:
    builder = _load_builder()
    builder.build(shared_dir, tmp_path)
    built = {p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file()}
    kept = {
        p.relative_to(FIXTURES)
        for p in FIXTURES.rglob("*")
        if p.is_file()
        and p.name not in NOT_BUILT
        and p.suffix not in (".py", ".pyc")
        and p.relative_to(FIXTURES).parts[0] not in OWN_BUILDER
    }
    assert built == kept, f"files differ: only rebuilt {sorted(built - kept)}, only kept {sorted(kept - built)}"
    stale = [str(p) for p in sorted(built) if not _equal(_content(tmp_path / p), _content(FIXTURES / p))]
    assert not stale, f"tests/data is out of date (run tests/data/make_fixtures.py): {stale}"
