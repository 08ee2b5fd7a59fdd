"""LPIPS-VGG v0.1 (Zhang et al., CVPR 2018) without torchvision.

The distance between two images x0, x1 in [0, 1]:
  1. map to [-1, 1] (the lpips package's `normalize=True`), then the package's fixed scaling
     layer (x - shift) / scale;
  2. VGG16 conv features after relu1_2, relu2_2, relu3_3, relu4_3, relu5_3;
  3. each feature map divided by its channel-wise L2 norm (+1e-10) at every pixel;
  4. squared difference, a learned non-negative 1x1 projection to one channel (the "linear
     heads"), spatial mean; the sum over the five layers is the distance.

Weights are never bundled and never downloaded while computing a metric: the trunk is
torchvision's ImageNet file `vgg16-397923af.pth` (keys `features.N.weight/bias`, classifier keys
ignored) and the heads are the lpips package's `weights/v0.1/vgg.pth` (keys `lin{k}.model.1.weight`).
`surfsplat weights download lpips-vgg16 lpips-vgg-lin` fetches both into torch hub's cache, where
they are found by default (the registry names `lpips-vgg16` / `lpips-vgg-lin` may also be given in
place of paths). When either is missing, loading raises `LpipsUnavailable` ("LPIPS unavailable:
<reason>"); there is no way to build this module without weights, so no report can print a number
from random weights.
"""

from __future__ import annotations

import importlib.util
import pickle
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..utils.checks import SurfSplatInputError, check_tensor

VGG16_FILENAME = "vgg16-397923af.pth"  # torchvision's ImageNet VGG16, in the torch hub cache
LIN_FILENAME = "vgg.pth"  # the lpips package's v0.1 linear heads for the VGG trunk

# (torchvision index of each 3x3 conv, in and out channels) per VGG16 stage; a 2x2 max pool
# precedes every stage but the first, and LPIPS taps the ReLU after each stage's last conv.
VGG16_STAGES: tuple[tuple[tuple[int, int, int], ...], ...] = (
    ((0, 3, 64), (2, 64, 64)),
    ((5, 64, 128), (7, 128, 128)),
    ((10, 128, 256), (12, 256, 256), (14, 256, 256)),
    ((17, 256, 512), (19, 512, 512), (21, 512, 512)),
    ((24, 512, 512), (26, 512, 512), (28, 512, 512)),
)
LPIPS_CHANNELS = tuple(stage[-1][2] for stage in VGG16_STAGES)  # (64, 128, 256, 512, 512)
MIN_SIZE = 16  # four 2x pools before relu5_3: smaller images leave that layer empty

# The lpips package's ScalingLayer (v0.1): inputs in [-1, 1] are shifted and scaled per channel,
# close to ImageNet normalisation expressed for [-1, 1] inputs.
LPIPS_SHIFT = (-0.030, -0.088, -0.188)
LPIPS_SCALE = (0.458, 0.448, 0.450)
FEATURE_EPS = 1e-10  # added to the channel norm before dividing (lpips.normalize_tensor)


class LpipsUnavailable(SurfSplatInputError):
    """LPIPS cannot be computed (weights missing or unreadable); the message says why."""

    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(f"LPIPS unavailable: {reason}")


def vgg_key(conv_index: int, kind: str) -> str:
    """torchvision's state-dict key of a VGG16 conv: `features.{index}.{weight|bias}`."""
    return f"features.{conv_index}.{kind}"


def lin_key(layer: int) -> str:
    """The lpips package's state-dict key of a linear head: `lin{k}.model.1.weight`."""
    return f"lin{layer}.model.1.weight"


def vgg_shapes() -> dict[str, tuple[int, ...]]:
    """Every trunk tensor LPIPS needs, by torchvision key."""
    shapes: dict[str, tuple[int, ...]] = {}
    for stage in VGG16_STAGES:
        for index, c_in, c_out in stage:
            shapes[vgg_key(index, "weight")] = (c_out, c_in, 3, 3)
            shapes[vgg_key(index, "bias")] = (c_out,)
    return shapes


def lin_shapes() -> dict[str, tuple[int, ...]]:
    """Every linear-head tensor, by lpips key: [1, C, 1, 1] (a bias-free 1x1 conv)."""
    return {lin_key(k): (1, c, 1, 1) for k, c in enumerate(LPIPS_CHANNELS)}


def _buffer_name(key: str) -> str:
    return key.replace(".", "_")


