"""Typed configuration dataclasses from JSON-style data (lists become tuples), shared by the model
and training configs: one error naming the field for unknown keys and wrong types."""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any, Literal

from .checks import SurfSplatInputError


def dataclass_from_dict(cls: type, data: object, where: str) -> Any:
    """Build (nested) config dataclasses from JSON data; unknown keys and wrong types are errors."""
    if not isinstance(data, dict):
        raise SurfSplatInputError(f"{where}: expected an object, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise SurfSplatInputError(f"{where}: unknown fields {unknown} for {cls.__name__}")
    values = {name: _coerce(hints[name], data[name], f"{where}.{name}") for name in names if name in data}
    try:
        return cls(**values)
    except (TypeError, ValueError) as err:
        raise SurfSplatInputError(f"{where}: {err}") from None


def _coerce(hint: Any, value: Any, where: str) -> Any:
    """Check one JSON value against a field's type hint and convert lists to tuples."""
    origin = typing.get_origin(hint)
    if dataclasses.is_dataclass(hint):
        return dataclass_from_dict(hint, value, where)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(hint)
        if value is None and type(None) in options:
            return None
        errors = []
        for option in options:
            if option is type(None):
                continue
            try:
                return _coerce(option, value, where)
            except SurfSplatInputError as err:
                errors.append(str(err))
        raise SurfSplatInputError(errors[0] if len(errors) == 1 else f"{where}: no type of {hint} accepts {value!r}")
    if origin is Literal:
        allowed = typing.get_args(hint)
        if value not in allowed:
            raise SurfSplatInputError(f"{where}: expected one of {allowed}, got {value!r}")
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise SurfSplatInputError(f"{where}: expected a list, got {type(value).__name__}")
        args = typing.get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(args[0], v, f"{where}[{i}]") for i, v in enumerate(value))
        if len(args) != len(value):
            raise SurfSplatInputError(f"{where}: expected {len(args)} values, got {len(value)}")
        return tuple(_coerce(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if hint is bool:
        if not isinstance(value, bool):
            raise SurfSplatInputError(f"{where}: expected true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise SurfSplatInputError(f"{where}: expected an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SurfSplatInputError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise SurfSplatInputError(f"{where}: expected a string, got {value!r}")
        return value
    raise SurfSplatInputError(f"{where}: unsupported field type {hint}")
