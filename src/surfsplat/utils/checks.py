"""Input validation at public boundaries: one clear error naming the argument."""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Sequence
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


def check_output_dir(
    path: str | os.PathLike,
    option: str = "--out",
    *,
    inputs: Iterable[str | os.PathLike | None] = (),
    writes: Iterable[str] = (),
) -> Path:
    """Check, before any work, that `path` can be the folder a command writes its outputs to.

    Refused with one error naming `option` and the path: a file where the folder should be (or
    above it), a folder that cannot be written, a folder that is one of the `inputs` folders (an
    input folder is never filled with outputs), and a file of `writes` (names relative to the
    folder) that is one of the `inputs` (it would be overwritten). Nothing is created. Returns the
    path.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise SurfSplatInputError(f"{option} {path}: exists and is a file, expected a folder")
    _check_writable(path, path, option)
    target = path.resolve()
    written = {(target / name).resolve(): name for name in writes}
    for given in inputs:
        if given is None:
            continue
        source = Path(given).resolve()
        if source.is_dir() and source == target:
            raise SurfSplatInputError(
                f"{option} {path}: is the input folder {given}; outputs go to a folder of their own"
            )
        if source in written:
            raise SurfSplatInputError(
                f"{option} {path}: writing {written[source]} there would overwrite the input {given}; "
                f"choose another {option}"
            )
    return path


def check_output_file(path: str | os.PathLike, option: str, *, inputs: Iterable[str | os.PathLike | None] = ()) -> Path:
    """Check, before any work, that the file `path` can be written: not a folder, its folder
    writable or creatable, and not one of the `inputs`. Returns the path."""
    path = Path(path)
    if path.is_dir():
        raise SurfSplatInputError(f"{option} {path}: is a folder, expected a file name")
    _check_writable(path.parent, path, option)
    target = path.resolve()
    for given in inputs:
        if given is not None and Path(given).resolve() == target:
            raise SurfSplatInputError(f"{option} {path}: would overwrite the input {given}")
    return path


def _check_writable(folder: Path, shown: Path, option: str) -> None:
    """`folder` (where the outputs go) or, when it is still to be made, the nearest existing folder
    above it must be a folder this process can write into."""
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise SurfSplatInputError(f"{option} {shown}: {existing} is a file, expected a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise SurfSplatInputError(f"{option} {shown}: {existing} is not writable")
