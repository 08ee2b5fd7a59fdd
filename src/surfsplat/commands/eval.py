"""`surfsplat eval`: standard and HRRC metrics over an evaluation index, in the paper's table layout.

    surfsplat eval --checkpoint runs/tiny --data data/re10k/test --index evaluation_index_re10k.json
    surfsplat eval --checkpoint re10k.ckpt --trust-pickle --data data/re10k/test --index idx.json --size 256 256
    surfsplat eval --data data/test --index idx.json \\
        --compare "full=runs/full" "w/o FAB=runs/full:opacity_max=1.0" "3DGS=runs/gauss3d"

Writes metrics.json (means, averages, every scene, timing, peak memory), per_scene.csv and
table.txt to --out, and prints the table: standard / x2 / x4 / average, PSNR, SSIM, LPIPS.
--geometry adds depth, normal and surface errors against exact truth for procedural scenes (the
chunks `surfsplat demo` writes under its eval data, or `write_synthetic_chunks`): per scene in
metrics.json and geometry_per_scene.csv, means in the table. Scenes without truth are named and
left out; when none has truth the table says so instead of printing numbers.
LPIPS needs torchvision's VGG16 file and the LPIPS v0.1 heads (see --lpips-vgg); without them the
table says "LPIPS unavailable: <reason>" and prints no number.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..utils.checks import SurfSplatInputError, check_output_dir
from .export import add_compact_argument
from .options import add_depth_range, add_precision, add_release_options, add_size


def add_arguments(parser: argparse.ArgumentParser) -> None:
    which = parser.add_argument_group("models")
    which.add_argument(
        "--checkpoint",
        help="a weights name (`surfsplat weights list`, e.g. re10k-256x256-small), hf://owner/repo/file, "
        "our checkpoint (run folder, checkpoint folder, model.safetensors) or a release .ckpt/.pth",
    )
    which.add_argument(
        "--compare",
        nargs="+",
        metavar="[NAME=]CKPT[:field=value,...]",
        default=None,
        help="several checkpoints or adapter ablations side by side (e.g. 'w/o FAB=runs/x:opacity_max=1.0')",
    )
    add_release_options(which, "release .ckpt/.pth files")
    data = parser.add_argument_group("data")
    data.add_argument("--data", nargs="+", required=True, type=Path, help="chunk folders (*.torch + index.json)")
    data.add_argument(
        "--index", required=True, type=Path, help="evaluation index JSON (context/target views per scene)"
    )
    add_size(data, "rescale and centre-crop views to H x W first (the release uses 256 256 for RE10K)")
    add_depth_range(data, 0.5, 100.0, "near depth bound (RealEstate10K: 0.5)", "far depth bound (RealEstate10K: 100)")
    data.add_argument("--max-entries", type=int, default=None, help="evaluate only the first N entries")
    metric = parser.add_argument_group("metrics")
    metric.add_argument(
        "--hrrc-upsample",
        choices=("bicubic", "bilinear"),
        default="bicubic",
        help="HRRC ground-truth upsampling: bicubic (the paper) or bilinear (the release's code)",
    )
    metric.add_argument("--factors", nargs="+", type=int, default=[1, 2, 4], help="render scales (1 = standard)")
    metric.add_argument(
        "--mode", choices=("auto", "surfel", "ewa"), default="auto", help="rasterization (auto follows the adapter)"
    )
    add_compact_argument(
        metric, "score the compacted reconstruction (surfsplat.compact, level 1-5) to measure what compaction costs"
    )
    metric.add_argument("--lpips-vgg", default=None, help="torchvision's vgg16-397923af.pth")
    metric.add_argument("--lpips-lin", default=None, help="the lpips package's v0.1 vgg.pth")
    geometry = parser.add_argument_group("geometry (procedural scenes: exact truth)")
    geometry.add_argument(
        "--geometry",
        action="store_true",
        help="also score depth/normals at the target views and the surfels' and TSDF mesh's surfaces against "
        "exact truth (procedural scenes only; other scenes are named and left out)",
    )
    geometry.add_argument(
        "--geometry-threshold", type=float, default=0.05, help="F-score distance in scene units (default 0.05 m)"
    )
    geometry.add_argument(
        "--geometry-min-alpha", type=float, default=0.1, help="render pixels count where alpha >= this (default 0.1)"
    )
    parser.add_argument(
        "--out", type=Path, default=Path("outputs/eval"), help="folder for metrics.json, per_scene.csv, table.txt"
    )
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    add_precision(parser)
    parser.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    from ..data.eval_index import EvaluationIndex
    from ..evaluation import (
        RESULT_FILES,
        EvalConfig,
        SampleCounts,
        evaluate,
        format_results,
        iter_index_samples,
        write_results,
    )
    from ..metrics.lpips import try_load_lpips
    from ..model.loading import ModelSpec, load_model
    from ..reconstruction.pipeline import resolve_device as _device

    if (args.checkpoint is None) == (args.compare is None):
        raise SurfSplatInputError("give --checkpoint or --compare (one of them)")
    specs = (
        [ModelSpec(args.checkpoint, preset=args.preset, trust_pickle=args.trust_pickle)]
        if args.checkpoint is not None
        else [ModelSpec.parse(text, args.preset, args.trust_pickle) for text in args.compare]
    )
    for folder in args.data:
        if not folder.is_dir():
            raise FileNotFoundError(f"{folder}: chunk folder not found")
    check_output_dir(args.out, "--out", inputs=[args.index, *args.data], writes=RESULT_FILES)
    index = EvaluationIndex.load(args.index)
    if args.size is not None and (args.size[0] < 1 or args.size[1] < 1):
        raise SurfSplatInputError(f"--size: expected positive H W, got {args.size}")
    if args.max_entries is not None and args.max_entries < 1:
        raise SurfSplatInputError(f"--max-entries: expected at least 1, got {args.max_entries}")
    geometry = None
    if args.geometry:
        from ..evaluation.geometry import GeometryConfig

        if 1 not in args.factors:
            raise SurfSplatInputError("--geometry scores the x1 renders: --factors must include 1")
        geometry = GeometryConfig(min_alpha=args.geometry_min_alpha, threshold=args.geometry_threshold)
    config = EvalConfig(
        geometry=geometry,
        factors=tuple(args.factors),
        upsample=args.hrrc_upsample,
        mode=args.mode,
        max_entries=args.max_entries,
        progress=not args.no_progress,
        compact=args.compact,
        precision=args.precision,
    )
    device = _device(args.device)
    models = [load_model(spec, device) for spec in specs]  # every checkpoint is read before the first scene runs
    names = [name for _, name in models]
    if len(set(names)) != len(names):
        raise SurfSplatInputError(f"--compare: model names must differ, got {names} (name them: NAME=CKPT)")
    lpips = try_load_lpips(args.lpips_vgg, args.lpips_lin, device=device)

    # One (checked) sample stream per model, each with its own counts; the folders are validated here,
    # before any model runs.
    counts = [SampleCounts() for _ in models]
    sample_sets = [
        iter_index_samples(
            args.data, index, tuple(args.size) if args.size else None, args.near, args.far, args.max_entries, c
        )
        for c in counts
    ]
    results = {}
    non_null = sum(v is not None for v in index.entries.values())
    total = min(non_null, args.max_entries) if args.max_entries else non_null
    for (model, name), samples in zip(models, sample_sets):
        results[name] = evaluate(model, samples, config, lpips=lpips, name=name, total=total)
    first = counts[0]
    written = write_results(results, args.out, first)
    print(format_results(results))
    print(
        f"entries: {first.evaluated} evaluated, {first.excluded} excluded by the index (null), "
        f"{len(first.missing)} in the index but not in the data, {first.not_in_index} data scenes not in the index"
    )
    for key, path in written.items():
        print(f"  {key}: {path}")
    return 0