class Lpips(nn.Module):
    """LPIPS-VGG v0.1 as a differentiable module; the weights are fixed, non-persistent buffers.

    Build it with `load_lpips()` (files) or from two state dicts in the files' key layouts.
    Buffers keep the weights out of `parameters()` (an optimizer never sees them) and out of the
    owner's `state_dict()` (checkpoints do not carry 58 MB of ImageNet weights).
    """

    def __init__(
        self,
        vgg_state: Mapping[str, Tensor],
        lin_state: Mapping[str, Tensor],
        *,
        sources: tuple[str, str] = ("state dict", "state dict"),  # named in errors: files or dicts
    ) -> None:
        super().__init__()
        vgg = _select("VGG16 weights", vgg_state, vgg_shapes(), ("classifier.",), sources[0])
        lin = _select("LPIPS linear weights", lin_state, lin_shapes(), (), sources[1])
        for key, value in {**vgg, **lin}.items():
            self.register_buffer(_buffer_name(key), value, persistent=False)
        self.register_buffer("shift", torch.tensor(LPIPS_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(LPIPS_SCALE).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    def _buffer(self, key: str) -> Tensor:
        return getattr(self, _buffer_name(key))

    def features(self, x: Tensor) -> list[Tensor]:
        """The five tapped VGG16 activations of [N, 3, H, W] scaled inputs."""
        taps = []
        for stage_index, stage in enumerate(VGG16_STAGES):
            if stage_index > 0:
                x = F.max_pool2d(x, kernel_size=2, stride=2)
            for index, _, _ in stage:
                weight, bias = self._buffer(vgg_key(index, "weight")), self._buffer(vgg_key(index, "bias"))
                x = F.relu(F.conv2d(x, weight, bias, padding=1))
            taps.append(x)
        return taps

    def forward(self, prediction: Tensor, target: Tensor) -> Tensor:
        """LPIPS distance per image pair; prediction, target: [B, 3, H, W] in [0, 1]. Returns [B]."""
        # Shapes only: as a training loss this runs every step, and a finiteness check would
        # synchronise with the GPU; NaN inputs give a NaN distance.
        check_tensor("prediction", prediction, ("B", 3, "H", "W"), finite=False)
        check_tensor("target", target, tuple(prediction.shape), finite=False)
        height, width = prediction.shape[-2:]
        if min(height, width) < MIN_SIZE:
            raise SurfSplatInputError(
                f"prediction: LPIPS needs images of at least {MIN_SIZE}x{MIN_SIZE} pixels, got {height}x{width}"
            )
        batch = prediction.shape[0]
        both = torch.cat([prediction, target], dim=0).to(self.shift.dtype)  # the weights' float32
        both = (2 * both - 1 - self.shift) / self.scale  # [0,1] -> [-1,1] -> lpips scaling layer
        distance = prediction.new_zeros(batch, dtype=torch.float32)
        for layer, feats in enumerate(self.features(both)):
            # Normalise in float32 even under fp16 autocast, where the 1e-10 guard would be 0
            # and an all-zero ReLU pixel would divide 0 by 0.
            feats = feats.float()
            feats = feats / (feats.square().sum(dim=1, keepdim=True).sqrt() + FEATURE_EPS)
            diff = (feats[:batch] - feats[batch:]).square()
            distance = distance + F.conv2d(diff, self._buffer(lin_key(layer))).mean(dim=(1, 2, 3))
        return distance


def _select(
    what: str,
    state: Mapping[str, Tensor],
    shapes: Mapping[str, tuple[int, ...]],
    ignore_prefixes: Sequence[str],
    source: str,
) -> dict[str, Tensor]:
    """The expected tensors of `state` as float32, with one clear error for any mismatch."""
    if not isinstance(state, Mapping):
        raise LpipsUnavailable(f"{what} in {source}: expected a state dict, got {type(state).__name__}")
    missing = [k for k in shapes if k not in state]
    unexpected = [k for k in state if k not in shapes and not str(k).startswith(tuple(ignore_prefixes))]
    if missing or unexpected:
        raise LpipsUnavailable(
            f"{what} in {source} do not have the expected keys: missing {missing[:6]}"
            f"{' ...' if len(missing) > 6 else ''}, unexpected {unexpected[:6]}{' ...' if len(unexpected) > 6 else ''}"
        )
    selected = {}
    for key, shape in shapes.items():
        value = state[key]
        if not isinstance(value, Tensor) or not value.is_floating_point():
            raise LpipsUnavailable(f"{what} in {source}: {key} is not a floating-point tensor")
        if tuple(value.shape) != shape:
            raise LpipsUnavailable(f"{what} in {source}: {key} has shape {tuple(value.shape)}, expected {shape}")
        if not bool(torch.isfinite(value).all()):
            raise LpipsUnavailable(f"{what} in {source}: {key} contains NaN or inf")
        selected[key] = value.detach().to(torch.float32, copy=True)
    return selected


# ---------------------------------------------------------------------------- finding weights
VGG16_NAME = "lpips-vgg16"  # registry names of the two files (surfsplat.model.registry)
LIN_NAME = "lpips-vgg-lin"


def _registry_file(name: str) -> Path:
    from ..model.pretrained import torch_hub_file
    from ..model.registry import lookup

    return torch_hub_file(lookup(name).source.filename)


def default_vgg_paths() -> list[Path]:
    """Where torchvision (and `surfsplat weights download lpips-vgg16`) caches the trunk:
    <torch hub dir>/checkpoints/vgg16-397923af.pth.

    `torch.hub.get_dir()` honours TORCH_HOME, then XDG_CACHE_HOME (default ~/.cache/torch/hub).
    """
    return [_registry_file(VGG16_NAME)]


def default_lin_paths() -> list[Path]:
    """Where the v0.1 heads are: the lpips package, torchmetrics' bundled copy, then torch hub's
    cache (`surfsplat weights download lpips-vgg-lin`).

    Packages are located without importing them (the lpips package imports torchvision).
    """
    candidates = []
    for package, relative in (
        ("lpips", Path("weights") / "v0.1" / LIN_FILENAME),
        ("torchmetrics", Path("functional") / "image" / "lpips_models" / LIN_FILENAME),
    ):
        spec = importlib.util.find_spec(package)
        for location in (spec.submodule_search_locations or []) if spec is not None else []:
            candidates.append(Path(location) / relative)
    return candidates + [_registry_file(LIN_NAME)]


@dataclass(frozen=True)
class LpipsWeightPaths:
    """The two files LPIPS-VGG needs."""

    vgg: Path  # torchvision layout: features.N.weight/bias (+ classifier.*)
    lin: Path  # lpips layout: lin{k}.model.1.weight


def _resolve(what: str, given: str | Path | None, defaults: list[Path], hint: str) -> Path:
    if given is not None and str(given) in (VGG16_NAME, LIN_NAME):
        # a registry name: its cached file, never a download in the middle of an evaluation
        defaults, given = [_registry_file(str(given))], None
    if given is not None:
        path = Path(given).expanduser()
        if not path.is_file():
            raise LpipsUnavailable(f"{what} file {path} does not exist")
        return path
    for path in defaults:
        if path.is_file():
            return path
    looked = ", ".join(str(p) for p in defaults) or "no standard location exists"
    raise LpipsUnavailable(f"{what} not found (looked in: {looked}); {hint}")


def find_lpips_weights(vgg_path: str | Path | None = None, lin_path: str | Path | None = None) -> LpipsWeightPaths:
    """Resolve both weight files: explicit paths win, else the standard cache locations."""
    vgg = _resolve(
        f"VGG16 weights {VGG16_FILENAME}",
        vgg_path,
        default_vgg_paths(),
        f"run `surfsplat weights download {VGG16_NAME}`, copy torchvision's {VGG16_FILENAME} there or pass its path",
    )
    lin = _resolve(
        f"LPIPS v0.1 linear weights {LIN_FILENAME}",
        lin_path,
        default_lin_paths(),
        f"run `surfsplat weights download {LIN_NAME}`, install the lpips package (its weights/v0.1/vgg.pth) "
        "or pass the file's path",
    )
    return LpipsWeightPaths(vgg=vgg, lin=lin)


def read_state_dict(path: Path, what: str) -> Mapping[str, Tensor]:
    """Read a torch-saved state dict (legacy or zip format) safely, without executing code."""
    # Zip-format files can be memory-mapped, so reading the trunk does not load the 480 MB of
    # classifier weights torchvision's file also carries; legacy-format files cannot.
    mmap = zipfile.is_zipfile(path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
    except (RuntimeError, pickle.UnpicklingError, EOFError, OSError, ValueError) as err:
        raise LpipsUnavailable(f"cannot read {what} file {path}: {err}") from err
    if not isinstance(state, Mapping):
        raise LpipsUnavailable(f"{what} file {path} does not hold a state dict (got {type(state).__name__})")
    return state


def load_lpips(
    vgg_path: str | Path | None = None,
    lin_path: str | Path | None = None,
    *,
    device: torch.device | str | None = None,
) -> Lpips:
    """LPIPS-VGG v0.1 from files; raises `LpipsUnavailable` with the reason when it cannot."""
    paths = find_lpips_weights(vgg_path, lin_path)
    vgg_state = read_state_dict(paths.vgg, "VGG16 weights")
    lin_state = read_state_dict(paths.lin, "LPIPS linear weights")
    model = Lpips(vgg_state, lin_state, sources=(str(paths.vgg), str(paths.lin)))
    return model if device is None else model.to(device)


def try_load_lpips(
    vgg_path: str | Path | None = None,
    lin_path: str | Path | None = None,
    *,
    device: torch.device | str | None = None,
) -> Lpips | LpipsUnavailable:
    """Like `load_lpips`, but returns the `LpipsUnavailable` as a result for reports to print."""
    try:
        return load_lpips(vgg_path, lin_path, device=device)
    except LpipsUnavailable as unavailable:
        return unavailable
