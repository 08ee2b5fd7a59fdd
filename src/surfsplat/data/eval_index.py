"""Evaluation index files of the pixelSplat / MVSplat / DepthSplat / SurfSplat releases.

A JSON object `{entry_key: {"context": [i, j, ...], "target": [a, b, ...]} or null}`. null marks a
scene the benchmark excludes. An entry key is either a scene key (RealEstate10K, ACID, DL3DV,
ScanNet slices) or a scene key plus a `_NN` suffix when one scene has several entries (MVSplat's
DTU index: `scan1_train_00` ... `scan1_train_03` for the chunk key `scan1_train`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from ..utils.checks import SurfSplatInputError, read_json

_SUFFIX = re.compile(r"^(.*)_(\d+)$")


@dataclass(frozen=True)
class EvaluationEntry:
    """Context and target view indices of one evaluation sample."""

    context: tuple[int, ...]
    target: tuple[int, ...]


class EvaluationIndex:
    """entries: entry key -> EvaluationEntry, or None for an excluded scene."""

    def __init__(self, entries: dict[str, EvaluationEntry | None], source: str = "evaluation index") -> None:
        self.entries = entries
        self.source = source
        self._by_scene: dict[str, list[str]] = {}
        for key in entries:
            m = _SUFFIX.match(key)
            if m:
                self._by_scene.setdefault(m.group(1), []).append(key)

    @classmethod
    def load(cls, path: str | Path) -> EvaluationIndex:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: evaluation index not found")
        return cls.from_dict(read_json(path), str(path))

    @classmethod
    def from_dict(cls, data: object, source: str = "evaluation index") -> EvaluationIndex:
        if not isinstance(data, dict):
            raise SurfSplatInputError(f"{source}: expected a JSON object of scene keys, got {type(data).__name__}")
        entries: dict[str, EvaluationEntry | None] = {}
        for key, value in data.items():
            if value is None:
                entries[key] = None
                continue
            if not isinstance(value, dict):
                raise SurfSplatInputError(
                    f"{source}: entry '{key}' must be an object or null, got {type(value).__name__}"
                )
            views = {}
            for field in ("context", "target"):
                if field not in value:
                    raise SurfSplatInputError(f"{source}: entry '{key}' is missing key '{field}'")
                items = value[field]
                if (
                    not isinstance(items, list)
                    or not items
                    or not all(isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in items)
                ):
                    raise SurfSplatInputError(
                        f"{source}: entry '{key}' field '{field}' must be a non-empty list of view indices >= 0, got {items!r}"
                    )
                views[field] = tuple(items)
            unknown = set(value) - {"context", "target"}
            if unknown:
                raise SurfSplatInputError(f"{source}: entry '{key}' has unknown keys {sorted(unknown)}")
            entries[key] = EvaluationEntry(views["context"], views["target"])
        return cls(entries, source)

    def __len__(self) -> int:
        return len(self.entries)

    def __contains__(self, scene_key: str) -> bool:
        return scene_key in self.entries or scene_key in self._by_scene

    @property
    def num_excluded(self) -> int:
        return sum(v is None for v in self.entries.values())

    def lookup(self, scene_key: str) -> list[tuple[str, EvaluationEntry | None]]:
        """The entries of a scene: its own key, or else its `key_NN` entries in order; [] if none."""
        if scene_key in self.entries:
            return [(scene_key, self.entries[scene_key])]
        keys = sorted(self._by_scene.get(scene_key, []), key=lambda k: int(_SUFFIX.match(k).group(2)))
        return [(k, self.entries[k]) for k in keys]
