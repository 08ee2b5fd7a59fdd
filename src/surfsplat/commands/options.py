"""Command-line options several commands share, written once: camera files, the network input
size, the depth range, release checkpoints and forward-pass precision."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..utils.precision import PRECISIONS

Group = argparse._ActionsContainer  # a parser or an argument group


def add_cameras(group: Group, help: str, required: bool = False) -> None:
    group.add_argument("--cameras", type=Path, default=None, required=required, help=help)


def add_size(group: Group, help: str) -> None:
    group.add_argument("--size", nargs=2, type=int, metavar=("H", "W"), default=None, help=help)


def add_depth_range(group: Group, near: float | None, far: float | None, near_help: str, far_help: str) -> None:
    group.add_argument("--near", type=float, default=near, help=near_help)
    group.add_argument("--far", type=float, default=far, help=far_help)


def add_release_options(group: Group, files: str = "a release .ckpt/.pth") -> None:
    """--preset and --trust-pickle: how to read a release checkpoint given by path."""
    group.add_argument("--preset", default=None, help=f"encoder preset of {files} given by path (default small)")
    group.add_argument(
        "--trust-pickle", action="store_true", help="allow unpickling a release .ckpt's hyper-parameters"
    )


def add_device(group: Group, what: str = "every stage") -> None:
    """--device: where the work runs (auto: CUDA when available); only file I/O goes to the host."""
    group.add_argument(
        "--device",
        choices=("auto", "cpu", "cuda"),
        default="auto",
        help=f"device of {what} (auto: CUDA when available); files are read and written on the host",
    )


def add_precision(group: Group) -> None:
    group.add_argument(
        "--precision",
        choices=PRECISIONS,
        default="auto",
        help="forward-pass precision (auto: bf16 where the device has fast bf16, else fp32); rendering is fp32",
    )
