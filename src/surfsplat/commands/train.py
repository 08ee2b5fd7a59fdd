"""`surfsplat train`: train SurfSplat from a preset, a JSON config, or a checkpoint to resume.

    surfsplat train --preset tiny --out runs/tiny                        # CPU smoke run, synthetic rooms
    surfsplat train --preset small --roots data/re10k/train --val-roots data/re10k/test \\
        --paper-init --out runs/small        # Depth Anything V2 + UniMatch weights, as the paper trains
    surfsplat train --resume --out runs/small                            # continue exactly where it stopped
    torchrun --nproc_per_node 4 -m surfsplat train --preset small ...     # data-parallel, same options

Options override the preset (or the JSON config, or the resumed run's stored config); anything
else is reachable with `--set section.field=VALUE` (VALUE in JSON, e.g. --set optim.grad_clip=1.0).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from ..render.types import BACKENDS
from ..train.checkpoint import latest_checkpoint
from ..train.config import TRAIN_PRESETS, TrainConfig, config_from_dict, override, paper_init, train_preset
from ..train.loop import fit, read_checkpoint_config
from ..utils.checks import SurfSplatInputError, check_output_dir, read_json

# option dest -> dotted config field it sets
_FIELDS: dict[str, str] = {
    "out": "out_dir",
    "steps": "steps",
    "batch_size": "batch_size",
    "seed": "seed",
    "precision": "precision",
    "device": "device",
    "cpu_threads": "cpu_threads",
    "dataset": "data.dataset",
    "roots": "data.roots",
    "val_roots": "data.val_roots",
    "val_index": "data.val_index",
    "image_shape": "data.image_shape",
    "num_workers": "data.num_workers",
    "lr": "optim.lr",
    "vit_lr": "optim.vit_lr",
    "lpips_weight": "loss.lpips_weight",
    "lpips_vgg": "loss.lpips_vgg_path",
    "lpips_lin": "loss.lpips_lin_path",
    "checkpoint_every": "checkpoint_every",
    "val_every": "val_every",
    "log_every": "log_every",
    "init_checkpoint": "model.init_checkpoint",
    "release_weights": "model.release_weights",
    "init_monodepth": "model.init.monodepth",
    "init_mvdepth": "model.init.mvdepth",
    "render_backend": "model.render_backend",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    source = parser.add_argument_group("what to train")
    source.add_argument("--preset", choices=sorted(TRAIN_PRESETS), help="start from a preset configuration")
    source.add_argument("--config", help="start from a JSON configuration (e.g. a run's config.json)")
    source.add_argument(
        "--resume",
        nargs="?",
        const="latest",
        default=None,
        metavar="CHECKPOINT",
        help="continue a run: its newest checkpoint under --out, or the given checkpoint folder",
    )
    source.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="override any field by dotted path, VALUE in JSON (repeatable)",
    )
    common = parser.add_argument_group("common overrides")
    common.add_argument("--out", help="output folder (checkpoints/, tensorboard/, metrics.jsonl)")
    common.add_argument("--steps", type=int, help="total optimizer steps")
    common.add_argument("--batch-size", type=int, help="global batch size (split across ranks)")
    common.add_argument("--seed", type=int)
    common.add_argument("--precision", choices=("auto", "fp32", "bf16", "fp16"))
    common.add_argument("--device", choices=("auto", "cpu", "cuda"))
    common.add_argument(
        "--render-backend",
        choices=BACKENDS,
        help="renderer of the training views (auto: gsplat on CUDA, the compiled one on CPU)",
    )
    common.add_argument(
        "--cpu-threads", type=int, help="CPU threads per rank (torch and the compiled renderer; 0: defaults)"
    )
    common.add_argument("--dataset", choices=("synthetic", "chunks"))
    common.add_argument("--roots", nargs="+", help="training chunk folders")
    common.add_argument("--val-roots", nargs="+", help="held-out chunk folders for validation")
    common.add_argument("--val-index", help="evaluation index JSON fixing the validation views")
    common.add_argument("--image-shape", nargs=2, type=int, metavar=("H", "W"))
    common.add_argument("--num-workers", type=int, help="data-loader workers per rank")
    common.add_argument("--lr", type=float, help="peak learning rate (all but the ViT)")
    common.add_argument("--vit-lr", type=float, help="peak learning rate of the pretrained ViT")
    common.add_argument(
        "--lpips-weight", type=float, help="lambda of the LPIPS term (0: MSE only, no VGG files needed)"
    )
    common.add_argument("--lpips-vgg", help="torchvision's vgg16-397923af.pth")
    common.add_argument("--lpips-lin", help="the lpips package's v0.1 vgg.pth")
    common.add_argument("--checkpoint-every", type=int)
    common.add_argument("--val-every", type=int, help="steps between validations (0: never)")
    common.add_argument("--log-every", type=int)
    common.add_argument("--init-checkpoint", help="our model checkpoint (path or weights name) to start from")
    common.add_argument("--release-weights", help="a released SurfSplat checkpoint (path or name) to fine-tune")
    common.add_argument(
        "--init-monodepth",
        "--depth-anything",
        dest="init_monodepth",
        metavar="NAME|PATH",
        help="Depth Anything V2 weights for the monocular ViT (e.g. depth-anything-v2-vits)",
    )
    common.add_argument(
        "--init-mvdepth",
        metavar="NAME|PATH",
        help="UniMatch weights for the multi-view CNN and transformer (e.g. unimatch-gmflow-scale1)",
    )
    common.add_argument(
        "--paper-init",
        action="store_true",
        help="start as the paper does: the preset's Depth Anything V2 ViT and UniMatch's GMFlow weights",
    )
    common.add_argument("--no-progress", action="store_true", help="no progress bar (logs still go to TensorBoard)")


def _parse_set(items: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise SurfSplatInputError(f"--set {item!r}: expected FIELD=VALUE")
        key, text = item.split("=", 1)
        try:
            out[key.strip()] = json.loads(text)
        except ValueError:
            out[key.strip()] = text  # a bare word is a string (paths, presets)
    return out


def build_config(args: argparse.Namespace) -> tuple[TrainConfig, str | Path | bool]:
    """(configuration, resume target) from the parsed options."""
    starts = [name for name in ("preset", "config") if getattr(args, name)]
    if len(starts) > 1:
        raise SurfSplatInputError("--preset and --config: give one of them")
    resume: str | Path | bool = False
    if args.resume is not None:
        if args.resume == "latest":
            if args.out is None and not starts:
                raise SurfSplatInputError("--resume: give --out (the run folder) or a checkpoint folder")
            resume = True
        else:
            resume = Path(args.resume)
    if args.preset:
        config = train_preset(args.preset)
    elif args.config:
        path = Path(args.config)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: configuration file not found")
        config = config_from_dict(read_json(path))
    elif resume is not False:
        folder = resume if isinstance(resume, Path) else latest_checkpoint(args.out)
        if folder is None:
            raise SurfSplatInputError(f"--resume: no checkpoint in {Path(args.out) / 'checkpoints'}")
        config = read_checkpoint_config(folder)
    else:
        raise SurfSplatInputError("give --preset, --config or --resume")
    changes: dict[str, Any] = {}
    if args.paper_init:
        preset = _parse_set(args.set).get("model.preset", config.model.preset)
        changes.update(paper_init(preset))
    changes.update({field: getattr(args, dest) for dest, field in _FIELDS.items() if getattr(args, dest) is not None})
    if args.no_progress:
        changes["progress"] = False
    changes.update(_parse_set(args.set))
    return (override(config, changes) if changes else config), resume


def run(args: argparse.Namespace) -> int:
    config, resume = build_config(args)
    check_output_dir(config.out_dir, "--out" if args.out is not None else "out_dir")
    result = fit(config, resume=resume)
    if result.rank != 0:
        return 0  # rank 0 reports for the whole run
    if result.losses:
        print(
            f"trained steps {result.start_step}..{result.step}: loss {result.losses[0][1]:.5f} -> {result.losses[-1][1]:.5f}"
        )
    for step, metrics in sorted(result.validation.items()):
        shown = ", ".join(f"{k} {v:.4f}" for k, v in metrics.items() if k != "num_images")
        print(f"validation at step {step} ({int(metrics['num_images'])} images): {shown}")
    if result.checkpoint is not None:
        print(f"checkpoint: {result.checkpoint}")
    return 0
