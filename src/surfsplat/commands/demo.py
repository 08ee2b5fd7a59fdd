"""`surfsplat demo [--out DIR]`: the whole product on a fresh machine, nothing downloaded (see
`surfsplat.demo` for what it does).

    surfsplat demo --out outputs/demo            # about 5-9 minutes on a shared 2-core CPU
    surfsplat demo --out outputs/quick --quick   # a reduced budget (tests, smoke runs)
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from ..demo import DemoConfig, run_demo
from ..utils.checks import SurfSplatInputError, check_output_dir
from ..utils.precision import PRECISIONS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("outputs/demo"), help="output folder")
    parser.add_argument("--quick", action="store_true", help="a reduced budget (32 px, a few steps; for tests)")
    parser.add_argument("--steps", type=int, default=None, help="training steps (default 150)")
    parser.add_argument(
        "--train-minutes",
        type=float,
        default=None,
        help="hard limit of training (default 4): stopped there, the newest checkpoint is used",
    )
    parser.add_argument("--image-size", type=int, default=None, help="square image size, a multiple of 16 (default 64)")
    parser.add_argument("--eval-scenes", type=int, default=None, help="held-out rooms (default 3)")
    parser.add_argument(
        "--precision",
        choices=PRECISIONS,
        default="auto",
        help="training and evaluation precision (auto: bf16 where the device has fast bf16, else fp32)",
    )


def run(args: argparse.Namespace) -> int:
    config = DemoConfig.quick() if args.quick else DemoConfig()
    changes = {
        k: v
        for k, v in (("steps", args.steps), ("image_size", args.image_size), ("eval_scenes", args.eval_scenes))
        if v is not None
    }
    changes["precision"] = args.precision
    if args.train_minutes is not None:
        changes["train_seconds"] = args.train_minutes * 60
    config = replace(config, **changes)
    check_output_dir(args.out, "--out")
    for stale in ("train", "data"):
        if (args.out / stale).exists() and any((args.out / stale).iterdir()):
            raise SurfSplatInputError(
                f"--out {args.out}: already holds a demo run ({stale}/ is not empty); choose an empty folder"
            )
    run_demo(config, args.out)
    return 0
