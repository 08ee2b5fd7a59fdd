"""Regenerate the golden fixture's weights from `formula_weights.json`.

The golden fixture ships no weight file: every tensor of the release-layout state dict is
defined by a hash formula (see the fixture's README). Per tensor with n elements:

    seed = crc32(key)                      (uint32)
    h    = ((i + seed) mod 2^32) * 2654435761 mod 2^32,   i = 0 .. n-1
    h    = fmix32(h)                       (MurmurHash3 finalizer)
    z    = (h / 2^32 - 0.5) * sqrt(12)     (float64, uniform with unit variance)
    w    = float32(mean + std * z)         (rounded once)

Everything is vectorised with numpy uint64 so that products of two 32-bit numbers never overflow;
regenerating the 38M weights of the small model takes a few seconds.
"""

from __future__ import annotations

import json
import math
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..utils.checks import SurfSplatInputError

_MASK32 = np.uint64(0xFFFFFFFF)
_KNUTH = np.uint64(2654435761)  # Knuth's multiplicative hash constant
_FMIX1 = np.uint64(0x85EBCA6B)
_FMIX2 = np.uint64(0xC2B2AE35)


def hash_uniform(key: str, n: int) -> np.ndarray:
    """The formula's raw 32-bit hashes h (as uint64) for the first n indices of `key`."""
    seed = np.uint64(zlib.crc32(key.encode("utf-8")))
    h = np.arange(n, dtype=np.uint64)
    h += seed
    h &= _MASK32
    h *= _KNUTH
    h &= _MASK32
    # MurmurHash3 fmix32; the masks keep every intermediate below 2^32 so products fit in 64 bits
    h ^= h >> np.uint64(16)
    h *= _FMIX1
    h &= _MASK32
    h ^= h >> np.uint64(13)
    h *= _FMIX2
    h &= _MASK32
    h ^= h >> np.uint64(16)
    return h


def formula_tensor(key: str, shape: tuple[int, ...], mean: float, std: float) -> np.ndarray:
    """One tensor of the fixture: float32, row-major `shape`."""
    n = math.prod(shape)
    mean64 = float(np.float32(mean))
    std64 = float(np.float32(std))
    if std64 == 0.0:
        return np.full(shape, np.float32(mean64), dtype=np.float32)
    u = hash_uniform(key, n).astype(np.float64) / 2.0**32
    z = (u - 0.5) * math.sqrt(12.0)
    return (mean64 + std64 * z).astype(np.float32).reshape(shape)


def read_spec(path: str | Path) -> dict:
    """Parse and sanity-check `formula_weights.json`."""
    path = Path(path)
    try:
        spec = json.loads(path.read_text())
    except FileNotFoundError:
        raise
    except (OSError, ValueError) as err:
        raise SurfSplatInputError(f"{path}: not a readable formula-weights JSON ({err})") from None
    for field in ("tensors", "num_tensors"):
        if field not in spec:
            raise SurfSplatInputError(f"{path}: missing field '{field}'")
    if len(spec["tensors"]) != spec["num_tensors"]:
        raise SurfSplatInputError(
            f"{path}: 'tensors' lists {len(spec['tensors'])} entries, 'num_tensors' says {spec['num_tensors']}"
        )
    return spec


def iter_formula_weights(spec: dict) -> Iterator[tuple[str, np.ndarray]]:
    """Yield (release key, float32 array) in the spec's order."""
    for entry in spec["tensors"]:
        yield entry["key"], formula_tensor(entry["key"], tuple(entry["shape"]), entry["mean"], entry["std"])


def formula_state_dict(path: str | Path) -> dict[str, np.ndarray]:
    """The whole release-layout state dict as numpy arrays, keyed by the release's names."""
    return dict(iter_formula_weights(read_spec(path)))
