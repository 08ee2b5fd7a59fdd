"""Weights in and out: released SurfSplat checkpoints, Depth Anything V2 backbones, our own files.

Released checkpoints name parameters after the release's module tree (`depth_predictor.backbone.*`,
`gaussian_regressor.*`, ...; Lightning `.ckpt` files prefix them with `encoder.`). They load into
`SurfSplatEncoder` through one explicit table, `RELEASE_KEY_RULES`, from the release's names to
ours; the same table, read backwards, exports our weights in the release layout. Anything missing,
unexpected or of the wrong shape is reported in one error that lists it; nothing loads partially.

The paper's training initialisation loads the same way, each into its branch: Depth Anything V2
files (`depth_anything_v2_vit{s,b,l}.pth`) into the monocular ViT, UniMatch's GMFlow file
(`gmflow-scale1-things-e9887eda.pth`, its `model` entry) into the multi-view CNN and transformer
through `UNIMATCH_KEY_RULES`. The release loads both into its whole depth predictor with
strict=False, so whatever matches by name and shape is filled and the rest silently stays random;
here the branch must match completely, the file's other modules are listed as ignored, and the
report names every parameter that was filled (`LoadReport.filled`, `describe_init`).

Our own checkpoints are a `.safetensors` file (the model's state dict) next to a `.json` file with
the model configuration, so a model is rebuilt without pickle.
"""

from __future__ import annotations

import json
import pickle
import re
import struct
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import Tensor, nn

from ..utils.atomic import atomic_path
from ..utils.atomic import write_text as atomic_write_text
from ..utils.checks import SurfSplatInputError, read_json
from .encoder.encoder import SurfSplatEncoder

# ----------------------------------------------------------------------------- the mapping table
# (release name prefix, our name prefix); `{i}` stands for an integer and is carried over.
# Inside the prefixes the names agree (DINOv2, UniMatch, LDM U-Net and DPT names are kept).
RELEASE_KEY_RULES: tuple[tuple[str, str], ...] = (
    ("depth_predictor.pretrained.", "vit."),
    ("depth_predictor.backbone.", "cnn."),
    ("depth_predictor.transformer.layers.{i}.self_attn.", "transformer.layers.{i}.self_attn."),
    ("depth_predictor.transformer.layers.{i}.cross_attn_ffn.", "transformer.layers.{i}.cross_attn."),
    ("depth_predictor.mv_pyramid.", "mv_pyramid."),
    ("depth_predictor.mono_pyramid.", "mono_pyramid."),
    ("depth_predictor.regressor.{i}.", "scales.{i}.regressor."),
    ("depth_predictor.regressor_residual.{i}.", "scales.{i}.residual."),
    ("depth_predictor.depth_head.{i}.", "scales.{i}.depth_head."),
    ("depth_predictor.upsampler.", "depth_upsampler."),
    ("feature_upsampler.", "feature_upsampler."),
    ("gaussian_regressor.", "gaussian_head.regressor."),
    ("gaussian_head.", "gaussian_head.head."),
)

# Depth Anything V2 files hold the ViT under `pretrained.` and their own DPT head under `depth_head.`;
# only the ViT is SurfSplat's (the release initialises it from these files).
DEPTH_ANYTHING_VIT_PREFIX = "pretrained."
DEPTH_ANYTHING_SKIPPED = ("depth_head.", "pretrained.mask_token")

# Lightning checkpoints of the release: the encoder's parameters, and modules that are not ours.
LIGHTNING_ENCODER_PREFIX = "encoder."

# UniMatch (GMFlow) names -> ours. The release's depth predictor holds UniMatch's CNN and
# transformer under the same names (`depth_predictor.backbone.`, `.transformer.`), which is why its
# strict=False load fills them; these rules equal RELEASE_KEY_RULES with that prefix removed.
UNIMATCH_KEY_RULES: tuple[tuple[str, str], ...] = (
    ("backbone.", "cnn."),
    ("transformer.layers.{i}.self_attn.", "transformer.layers.{i}.self_attn."),
    ("transformer.layers.{i}.cross_attn_ffn.", "transformer.layers.{i}.cross_attn."),
)
# GMFlow's flow propagation and convex upsampler (and UniMatch's optional refinement) have no
# counterpart in SurfSplat.
UNIMATCH_SKIPPED = ("feature_flow_attn.", "upsampler.", "refine_proj.", "refine.")
UNIMATCH_BRANCH = ("cnn.", "transformer.")  # our encoder modules a UniMatch file fills

