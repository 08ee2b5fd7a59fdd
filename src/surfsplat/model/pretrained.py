"""Pretrained weights by name or path: find or fetch the file, build the model it fits, load it.

    model = load_pretrained("re10k-256x256-small")      # fetched once into the Hugging Face cache
    model = load_pretrained("runs/tiny")                 # our own checkpoints: paths keep working
    model = load_pretrained("hf://owner/repo/dir/re10k-256x256-surfsplat-base.pth")  # another location
    path = fetch(lookup("unimatch-gmflow-scale1"))       # the cached file (downloaded when missing)

Files are never downloaded by hand-written code: Hugging Face files go through `hf_hub_download`
(its cache, HF_HUB_OFFLINE, HF_HOME / HF_HUB_CACHE, progress bar, resume, checksums); files on
other servers through `torch.hub.download_url_to_file` into torch hub's cache (TORCH_HOME), with the
SHA-256 prefix the file name carries checked. HF_HUB_OFFLINE=1 stops both. A file that is needed,
absent and cannot be fetched is one error naming the file, where it comes from, and the
`surfsplat weights download NAME` command that fetches it ahead of time.

Resolution order of a string: a registry name, then an `hf://` address, then a path. A path that is
spelled like a name is written `./name`.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import logging
from dataclasses import dataclass
from pathlib import Path

import torch

from ..utils.checks import SurfSplatInputError
from .adapter import AdapterConfig
from .checkpoint import load_checkpoint, load_release_weights
from .registry import HF_SCHEME, PACKAGE_WEIGHTS, REGISTRY, Role, Source, WeightsEntry, looks_like_name, lookup
from .surfsplat import PRESETS, SurfSplat, SurfSplatConfig

logger = logging.getLogger("surfsplat.weights")

RELEASE_SUFFIXES = (".ckpt", ".pth", ".pt")  # PyTorch files: the release's layout


class WeightsUnavailable(SurfSplatInputError):
    """A named file that is not on this machine and cannot be fetched now."""


# ----------------------------------------------------------------------------------------- files
def _offline() -> bool:
    from huggingface_hub import constants

    return bool(constants.HF_HUB_OFFLINE)


def torch_hub_file(filename: str) -> Path:
    """Where torch hub caches a downloaded file: `<torch hub dir>/checkpoints/<filename>`.

    `torch.hub.get_dir()` honours TORCH_HOME, then XDG_CACHE_HOME (default ~/.cache/torch/hub).
    """
    return Path(torch.hub.get_dir()) / "checkpoints" / filename


def package_file(filename: str) -> Path:
    return Path(str(importlib.resources.files("surfsplat"))) / PACKAGE_WEIGHTS / filename


def hash_prefix(filename: str) -> str | None:
    """The SHA-256 prefix a torch-hub style file name carries (`vgg16-397923af.pth` -> 397923af)."""
    match = torch.hub.HASH_REGEX.search(filename)
    return match.group(1) if match and match.group(1) else None


def cached_file(entry: WeightsEntry) -> Path | None:
    """The local file of `entry` if this machine has it; never touches the network."""
    source = entry.source
    if source.kind == "hf":
        from huggingface_hub import try_to_load_from_cache

        found = try_to_load_from_cache(source.repo, source.filename, revision=source.revision)
        return Path(found) if isinstance(found, str) else None
    path = torch_hub_file(source.filename) if source.kind == "url" else package_file(source.filename)
    return path if path.is_file() else None


def _fetch_command(entry: WeightsEntry) -> str:
    return f"surfsplat weights download {entry.name}"


def fetch(entry: WeightsEntry, *, force: bool = False) -> Path:
    """The local file of `entry`, downloaded into its cache first when it is missing (or `force`)."""
    sources = [entry.source]
    if entry.layout == "surfsplat":  # our format is a pair: the weights and the configuration beside them
        sources.append(
            dataclasses.replace(entry.source, filename=str(Path(entry.source.filename).with_suffix(".json")))
        )
    paths = []
    for source in sources:
        if source.kind == "package":
            path = package_file(source.filename)
            if not path.is_file():
                raise WeightsUnavailable(
                    f"{entry.name}: {source.filename} is not shipped with this installation of surfsplat ({path})"
                )
            paths.append(path)
        elif source.kind == "hf":
            paths.append(_fetch_hf(entry, source, force))
        else:
            paths.append(_fetch_url(entry, source, force))
    return paths[0]


def _fetch_hf(entry: WeightsEntry, source: Source, force: bool) -> Path:
    from huggingface_hub import constants, hf_hub_download
    from huggingface_hub.errors import (
        EntryNotFoundError,
        LocalEntryNotFoundError,
        OfflineModeIsEnabled,
        RepositoryNotFoundError,
        RevisionNotFoundError,
    )

    where = f"{source.filename} of the Hugging Face repository {source.repo}"
    try:
        return Path(hf_hub_download(source.repo, source.filename, revision=source.revision, force_download=force))
    except (LocalEntryNotFoundError, OfflineModeIsEnabled) as err:
        reason = "offline mode (HF_HUB_OFFLINE) is on" if _offline() else "the hub could not be reached"
        raise WeightsUnavailable(
            f"{entry.name}: {where} is not in the cache ({constants.HF_HUB_CACHE}) and {reason}; "
            f"fetch it where there is internet with `{_fetch_command(entry)}` ({type(err).__name__})"
        ) from None
    except RepositoryNotFoundError:
        raise WeightsUnavailable(
            f"{entry.name}: the Hugging Face repository {source.repo} does not exist or is private; "
            f"give the file's location as {HF_SCHEME}owner/repo/path/file"
        ) from None
    except (EntryNotFoundError, RevisionNotFoundError) as err:
        raise WeightsUnavailable(
            f"{entry.name}: {where} was not found on the hub ({type(err).__name__}); "
            f"give the file's location as {HF_SCHEME}owner/repo/path/file"
        ) from None
    except ValueError as err:  # e.g. force_download while offline
        raise WeightsUnavailable(f"{entry.name}: {where}: {err}") from None


def _fetch_url(entry: WeightsEntry, source: Source, force: bool) -> Path:
    path = torch_hub_file(source.filename)
    if path.is_file() and not force:
        return path
    if _offline():
        raise WeightsUnavailable(
            f"{entry.name}: {path} is not in the torch hub cache and offline mode (HF_HUB_OFFLINE) is on; "
            f"fetch it from {source.url} where there is internet with `{_fetch_command(entry)}`"
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        # torch hub writes to a temporary file and renames it: an interrupted download leaves nothing
        torch.hub.download_url_to_file(source.url, str(path), hash_prefix=hash_prefix(source.filename), progress=True)
    except RuntimeError as err:  # the SHA-256 prefix did not match
        raise WeightsUnavailable(f"{entry.name}: download of {source.url} is corrupt: {err}") from None
    except OSError as err:  # URLError, HTTPError, no route
        raise WeightsUnavailable(
            f"{entry.name}: cannot download {source.url} ({err}); fetch it where there is internet with "
            f"`{_fetch_command(entry)}` and copy {path}"
        ) from None
    return path


def resolve(name_or_path: str | Path, role: Role | None = None) -> tuple[Path, WeightsEntry | None]:
    """(local file, registry entry or None) for a name, an `hf://` address or a path; fetches names."""
    text = str(name_or_path)
    if text.startswith(HF_SCHEME) or (not isinstance(name_or_path, Path) and text in REGISTRY):
        entry = lookup(text, role)
        return fetch(entry), entry
    path = Path(text).expanduser()
    if path.exists() or path.with_suffix(".json").exists():
        return path, None
    if looks_like_name(text):
        lookup(text, role)  # an unknown name: the error lists the known ones
    raise FileNotFoundError(f"{path}: checkpoint not found (no such file or folder)")


# ----------------------------------------------------------------------------------------- models
@dataclass(frozen=True)
class PretrainedInfo:
    """Where a loaded model's weights came from and what they were trained for."""

    name: str  # registry name, hf:// address or path
    path: Path  # the local file
    preset: str | None  # encoder preset
    resolution: tuple[int, int] | None  # (H, W) the weights were trained at, where known
    adapter: str  # adapter mode the model runs with


