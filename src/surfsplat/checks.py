"""Input validation at public boundaries: one clear error naming the argument."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor


class SurfSplatInputError(ValueError):
    """Raised when a public function or file receives malformed input."""


def read_json(path: str | Path) -> Any:
    """The parsed content of a JSON file; malformed text raises SurfSplatInputError naming the
    file (a missing file stays FileNotFoundError)."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except ValueError as err:
        raise SurfSplatInputError(f"{path}: not valid JSON ({err})") from None


def check_tensor(name: str, value: object, shape: Sequence[int | str | None], *, finite: bool = True) -> Tensor:
    """Check that `value` is a floating tensor with the given shape pattern.

    `shape` entries: an int (exact size), a str (a named size: it must agree wherever the same
    name appears in one call) or None (any size). Returns the tensor unchanged.
    """
    if not isinstance(value, Tensor):
        raise SurfSplatInputError(f"{name}: expected a torch.Tensor, got {type(value).__name__}")
    if value.ndim != len(shape):
        raise SurfSplatInputError(
            f"{name}: expected shape {_pattern(shape)}, got {tuple(value.shape)} ({value.ndim} dims)"
        )
    named: dict[str, int] = {}
    for axis, (want, got) in enumerate(zip(shape, value.shape)):
        if isinstance(want, int) and want != got:
            raise SurfSplatInputError(
                f"{name}: expected shape {_pattern(shape)}, got {tuple(value.shape)} (axis {axis})"
            )
        if isinstance(want, str):
            if named.setdefault(want, got) != got:
                raise SurfSplatInputError(
                    f"{name}: expected shape {_pattern(shape)}, got {tuple(value.shape)} ({want} differs)"
                )
    if not value.is_floating_point():
        raise SurfSplatInputError(f"{name}: expected a floating-point tensor, got {value.dtype}")
    if finite and not bool(torch.isfinite(value).all()):
        bad = (~torch.isfinite(value)).nonzero()[0].tolist()
        raise SurfSplatInputError(f"{name}: contains NaN or inf (first at index {tuple(bad)})")
    return value


def _pattern(shape: Sequence[int | str | None]) -> str:
    return "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