# Containers of a state dict inside a checkpoint file: Lightning's, and UniMatch's / DepthSplat's.
STATE_DICT_ENTRIES = ("state_dict", "model")

FORMAT_NAME = "surfsplat-model"
FORMAT_VERSION = 1


def _compile(template: str) -> re.Pattern:
    return re.compile("^" + re.escape(template).replace(re.escape("{i}"), r"(?P<i>\d+)"))


_FORWARD = [(_compile(src), dst) for src, dst in RELEASE_KEY_RULES]
_BACKWARD = [(_compile(dst), src) for src, dst in RELEASE_KEY_RULES]
_UNIMATCH = [(_compile(src), dst) for src, dst in UNIMATCH_KEY_RULES]


def _translate(key: str, rules: list[tuple[re.Pattern, str]]) -> str | None:
    for pattern, template in rules:
        match = pattern.match(key)
        if match:
            prefix = template.replace("{i}", match.group("i")) if "i" in pattern.groupindex else template
            return prefix + key[match.end() :]
    return None


def release_to_ours(key: str) -> str | None:
    """Our encoder parameter name for a release name, or None when no rule covers it."""
    return _translate(key, _FORWARD)


def ours_to_release(key: str) -> str | None:
    return _translate(key, _BACKWARD)


def unimatch_to_ours(key: str) -> str | None:
    """Our encoder parameter name for a UniMatch name, or None when no rule covers it."""
    return _translate(key, _UNIMATCH)