def resolve_checkpoint(path: str | Path) -> Path:
    """The model file stem of our checkpoint formats, or the release file itself.

    Accepts `x.safetensors` / `x.json`, a training checkpoint folder (`model.safetensors` inside),
    a run folder (its newest `checkpoints/step-*`), or a release `.ckpt` / `.pth`.
    """
    path = Path(path)
    if not path.exists() and not path.with_suffix(".json").exists():
        raise FileNotFoundError(f"{path}: checkpoint not found")
    if path.is_dir():
        if (path / "model.json").is_file():
            return path / "model.safetensors"
        steps = sorted((path / "checkpoints").glob("step-*")) if (path / "checkpoints").is_dir() else []
        steps = [s for s in steps if (s / "model.json").is_file()]
        if steps:
            return steps[-1] / "model.safetensors"
        raise FileNotFoundError(f"{path}: a folder without model.json or checkpoints/step-*/model.json")
    return path


def with_adapter(model: SurfSplat, overrides: dict[str, object]) -> SurfSplat:
    """The same weights under a changed adapter configuration (an inference-time ablation)."""
    fields = set(type(model.cfg.adapter).__dataclass_fields__)
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise SurfSplatInputError(f"adapter overrides: unknown fields {unknown} (known: {sorted(fields)})")
    adapter = dataclasses.replace(model.cfg.adapter, **overrides)
    changed = SurfSplat(SurfSplatConfig(encoder=model.cfg.encoder, adapter=adapter))
    mine, theirs = changed.state_dict(), model.state_dict()
    if set(mine) != set(theirs) or any(mine[k].shape != theirs[k].shape for k in mine):
        raise SurfSplatInputError(
            f"adapter overrides {overrides}: the network's head differs under this adapter; a checkpoint trained "
            "with it is needed (train the ablation instead)"
        )
    changed.load_state_dict(theirs)
    return changed


