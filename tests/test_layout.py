"""The code layout holds (docs/layout.md): each package imports only packages above it in the
pipeline order, at the top of a file or inside a function, and the library never imports the
command line."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "surfsplat"
# docs/layout.md's order: a package may import the ones before it.
ORDER = (
    "utils",
    "geometry",
    "render",
    "data",
    "model",
    "export",
    "poses",
    "metrics",
    "compaction",
    "capture",
    "reconstruction",
    "evaluation",
    "train",
    "demo",
    "viewer",
    "app",
    "testing",
    "commands",
    "cli",
)
ENTRY_POINTS = ("__main__.py",)  # `python -m surfsplat`, `python -m surfsplat.train`: the command line


def _imported_packages(path: Path, text: str | None = None) -> list[tuple[int, str]]:
    """(line, top-level package) of every surfsplat import in a file (or `text` as that file),
    relative ones resolved."""
    module = path.relative_to(SRC.parent).with_suffix("").parts
    package = module[:-1]
    found = []
    for node in ast.walk(ast.parse(path.read_text() if text is None else text)):
        if not isinstance(node, ast.ImportFrom):
            continue
        if node.level:
            base = list(package[: len(package) - (node.level - 1)])
            target = base + (node.module.split(".") if node.module else [])
        else:
            target = (node.module or "").split(".")
        if target[0] != "surfsplat":
            continue
        names = target[1:2] or [alias.name for alias in node.names]
        found += [(node.lineno, name) for name in names]
    return found


def test_every_package_imports_only_the_packages_above_it():
    wrong = []
    for path in sorted(SRC.rglob("*.py")):
        top = path.relative_to(SRC).parts[0].removesuffix(".py")
        if top not in ORDER or path.name in ENTRY_POINTS:
            continue
        for line, name in _imported_packages(path):
            if name in ORDER and ORDER.index(name) > ORDER.index(top):
                wrong.append(f"{path.relative_to(SRC)}:{line} imports {name}")
    assert not wrong, wrong


def test_the_check_sees_an_upward_import():
    """Relative imports are resolved, inside functions too, so a library module importing a command is caught."""
    probe = SRC / "utils" / "probe.py"
    assert _imported_packages(probe, "def f():\n    from ..commands import demo\n") == [(2, "commands")]
    assert _imported_packages(probe, "from . import atomic\nfrom .. import render\n") == [(1, "utils"), (2, "render")]


def test_every_package_is_placed():
    packages = {p.name for p in SRC.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert packages <= set(ORDER), sorted(packages - set(ORDER))