# ----------------------------------------------------------------------------- reading files
def read_state_dict(path: str | Path, *, trust_pickle: bool = False) -> dict[str, Tensor]:
    """Tensors of a checkpoint file: safetensors, or PyTorch (`torch.save`, Lightning `.ckpt`).

    A Lightning checkpoint's `state_dict` entry (or a UniMatch file's `model` entry) is returned. PyTorch files are unpickled with
    `weights_only=True`; pass `trust_pickle=True` only for files from a trusted source that also
    store arbitrary Python objects (e.g. OmegaConf hyper-parameters).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such checkpoint file")
    with path.open("rb") as f:
        head = f.read(9)
    if _looks_like_safetensors(head):
        try:
            return load_file(str(path))
        except SafetensorError as err:
            raise SurfSplatInputError(f"{path}: unreadable safetensors file (truncated or corrupt): {err}") from None
    if not (head.startswith(b"PK\x03\x04") or head[:1] == b"\x80"):
        raise SurfSplatInputError(f"{path}: not a checkpoint (neither a PyTorch nor a safetensors file)")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=not trust_pickle)
    except pickle.UnpicklingError as err:
        if "weights_only" in str(err) or "Weights only" in str(err):
            raise SurfSplatInputError(
                f"{path}: the file stores Python objects besides tensors; if you trust its source, "
                f"load it with trust_pickle=True ({str(err).splitlines()[0]})"
            ) from None
        raise SurfSplatInputError(f"{path}: corrupt PyTorch checkpoint: {err}") from None
    except (RuntimeError, EOFError, ValueError) as err:
        raise SurfSplatInputError(
            f"{path}: unreadable PyTorch checkpoint (truncated or corrupt): {str(err).splitlines()[0]}"
        ) from None
    if isinstance(obj, Mapping):
        container = next((k for k in STATE_DICT_ENTRIES if isinstance(obj.get(k), Mapping)), None)
        obj = obj[container] if container is not None else obj
    if not isinstance(obj, Mapping):
        raise SurfSplatInputError(
            f"{path}: expected a state dict (a mapping of names to tensors), got {type(obj).__name__}"
        )
    bad = [k for k, v in obj.items() if not isinstance(v, Tensor)]
    if bad:
        raise SurfSplatInputError(f"{path}: entries that are not tensors: {_listing(bad)}")
    return dict(obj)


def _looks_like_safetensors(head: bytes) -> bool:
    # 8-byte little-endian header length, then the JSON header
    return len(head) == 9 and head[8:9] == b"{" and 0 < struct.unpack("<Q", head[:8])[0] < 2**32


def _listing(keys: list[str], limit: int = 20) -> str:
    shown = ", ".join(keys[:limit])
    return shown + (f", ... and {len(keys) - limit} more" if len(keys) > limit else "")


# ----------------------------------------------------------------------------- loading
@dataclass
class LoadReport:
    loaded: int  # tensors copied into the model
    ignored: list[str]  # keys of the file deliberately skipped (modules that are not ours)
    filled: list[str] = field(default_factory=list)  # encoder state-dict keys the file set


def _encoder_of(model: nn.Module) -> SurfSplatEncoder:
    encoder = model if isinstance(model, SurfSplatEncoder) else getattr(model, "encoder", None)
    if not isinstance(encoder, SurfSplatEncoder):
        raise SurfSplatInputError(f"expected a SurfSplat model or encoder, got {type(model).__name__}")
    return encoder


def _load_exact(
    module: nn.Module,
    tensors: Mapping[str, Tensor],
    source: str,
    what: str,
    prefixes: tuple[str, ...] = ("",),
) -> list[str]:
    """Copy `tensors` into the keys of `module` under `prefixes`; any missing, unexpected or
    mis-shaped key is one error and nothing is copied. Returns the keys set."""
    expected = {k: v for k, v in module.state_dict().items() if k.startswith(prefixes)}
    missing = [k for k in expected if k not in tensors]
    unexpected = [k for k in tensors if k not in expected]
    misshaped = [
        f"{k} {tuple(tensors[k].shape)} (expected {tuple(expected[k].shape)})"
        for k in tensors
        if k in expected and tensors[k].shape != expected[k].shape
    ]
    problems = []
    if missing:
        problems.append(f"missing {len(missing)}: {_listing(missing)}")
    if unexpected:
        problems.append(f"unexpected {len(unexpected)}: {_listing(unexpected)}")
    if misshaped:
        problems.append(f"wrong shape {len(misshaped)}: {_listing(misshaped)}")
    if problems:
        raise SurfSplatInputError(f"{source}: does not match the {what}; " + "; ".join(problems))
    bad = nonfinite_tensors(tensors)
    if bad:
        raise SurfSplatInputError(f"{source}: {len(bad)} tensors hold NaN or inf: {_listing(bad)}")
    with torch.no_grad():
        for key, value in expected.items():
            value.copy_(tensors[key].to(value.dtype))
    return list(expected)


def load_release_weights(
    model: nn.Module, source: str | Path | Mapping[str, Tensor], *, trust_pickle: bool = False
) -> LoadReport:
    """Load a released SurfSplat encoder (state dict, `.pth`, Lightning `.ckpt`) into `model`.

    `model` is a `SurfSplat` or a `SurfSplatEncoder` built with the matching preset. Keys of a
    Lightning checkpoint outside `encoder.` (decoder, losses) are ignored and listed in the report.
    """
    encoder = _encoder_of(model)
    name = str(source) if not isinstance(source, Mapping) else "state dict"
    tensors = read_state_dict(source, trust_pickle=trust_pickle) if not isinstance(source, Mapping) else dict(source)
    ignored: list[str] = []
    if any(k.startswith(LIGHTNING_ENCODER_PREFIX) for k in tensors):
        ignored = [k for k in tensors if not k.startswith(LIGHTNING_ENCODER_PREFIX)]
        n = len(LIGHTNING_ENCODER_PREFIX)
        tensors = {k[n:]: v for k, v in tensors.items() if k.startswith(LIGHTNING_ENCODER_PREFIX)}
    mapped: dict[str, Tensor] = {}
    unmapped = []
    for key, value in tensors.items():
        ours = release_to_ours(key)
        if ours is None:
            unmapped.append(key)
        else:
            mapped[ours] = value
    if unmapped:
        raise SurfSplatInputError(f"{name}: {len(unmapped)} keys are not release encoder names: {_listing(unmapped)}")
    size = sum(p.numel() for p in encoder.parameters())
    filled = _load_exact(encoder, mapped, name, f"{size:,}-parameter encoder (release layout)")
    return LoadReport(loaded=len(filled), ignored=ignored, filled=filled)


def export_release_state_dict(model: nn.Module) -> dict[str, Tensor]:
    """Our encoder's weights under the release's names (the inverse of `load_release_weights`)."""
    out = {}
    for key, value in _encoder_of(model).state_dict().items():
        release = ours_to_release(key)
        if release is None:
            raise RuntimeError(f"no release name for encoder parameter {key}; extend RELEASE_KEY_RULES")
        out[release] = value
    return out


def load_depth_anything_v2(model: nn.Module, source: str | Path | Mapping[str, Tensor]) -> LoadReport:
    """Initialise the ViT from Depth Anything V2 weights (`depth_anything_v2_vit{s,b,l}.pth`).

    The file's ViT (`pretrained.*`) must match the model's ViT exactly; its own DPT head
    (`depth_head.*`) and mask token are not part of SurfSplat and are reported as ignored.
    """
    encoder = _encoder_of(model)
    name = str(source) if not isinstance(source, Mapping) else "state dict"
    tensors = read_state_dict(source) if not isinstance(source, Mapping) else dict(source)
    ignored = [k for k in tensors if k.startswith(DEPTH_ANYTHING_SKIPPED)]
    n = len(DEPTH_ANYTHING_VIT_PREFIX)
    vit = {}
    stray = []
    for key, value in tensors.items():
        if key in ignored:
            continue
        if key.startswith(DEPTH_ANYTHING_VIT_PREFIX):
            vit[key[n:]] = value
        else:
            stray.append(key)
    if stray:
        raise SurfSplatInputError(f"{name}: not a Depth Anything V2 file; unexpected keys: {_listing(stray)}")
    filled = _load_exact(
        encoder.vit, vit, name, f"ViT ({encoder.cfg.vit.embed_dim}-wide, {encoder.cfg.vit.depth} blocks)"
    )
    return LoadReport(loaded=len(filled), ignored=ignored, filled=["vit." + k for k in filled])


def load_unimatch(model: nn.Module, source: str | Path | Mapping[str, Tensor]) -> LoadReport:
    """Initialise the multi-view branch (CNN + transformer) from a UniMatch / GMFlow file.

    The file (`gmflow-scale1-things-e9887eda.pth`: `{"model": state dict}`) must fill every CNN and
    transformer tensor of the model (presets small, base and large have UniMatch's widths); its flow
    propagation and upsampler are reported as ignored. Everything else keeps its current values.
    """
    encoder = _encoder_of(model)
    name = str(source) if not isinstance(source, Mapping) else "state dict"
    tensors = read_state_dict(source) if not isinstance(source, Mapping) else dict(source)
    ignored = [k for k in tensors if k.startswith(UNIMATCH_SKIPPED)]
    mapped: dict[str, Tensor] = {}
    stray = []
    for key, value in tensors.items():
        if key in ignored:
            continue
        ours = unimatch_to_ours(key)
        if ours is None:
            stray.append(key)
        else:
            mapped[ours] = value
    if stray:
        raise SurfSplatInputError(f"{name}: not a UniMatch file; unexpected keys: {_listing(stray)}")
    cfg = encoder.cfg
    what = (
        f"multi-view branch (CNN {cfg.cnn_dims} -> {cfg.feature_channels}, {cfg.transformer_layers} transformer layers)"
    )
    filled = _load_exact(encoder, mapped, name, what, prefixes=UNIMATCH_BRANCH)
    return LoadReport(loaded=len(filled), ignored=ignored, filled=filled)


def describe_init(model: nn.Module, reports: Mapping[str, LoadReport]) -> list[str]:
    """Lines saying which encoder modules each initialisation filled and which stay random.

    reports: label (e.g. "monodepth depth-anything-v2-vits") -> what its load returned. Modules are
    the encoder's top-level children (`vit`, `cnn`, `transformer`, `scales`, `gaussian_head`, ...).
    """
    state = _encoder_of(model).state_dict()

    def summary(keys: list[str]) -> str:
        groups: dict[str, list[int]] = {}
        for key in keys:
            tally = groups.setdefault(key.split(".")[0], [0, 0])
            tally[0] += 1
            tally[1] += state[key].numel()
        return ", ".join(f"{g} ({n} tensors, {p:,} values)" for g, (n, p) in groups.items()) or "nothing"

    lines, filled = [], set()
    for label, report in reports.items():
        lines.append(f"{label}: filled {summary(report.filled)}")
        if report.ignored:
            lines.append(f"{label}: ignored {len(report.ignored)} tensors of the file ({_listing(report.ignored, 4)})")
        filled.update(report.filled)
    lines.append(f"random initialisation: {summary([k for k in state if k not in filled])}")
    return lines


# ----------------------------------------------------------------------------- our own format
def _paths(path: str | Path) -> tuple[Path, Path]:
    path = Path(path)
    stem = path.with_suffix("") if path.suffix in (".safetensors", ".json") else path
    return stem.with_suffix(".safetensors"), stem.with_suffix(".json")


def save_checkpoint(model: nn.Module, path: str | Path, metadata: Mapping | None = None) -> tuple[Path, Path]:
    """Write `<stem>.safetensors` (weights) and `<stem>.json` (configuration) for a SurfSplat model.

    metadata: JSON-ready facts about the weights stored beside the configuration (`surfsplat weights
    info` shows them), e.g. {"preset": "tiny", "resolution": [64, 64], "steps": 200, "source": "..."}.
    """
    from .surfsplat import SurfSplat

    if not isinstance(model, SurfSplat):
        raise SurfSplatInputError(f"save_checkpoint expects a SurfSplat model, got {type(model).__name__}")
    weights_path, config_path = _paths(path)
    tensors = {k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}
    bad = nonfinite_tensors(tensors)
    if bad:  # a model that diverged is never saved as if it were usable
        raise FloatingPointError(f"{weights_path}: not written, the weights hold NaN or inf ({_listing(bad)})")
    document = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "config": model.cfg.to_dict()}
    if metadata:
        document["metadata"] = dict(metadata)
    # The configuration is written last: a weights file without its configuration is not a checkpoint
    # that `load_checkpoint` opens, so an interrupted save never passes for a complete one.
    with atomic_path(weights_path) as tmp:
        save_file(tensors, str(tmp), metadata={"format": FORMAT_NAME, "version": str(FORMAT_VERSION)})
    atomic_write_text(config_path, json.dumps(document, indent=2))
    return weights_path, config_path


def nonfinite_tensors(tensors: Mapping[str, Tensor]) -> list[str]:
    """Names of the floating-point tensors holding NaN or inf, in the mapping's order."""
    return [k for k, v in tensors.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]


def training_metadata(step: int, config: Mapping) -> dict:
    """Preset, resolution, adapter, steps and source of a model trained by `surfsplat train`, from the
    step and the run's configuration (TrainConfig.to_dict())."""
    model = config.get("model") or {}
    data = config.get("data") or {}
    init = model.get("init") or {}
    starts = [
        f"{kind} {value}"
        for kind, value in (
            ("checkpoint", model.get("init_checkpoint")),
            ("release", model.get("release_weights")),
            *init.items(),
        )
        if value
    ]
    roots = f" ({', '.join(data.get('roots') or [])})" if data.get("roots") else ""
    origin = f", initialised from {'; '.join(starts)}" if starts else ", from random weights"
    return {
        "preset": model.get("preset"),
        "resolution": list(data["image_shape"]) if data.get("image_shape") else None,
        "adapter": (model.get("adapter") or {}).get("mode"),
        "steps": step,
        "source": f"surfsplat train on {data.get('dataset')} data{roots}{origin}",
    }


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu"):
    """Rebuild a SurfSplat model saved by `save_checkpoint`."""
    from .surfsplat import SurfSplat, SurfSplatConfig

    weights_path, config_path = _paths(path)
    if not config_path.is_file():
        raise FileNotFoundError(f"{config_path}: configuration file of the checkpoint is missing")
    meta = read_json(config_path)
    if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
        raise SurfSplatInputError(
            f"{config_path}: not a SurfSplat model configuration (format must be '{FORMAT_NAME}')"
        )
    if meta.get("version") != FORMAT_VERSION:
        raise SurfSplatInputError(
            f"{config_path}: unsupported version {meta.get('version')} (expected {FORMAT_VERSION})"
        )
    cfg = SurfSplatConfig.from_dict(meta.get("config"), source=str(config_path))
    model = SurfSplat(cfg)
    tensors = read_state_dict(weights_path)
    _load_exact(model, tensors, str(weights_path), "model described by " + config_path.name)
    return model.to(map_location)
