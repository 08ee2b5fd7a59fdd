"""Lay out a Hugging Face Space (sdk: gradio, CPU) for the browser app from this repository.

    python scripts/make_space.py OUT            # then push OUT to a new Space's git repository

OUT receives the package source (`src/`, `pyproject.toml`), `app.py` and
`README.md` (the Space's front matter) from `space/`, and `space/requirements.txt`, which installs CPU
PyTorch and the package from that copy with its `[app]` extra. Only files git tracks are copied.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ("src", "pyproject.toml")
SPACE = {"app.py": "app.py", "README.md": "README.md", "requirements.txt": "requirements.txt"}


def tracked(prefixes: tuple[str, ...]) -> list[str]:
    listed = subprocess.run(["git", "ls-files", "--", *prefixes], cwd=ROOT, capture_output=True, text=True, check=True)
    return [line for line in listed.stdout.splitlines() if (ROOT / line).is_file()]


def make_space(out: Path) -> list[Path]:
    """Write the Space into `out` (which must be empty or absent); returns the files written."""
    if out.exists() and any(out.iterdir()):
        raise SystemExit(f"{out}: not empty; give a new folder")
    written = []
    for name in tracked(PACKAGE):
        target = out / name
        target.parent.mkdir(parents=True, exist_ok=True)
        written.append(Path(shutil.copy2(ROOT / name, target)))
    for source, name in SPACE.items():
        written.append(Path(shutil.copy2(ROOT / "space" / source, out / name)))
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="an empty or new folder for the Space")
    args = parser.parse_args(argv)
    files = make_space(args.out)
    print(f"{len(files)} files in {args.out}: push them to a Space (git init, add, commit, push)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