def load_pretrained(
    name_or_path: str | Path,
    adapter: str | AdapterConfig | None = None,
    device: torch.device | str | None = None,
    *,
    preset: str | None = None,
    trust_pickle: bool = False,
) -> SurfSplat:
    """A SurfSplat model in eval mode from a registry name, an `hf://` address or a checkpoint path.

    adapter: "paper" / "official" (the adapter mode) or a whole AdapterConfig; None keeps what the
    weights were trained with (release files: the release-compatible "official" adapter).
    preset: encoder preset of a release file given by path (default small); for a name it must agree.
    trust_pickle: allow unpickling Python objects a release `.ckpt` stores besides its tensors.
    `model.pretrained_info` tells where the weights came from (`PretrainedInfo`).
    """
    path, entry = resolve(name_or_path, role="model")
    name = str(name_or_path)
    if entry is not None:
        layout = entry.layout
    else:
        path = resolve_checkpoint(path)
        layout = "release" if path.suffix in RELEASE_SUFFIXES else "surfsplat"
    if layout == "release":
        known = entry.preset if entry is not None else None
        if known is not None and preset is not None and preset != known:
            logger.warning("%s holds a %s model: preset %s is ignored", name, known, preset)
        chosen = known or preset or "small"
        if chosen not in PRESETS:
            raise SurfSplatInputError(f"preset: expected one of {sorted(PRESETS)}, got {chosen!r}")
        model = SurfSplat(SurfSplatConfig(encoder=PRESETS[chosen], adapter=_adapter_config(adapter, "official")))
        try:
            load_release_weights(model, path, trust_pickle=trust_pickle)
        except SurfSplatInputError as err:
            if entry is None:
                raise
            raise SurfSplatInputError(
                f"{name}: {err}; if the cached file is damaged, fetch it again with "
                f"`surfsplat weights download {entry.name} --force`"
            ) from None
    else:
        model = load_checkpoint(path)
        if adapter is not None:
            wanted = _adapter_config(adapter, model.cfg.adapter.mode, base=model.cfg.adapter)
            model = with_adapter(model, {f.name: getattr(wanted, f.name) for f in dataclasses.fields(wanted)})
        chosen = preset_of(model)
    resolution = entry.resolution if entry is not None else None
    model.pretrained_info = PretrainedInfo(name, path, chosen, resolution, model.cfg.adapter.mode)
    model = model.eval()
    return model if device is None else model.to(device)


def _adapter_config(adapter: str | AdapterConfig | None, default: str, base: AdapterConfig | None = None):
    if isinstance(adapter, AdapterConfig):
        return adapter
    mode = adapter or default
    if mode not in ("paper", "official"):
        raise SurfSplatInputError(f"adapter: expected 'paper', 'official' or an AdapterConfig, got {adapter!r}")
    return dataclasses.replace(base, mode=mode) if base is not None else AdapterConfig(mode=mode)


def preset_of(model: SurfSplat) -> str | None:
    """The preset name whose encoder configuration the model has (None for a custom one)."""
    return next((name for name, cfg in PRESETS.items() if cfg == model.cfg.encoder), None)


def check_resolution(model: SurfSplat, height: int, width: int) -> str | None:
    """Warn (and return the message) when a model runs at another resolution than it was trained at."""
    info = getattr(model, "pretrained_info", None)
    if info is None or info.resolution is None or tuple(info.resolution) == (height, width):
        return None
    message = (
        f"{info.name} was trained at {info.resolution[0]}x{info.resolution[1]} (HxW) and now runs at "
        f"{height}x{width}; quality may differ from the published numbers"
    )
    logger.warning(message)  # the log's formatter adds the one "warning: " prefix
    return message


