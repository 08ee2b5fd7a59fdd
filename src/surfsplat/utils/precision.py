"""Numeric precision of the network: `auto`, `fp32` or `bf16`, resolved for one device.

    precision = resolve_precision("auto", torch.device("cpu"))   # "bf16" on AMX / AVX512-BF16 CPUs
    with autocast(precision, device):
        prediction = model(images, cameras, near, far)

bf16 is PyTorch's own autocast: the model keeps float32 weights and runs its parts whose precision
decides the answer (cost-volume correlation, the softmax over depth candidates, depth regression,
the Gaussian adapter) in float32 inside it; everything else runs in bfloat16. `auto` picks bf16
only where the hardware computes bf16 natively (CUDA devices that report bf16 support, CPUs with
AMX or AVX512-BF16); elsewhere bf16 is emulated and slower than float32, so `auto` means fp32.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, Literal

import torch
from torch import Tensor

from .checks import SurfSplatInputError

Precision = Literal["auto", "fp32", "bf16"]
Resolved = Literal["fp32", "bf16"]
PRECISIONS: tuple[str, ...] = ("auto", "fp32", "bf16")

# CPU feature flags (Linux /proc/cpuinfo names) with native bf16 matrix or dot-product instructions.
CPU_BF16_FLAGS = ("amx_bf16", "avx512_bf16")


def parse_precision(value: str, option: str = "--precision") -> Precision:
    """`value` checked against auto|fp32|bf16 (case-insensitive), with an error naming `option`."""
    text = str(value).strip().lower()
    if text not in PRECISIONS:
        raise SurfSplatInputError(f"{option}: expected one of {', '.join(PRECISIONS)}, got {value!r}")
    return text  # type: ignore[return-value]


@functools.cache
def cpu_bf16_flags(cpuinfo: str = "/proc/cpuinfo") -> frozenset[str]:
    """The CPU's native-bf16 feature flags from `cpuinfo` (empty where the file does not exist,
    as on macOS and Windows: bf16 is then never picked automatically)."""
    path = Path(cpuinfo)
    if not path.is_file():
        return frozenset()
    for line in path.read_text(errors="replace").splitlines():
        if line.startswith("flags"):
            return frozenset(CPU_BF16_FLAGS).intersection(line.split(":", 1)[-1].split())
    return frozenset()


def has_fast_bf16(device: torch.device | str) -> bool:
    """Whether `device` computes bf16 natively (CUDA: compute capability 8.0+; CPU: AMX or
    AVX512-BF16), i.e. whether bf16 is faster there than float32."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported(including_emulation=False)
    if device.type == "cpu":
        return bool(cpu_bf16_flags())
    return False


def resolve_precision(precision: str, device: torch.device | str) -> Resolved:
    """The precision that runs on `device`: `auto` becomes bf16 where it is fast, else fp32."""
    choice = parse_precision(precision)
    if choice == "auto":
        return "bf16" if has_fast_bf16(device) else "fp32"
    return choice


def autocast_dtype(precision: str) -> torch.dtype | None:
    """The autocast dtype of a resolved precision (None: plain float32, no autocast)."""
    return {"fp32": None, "bf16": torch.bfloat16}[parse_precision(precision)]


@contextlib.contextmanager
def autocast(precision: str, device: torch.device | str) -> Iterator[Resolved]:
    """Run the body in `precision` on `device` (resolved first); yields what runs."""
    device = torch.device(device)
    resolved = resolve_precision(precision, device)
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=resolved == "bf16"):
        yield resolved


def reduced_precision(device_type: str) -> torch.dtype | None:
    """The autocast dtype in force for `device_type` here (None outside autocast)."""
    if not torch.is_autocast_enabled(device_type):
        return None
    return torch.get_autocast_dtype(device_type)


def without_autocast(device_type: str) -> contextlib.AbstractContextManager[None]:
    """Autocast off in the body. Two uses inside the model: float32 regions (callers pass `.float()`
    tensors in, so every op runs in float32), and exact data movement on bf16 tensors (padding,
    resampling) that autocast would otherwise run in float32 and cast back, changing nothing."""
    return torch.autocast(device_type, enabled=False)


def cat(tensors: Sequence[Tensor], dim: int) -> Tensor:
    """torch.cat that, inside autocast, concatenates in the autocast dtype: a mixed float32/bf16
    list would otherwise promote the whole (large) result to float32, which the next convolution
    casts straight back. Outside autocast it is torch.cat, bit for bit."""
    amp = reduced_precision(tensors[0].device.type)
    if amp is not None:
        tensors = [t.to(amp) if t.is_floating_point() else t for t in tensors]
    return torch.cat(tensors, dim=dim)


def float32(value: Any) -> Any:
    """A floating tensor (or a list / tuple of them) in float32; anything else as it is."""
    if isinstance(value, Tensor):
        return value.float() if value.is_floating_point() else value
    if isinstance(value, (list, tuple)):
        return type(value)(float32(v) for v in value)
    return value
