"""`surfsplat weights`: the named checkpoints, their cache, and what a checkpoint file holds.

    surfsplat weights list                              # every name, what it fits, whether it is cached
    surfsplat weights download re10k-256x256-small      # fetch ahead of time (e.g. on a login node)
    surfsplat weights path re10k-256x256-small          # the cached file, for scripts
    surfsplat weights info runs/tiny                    # preset, resolution, adapter, steps, source

Hugging Face files land in the hub's cache (HF_HOME / HF_HUB_CACHE); other files in torch hub's
cache (TORCH_HOME). With HF_HUB_OFFLINE=1 nothing is downloaded and missing files are errors.
"""

from __future__ import annotations

import argparse
import json


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION")
    sub.required = True
    listing = sub.add_parser("list", help="known names, what they fit, licence, and whether they are cached")
    listing.add_argument("--json", action="store_true", help="machine-readable output")
    download = sub.add_parser("download", help="fetch named weights into their cache now")
    download.add_argument("names", nargs="+", metavar="NAME", help="registry names or hf://owner/repo/path/file")
    download.add_argument("--force", action="store_true", help="fetch again even when cached (a damaged file)")
    path = sub.add_parser("path", help="print the cached file of a name (nothing is downloaded)")
    path.add_argument("name", metavar="NAME")
    info = sub.add_parser("info", help="metadata of a checkpoint (path) or of a name")
    info.add_argument("target", metavar="PATH|NAME")
    info.add_argument("--trust-pickle", action="store_true", help="allow unpickling a release .ckpt's extras")
    info.add_argument("--json", action="store_true", help="machine-readable output")


def run(args: argparse.Namespace) -> int:
    return {"list": _list, "download": _download, "path": _path, "info": _info}[args.action](args)


def _list(args: argparse.Namespace) -> int:
    import torch
    from huggingface_hub import constants

    from ..model.pretrained import cached_file
    from ..model.registry import REGISTRY

    rows = []
    for entry in REGISTRY.values():
        path = cached_file(entry)
        rows.append(
            {
                "name": entry.name,
                "role": entry.role,
                "preset": entry.preset,
                "resolution": list(entry.resolution) if entry.resolution else None,
                "adapter": entry.adapter,
                "cached": str(path) if path else None,
                "location": entry.source.describe(),
                "licence": entry.licence,
                "description": entry.description,
            }
        )
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    header = ("name", "role", "preset", "HxW", "adapter", "cached")
    table = [
        (
            r["name"],
            r["role"],
            r["preset"] or "-",
            "x".join(map(str, r["resolution"])) if r["resolution"] else "-",
            r["adapter"] or "-",
            "yes" if r["cached"] else "no",
        )
        for r in rows
    ]
    widths = [max(len(str(row[i])) for row in [header, *table]) for i in range(len(header))]
    for row in [header, *table]:
        print("  ".join(str(cell).ljust(w) for cell, w in zip(row, widths)).rstrip())
    print()
    for r in rows:
        print(f"{r['name']}: {r['description']}; {r['location']}; licence {r['licence']}")
    print()
    offline = " (offline: HF_HUB_OFFLINE is set)" if constants.HF_HUB_OFFLINE else ""
    print(f"Hugging Face cache: {constants.HF_HUB_CACHE}{offline}")
    print(f"torch hub cache: {torch.hub.get_dir()}/checkpoints")
    return 0


def _download(args: argparse.Namespace) -> int:
    from ..model.pretrained import fetch
    from ..model.registry import lookup

    entries = [lookup(name) for name in args.names]  # every name is checked before anything downloads
    for entry in entries:
        path = fetch(entry, force=args.force)
        print(f"{entry.name}: {path}")
    return 0


def _path(args: argparse.Namespace) -> int:
    from ..model.pretrained import WeightsUnavailable, cached_file
    from ..model.registry import lookup

    entry = lookup(args.name)
    path = cached_file(entry)
    if path is None:
        raise WeightsUnavailable(
            f"{entry.name}: not cached on this machine ({entry.source.describe()}); "
            f"fetch it with `surfsplat weights download {entry.name}`"
        )
    print(path)
    return 0


def _info(args: argparse.Namespace) -> int:
    from ..model.pretrained import describe

    info = describe(args.target, trust_pickle=args.trust_pickle)
    if args.json:
        print(json.dumps(info, indent=1, default=str))
        return 0
    width = max(len(k) for k in info)
    for key, value in info.items():
        if isinstance(value, (list, tuple)):
            value = "x".join(map(str, value)) if key == "resolution" else ", ".join(map(str, value))
        elif isinstance(value, int) and key in ("values", "bytes", "steps", "tensors"):
            value = f"{value:,}"
        print(f"{key.ljust(width)}  {value}")
    return 0