# ----------------------------------------------------------------------------------------- info
# Width of the ViT -> the preset whose monocular backbone has it (small ViT-S, base ViT-B, large ViT-L).
_VIT_WIDTH_PRESET = {cfg.vit.embed_dim: name for name, cfg in PRESETS.items() if name != "tiny"}


def detect_layout(keys: list[str]) -> str:
    """Which known layout a state dict's names follow ("unknown" if none)."""
    names = set(keys)
    if any(k.startswith(("encoder.depth_predictor.", "depth_predictor.")) for k in names):
        return "release"
    if any(k.startswith("pretrained.") for k in names) and any(k.startswith("depth_head.") for k in names):
        return "depth-anything-v2"
    if any(k.startswith("backbone.") for k in names) and any(k.startswith("transformer.") for k in names):
        return "unimatch"
    if "features.0.weight" in names:
        return "torchvision-vgg16"
    if "lin0.model.1.weight" in names:
        return "lpips-lin"
    if any(k.startswith("encoder.vit.") for k in names):
        return "surfsplat"
    return "unknown"


def describe_file(path: str | Path, *, trust_pickle: bool = False) -> dict[str, object]:
    """Metadata of a checkpoint file or folder: layout, preset, resolution, adapter, steps, source, size."""
    from ..utils.checks import read_json
    from .checkpoint import FORMAT_NAME, read_state_dict, training_metadata

    path = Path(path)
    stem = resolve_checkpoint(path) if path.is_dir() or path.suffix in (".safetensors", ".json", "") else path
    config_path = stem.with_suffix(".json")
    if config_path.is_file() and stem.suffix in (".safetensors", ".json", ""):
        meta = read_json(config_path)
        if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
            raise SurfSplatInputError(f"{config_path}: not a SurfSplat model configuration")
        cfg = SurfSplatConfig.from_dict(meta.get("config"), source=str(config_path))
        info: dict[str, object] = {
            "file": str(stem.with_suffix(".safetensors")),
            "layout": "surfsplat",
            "preset": next((n for n, c in PRESETS.items() if c == cfg.encoder), "custom"),
            "adapter": cfg.adapter.mode,
        }
        state = stem.parent / "train_state.json"
        if state.is_file():  # a training checkpoint folder: its run configuration says the rest
            document = read_json(state)
            if isinstance(document, dict) and isinstance(document.get("config"), dict):
                info.update(training_metadata(document.get("step"), document["config"]))
        info.update(meta.get("metadata") or {})
        tensors = read_state_dict(stem.with_suffix(".safetensors"))
    else:
        tensors = read_state_dict(stem, trust_pickle=trust_pickle)
        layout = detect_layout(list(tensors))
        info = {"file": str(stem), "layout": layout}
        width = next((v.shape[-1] for k, v in tensors.items() if k.endswith("pretrained.cls_token")), None)
        if layout in ("release", "depth-anything-v2") and width is not None:
            info["preset"] = _VIT_WIDTH_PRESET.get(int(width), f"unknown (ViT width {width})")
        if layout == "release":
            info["adapter"] = "official (trained with the release's adapter)"
    info["tensors"] = len(tensors)
    info["values"] = sum(v.numel() for v in tensors.values())
    info["bytes"] = (
        stem.with_suffix(".safetensors").stat().st_size if info["layout"] == "surfsplat" else stem.stat().st_size
    )
    return info


def describe(name_or_path: str, *, trust_pickle: bool = False) -> dict[str, object]:
    """Registry facts of a name (and of its file when cached), or the metadata of a checkpoint path."""
    if name_or_path.startswith(HF_SCHEME) or name_or_path in REGISTRY:
        entry = lookup(name_or_path)
        info: dict[str, object] = {
            "name": entry.name,
            "role": entry.role,
            "location": entry.source.describe(),
            "licence": entry.licence,
            "description": entry.description,
        }
        for key in ("preset", "resolution", "adapter"):
            if getattr(entry, key) is not None:
                info[key] = getattr(entry, key)
        path = cached_file(entry)
        info["cached"] = str(path) if path is not None else f"no (fetch with `surfsplat weights download {entry.name}`)"
        if path is not None:
            info.update({k: v for k, v in describe_file(path, trust_pickle=trust_pickle).items() if k not in info})
        return info
    path = Path(name_or_path)
    if not path.exists() and not path.with_suffix(".json").exists():
        if looks_like_name(name_or_path):
            lookup(name_or_path)
        raise FileNotFoundError(f"{path}: checkpoint not found (no such file or folder)")
    return describe_file(path, trust_pickle=trust_pickle)
