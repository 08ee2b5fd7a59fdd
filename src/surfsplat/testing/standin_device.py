"""A stand-in accelerator for CPU-only machines: tensors that say they are on another device, keep
their values on the CPU, and refuse to meet a CPU tensor.

    with StandinDevice() as dev:             # dev.device is torch.device("meta")
        model = model.to(dev.device)         # parameters and buffers move to the stand-in
        images = images.to(dev.device)
        loss = model(images, ...).sum()      # raises DeviceMixError at the first op that mixes
        loss.backward()                      # an input-device tensor with a CPU-created one
    dev.syncs                                # every host synchronisation, with its surfsplat line

Why not the meta device alone (checked on torch 2.13):
- several meta kernels do not check devices: bmm, mm, einsum, conv2d, linear, index_select and
  copy_ accept a CPU operand without complaint (bmm even returns a CPU tensor), so a CPU-created
  tensor can pass a meta run unnoticed;
- meta tensors have no values: `.item()`, `bool()`, `nonzero`, input validation and the renderer's
  data-dependent binning cannot run;
- `torch.autocast("meta", enabled=False)` raises, and the model enters such regions in every run.

How it works. `StandinTensor` is a wrapper subclass whose `.device` is `meta` (a non-CPU device
the autograd engine and `device=` arguments accept on every build) and that carries a real CPU
tensor. While `StandinDevice` is active, a TorchDispatchMode sees every aten op, forward and
backward, and applies CUDA's rule to it: all tensor operands on one device. An op with a stand-in
operand and a CPU operand (any shape, 0-dim included: stricter than CUDA, which accepts 0-dim CPU
tensors in elementwise ops) raises `DeviceMixError`, naming the op and the surfsplat line. Factory
ops asked for the stand-in device (`torch.eye(3, device=x.device)`, `.to(x)`, `zeros_like(x)`)
produce stand-in tensors; factories without a device produce plain CPU tensors, exactly what a
CUDA run would get. Values are computed by the ordinary CPU kernels, so data-dependent code runs
for real. A TorchFunctionMode routes the few constructors that bypass the dispatcher
(`torch.tensor`, `torch.as_tensor`, `torch.asarray`, `Tensor.new_tensor`) and `Tensor.tolist`
through the same rules.

Host synchronisations. Every op that makes a CUDA host wait for the device is recorded with its
innermost surfsplat source line (`syncs`): scalar reads (`.item()`, `bool()`, `float()`, f-string
formatting: aten._local_scalar_dense), copies to the CPU (`.cpu()`, `.tolist()`), ops whose output
size depends on the values (nonzero, boolean-mask indexing, masked_select, unique, bincount,
repeat_interleave without output_size), equal/allclose, linalg's error checks
(_linalg_check_errors, e.g. torch.linalg.inv), and blocking copies from the CPU (`.to(device)`,
`torch.tensor(data, device=...)`: CUDA synchronises the stream after them). Counts are host waits:
bincount and repeat_interleave wait twice on CUDA. Checked on an H200 (torch 2.11) against
torch.cuda.set_sync_debug_mode over a training step (benchmarks/host_syncs.py --device cuda): the
same waits at every surfsplat line, once bincount and those double waits were added, and one more
that PyTorch reports inside its own torch/cuda module.

Not emulated: autocast on the stand-in device (a disabled autocast region is a no-op; an enabled
one raises NotImplementedError), so reduced precision is checked on a real GPU only.
"""

from __future__ import annotations

import contextlib
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten, tree_map

STANDIN = torch.device("meta")
PACKAGE = Path(__file__).resolve().parents[1]  # src/surfsplat: frames there name where an op came from
TOOLS = Path(__file__).resolve().parent  # surfsplat/testing: this module's own frames, never named

aten = torch.ops.aten
# Ops that read device values on the host (CUDA: a device-to-host copy the host waits for).
_SYNC_OPS = {
    aten._local_scalar_dense.default: "scalar read (.item/bool/float/int)",
    aten.nonzero.default: "nonzero (data-dependent size)",
    aten.masked_select.default: "masked_select (data-dependent size)",
    aten.equal.default: "equal",
    aten.is_nonzero.default: "is_nonzero",
    aten.allclose.default: "allclose",
    aten._unique.default: "unique",
    aten._unique2.default: "unique",
    aten.unique_dim.default: "unique",
    aten.unique_consecutive.default: "unique",
    aten._linalg_check_errors.default: "linalg error check (info read on the host)",
    aten.bincount.default: "bincount (output size from the values)",
}
REPEAT_INTERLEAVE = "repeat_interleave without output_size"
# Ops whose CUDA kernels wait for the device more than once (counted by torch.cuda.set_sync_debug_mode):
# bincount reads the input's min and max, repeat_interleave the total and "no negative repeats".
_WAITS = {"bincount (output size from the values)": 2, REPEAT_INTERLEAVE: 2}
UPLOAD = "copy from the CPU (blocking)"


class DeviceMixError(RuntimeError):
    """An op received tensors on the stand-in device and on the CPU (CUDA: 'found at least two devices')."""


class StandinTensor(Tensor):
    """A CPU tensor `elem` that reports the stand-in device."""

    elem: Tensor
    __slots__ = ["elem"]
    __torch_function__ = torch._C._disabled_torch_function_impl

    @staticmethod
    def __new__(cls, elem: Tensor, requires_grad: bool = False) -> StandinTensor:
        out = Tensor._make_wrapper_subclass(
            cls,
            elem.size(),
            strides=elem.stride(),
            storage_offset=elem.storage_offset(),
            dtype=elem.dtype,
            layout=elem.layout,
            device=STANDIN,
            requires_grad=requires_grad,
        )
        out.elem = elem
        return out

    def __repr__(self) -> str:
        return f"StandinTensor(shape={tuple(self.shape)}, dtype={self.dtype})"

    @classmethod
    def __torch_dispatch__(cls, func, types, args=(), kwargs=None):
        # Inside a StandinDevice block the dispatch mode sees every op first; this is the fallback
        # for a thread without the mode, and the error for a tensor used after its block.
        if _ACTIVE is None:
            raise RuntimeError(f"{func}: stand-in tensors can only be used inside `with StandinDevice()`")
        return _ACTIVE.dispatch(func, args, kwargs or {})


def standin(t: Tensor, requires_grad: bool | None = None) -> StandinTensor:
    """A stand-in copy of the CPU tensor `t` (a leaf; requires_grad defaults to t's)."""
    grad = t.requires_grad if requires_grad is None else requires_grad
    return StandinTensor(t.detach().clone(), requires_grad=grad)


@dataclass
class Sync:
    op: str  # aten op (or Tensor.tolist)
    kind: str  # what it is, in words
    where: str  # innermost surfsplat frame, "path:line (function)", path relative to src/surfsplat
    stack: list[str] = field(default_factory=list)  # up to 4 surfsplat frames, innermost first
    waits: int = 1  # how many times the host waits for the device in this op


def _surfsplat_frames(limit: int = 4) -> list[str]:
    frames, frame = [], sys._getframe(1)
    while frame is not None and len(frames) < limit:
        path = Path(frame.f_code.co_filename)
        # Comprehensions and generator expressions count as the function that runs them.
        inner = frame.f_code.co_name.startswith("<") and frame.f_code.co_name != "<module>"
        if PACKAGE in path.parents and TOOLS not in path.parents and not inner:
            frames.append(f"{path.relative_to(PACKAGE)}:{frame.f_lineno} ({frame.f_code.co_name})")
        frame = frame.f_back
    return frames


def _is_standin_device(device: object) -> bool:
    return device is not None and torch.device(device) == STANDIN


_ACTIVE: StandinDevice | None = None


class SyncLog:
    """Recorded host synchronisations."""

    def __init__(self) -> None:
        self.syncs: list[Sync] = []

    def record(self, op: str, kind: str) -> None:
        stack = _surfsplat_frames()
        where = stack[0] if stack else "<outside surfsplat>"
        self.syncs.append(Sync(op, kind, where, stack, _WAITS.get(kind, 1)))

    def sync_counts(self) -> Counter:
        """{(where, kind): number of host waits} of the recorded host synchronisations."""
        counts: Counter = Counter()
        for s in self.syncs:
            counts[(s.where, s.kind)] += s.waits
        return counts


class HostSyncRecorder(SyncLog, TorchDispatchMode):
    """Records the host synchronisations of real accelerator tensors (e.g. on CUDA): the same list
    as StandinDevice.syncs, without the stand-in's device rules (the device enforces those)."""

    def __init__(self) -> None:
        SyncLog.__init__(self)
        TorchDispatchMode.__init__(self)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        leaves, _ = tree_flatten((args, kwargs))
        devices = [t.device for t in leaves if isinstance(t, Tensor)]
        on_device = [d for d in devices if d.type != "cpu"]
        requested = kwargs.get("device")
        if requested is not None:
            target = torch.device(requested)
        else:
            target = on_device[0] if on_device else torch.device("cpu")
        on_cpu = any(d.type == "cpu" for d in devices)
        kind = sync_kind(func, args, kwargs, on_device=bool(on_device), on_cpu=on_cpu, target=target)
        if kind is not None:
            self.record(str(func), kind)
        return func(*args, **kwargs)

    def __enter__(self):
        self._uploads = _Uploads(self)
        self._uploads.__enter__()
        return super().__enter__()

    def __exit__(self, *exc):
        try:
            return super().__exit__(*exc)
        finally:
            self._uploads.__exit__(*exc)


class _Uploads(TorchFunctionMode):
    """Tensors built from Python data on a device: a blocking upload the dispatcher does not show."""

    def __init__(self, log: SyncLog) -> None:
        super().__init__()
        self.log = log

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        device = kwargs.get("device")
        if func in (torch.tensor, torch.as_tensor, torch.asarray) and device is not None:
            data = args[0] if args else kwargs.get("data", kwargs.get("obj"))
            if torch.device(device).type != "cpu" and not isinstance(data, Tensor):
                self.log.record(getattr(func, "__name__", str(func)), UPLOAD)
        return func(*args, **kwargs)


class StandinDevice(SyncLog, contextlib.AbstractContextManager):
    """Run the body with the stand-in device available (module docstring)."""

    device = STANDIN

    def __init__(self) -> None:
        super().__init__()
        self._stack = contextlib.ExitStack()

    # ------------------------------------------------------------------ context
    def __enter__(self) -> StandinDevice:
        global _ACTIVE
        if _ACTIVE is not None:
            raise RuntimeError("StandinDevice blocks do not nest")
        _ACTIVE = self
        try:
            self._stack.enter_context(_AutocastShim())
            self._stack.enter_context(_Constructors(self))
            self._ops = _Ops(self)
            self._stack.enter_context(self._ops)
        except BaseException:
            _ACTIVE = None
            self._stack.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        global _ACTIVE
        try:
            self._stack.close()
        finally:
            _ACTIVE = None

    # ------------------------------------------------------------------ the rules
    def dispatch(self, func, args: tuple, kwargs: dict):
        if func.overloadpacket is aten.to:
            # Inference mode skips the autograd keys where Tensor.to decomposes, so it arrives whole,
            # e.g. Tensor.to(other) as aten.to.device with the device positional: decomposed here,
            # the rules see the _to_copy(device=...) it is made of (the mode is entered again: a
            # handler runs with it off, and the decomposition's ops must meet it).
            with self._ops:
                out = func.decompose(*args, **kwargs)
            if out is not NotImplemented:
                return out
        leaves, _ = tree_flatten((args, kwargs))
        tensors = [t for t in leaves if isinstance(t, Tensor)]
        on_device = [t for t in tensors if isinstance(t, StandinTensor)]
        on_cpu = [t for t in tensors if not isinstance(t, StandinTensor)]
        for t in on_cpu:
            if t.device != torch.device("cpu"):
                raise RuntimeError(f"{func}: a {t.device} tensor reached the stand-in run (made outside its rules)")
        if func is aten.copy_.default and isinstance(args[1], StandinTensor) and not isinstance(args[0], StandinTensor):
            # cpu_tensor.copy_(device_tensor): a deliberate download, allowed as on CUDA.
            self.record(str(func), "copy to the CPU")
            return func(args[0], args[1].elem, *args[2:], **kwargs)
        if on_device and on_cpu:
            shapes = ", ".join(str(tuple(t.shape)) for t in on_cpu)
            where = "; ".join(_surfsplat_frames()) or "<outside surfsplat>"
            raise DeviceMixError(
                f"Expected all tensors to be on the same device, but found at least two devices, {STANDIN} and cpu! "
                f"({func} got CPU tensor(s) of shape {shapes}; at {where})"
            )
        requested = kwargs.get("device")
        if _is_standin_device(requested):
            target = STANDIN
            kwargs = {**kwargs, "device": torch.device("cpu")}
            generator = kwargs.get("generator")
            if generator is not None and generator.device != STANDIN:
                raise DeviceMixError(f"{func}: a CPU generator used for a tensor on {STANDIN} (CUDA refuses this)")
        elif requested is not None:
            target = torch.device(requested)
        else:
            target = STANDIN if on_device else torch.device("cpu")
        kind = sync_kind(func, args, kwargs, on_device=bool(on_device), on_cpu=bool(on_cpu), target=target)
        if kind is not None:
            self.record(str(func), kind)
        inputs = {id(t.elem): t for t in on_device}
        out = func(*tree_map(_unwrap, args), **tree_map(_unwrap, kwargs))
        if target != STANDIN:
            return out

        # Under inference mode a view of a normal tensor is a normal tensor sharing its base's
        # version counter, which autograd sets after this returns: a wrapper made here would be an
        # inference tensor, which has none ("Cannot set version_counter for inference tensor").
        normal_view = (
            torch.is_inference_mode_enabled()
            and func.is_view
            and isinstance(args[0], Tensor)
            and not args[0].is_inference()
        )

        def wrap(x):
            if not isinstance(x, Tensor):
                return x
            if id(x) in inputs:  # in-place and out= ops return their (wrapped) argument
                return inputs[id(x)]
            if normal_view:
                with torch.inference_mode(False):
                    return StandinTensor(x)
            return StandinTensor(x)

        return tree_map(wrap, out)


def sync_kind(func, args: tuple, kwargs: dict, *, on_device: bool, on_cpu: bool, target: torch.device) -> str | None:
    """What kind of host synchronisation `func` is (None: none). `on_device` / `on_cpu`: whether it
    has operands on the device / on the CPU; `target`: where its outputs go."""
    if func is aten.copy_.default:  # dst.copy_(src, non_blocking)
        dst, src = (t.device.type != "cpu" for t in args[:2])
        blocking = not (args[2] if len(args) > 2 else kwargs.get("non_blocking", False))
        if src and not dst:
            return "copy to the CPU"
        return UPLOAD if dst and not src and blocking else None
    if not on_device:
        # A blocking copy from the CPU: CUDA synchronises the stream after it (memcpy_and_sync).
        if on_cpu and target.type != "cpu" and func is aten._to_copy.default and not kwargs.get("non_blocking"):
            return UPLOAD
        return None
    if func in _SYNC_OPS:
        return _SYNC_OPS[func]
    if target.type == "cpu":
        return "copy to the CPU"
    if func in (aten.index.Tensor, aten.index_put.default, aten.index_put_.default, aten._index_put_impl_.default):
        if any(i is not None and i.dtype in (torch.bool, torch.uint8) for i in args[1]):
            return "boolean-mask indexing (data-dependent size)"
    if func is aten.repeat_interleave.Tensor and kwargs.get("output_size") is None:
        return REPEAT_INTERLEAVE
    return None


def _unwrap(x):
    return x.elem if isinstance(x, StandinTensor) else x


class _Ops(TorchDispatchMode):
    def __init__(self, owner: StandinDevice) -> None:
        super().__init__()
        self.owner = owner

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        return self.owner.dispatch(func, args, kwargs or {})


class _Constructors(TorchFunctionMode):
    """Constructors that build tensors from Python data without the dispatcher, and tolist()."""

    def __init__(self, owner: StandinDevice) -> None:
        super().__init__()
        self.owner = owner

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in (torch.tensor, torch.as_tensor, torch.asarray) and _is_standin_device(kwargs.get("device")):
            data = args[0] if args else kwargs.get("data", kwargs.get("obj"))
            if isinstance(data, StandinTensor):
                return func(*args, **kwargs)
            grad = kwargs.pop("requires_grad", False)
            host = func(*args, **{**kwargs, "device": "cpu"})
            return host.to(STANDIN).requires_grad_(grad)
        if func is Tensor.new_tensor and isinstance(args[0], StandinTensor):
            device = kwargs.get("device") or STANDIN
            host = torch.tensor(args[1], dtype=kwargs.get("dtype") or args[0].dtype, device="cpu")
            out = host.to(device) if _is_standin_device(device) else host
            return out.requires_grad_(kwargs.get("requires_grad", False))
        if func is Tensor.tolist and isinstance(args[0], StandinTensor):
            self.owner.record("Tensor.tolist", "copy to the CPU")
            return args[0].elem.tolist()
        if func in (Tensor.numpy, Tensor.__array__) and isinstance(args[0], StandinTensor):
            raise TypeError(f"can't convert {STANDIN} device type tensor to numpy. Use Tensor.cpu() first.")
        return func(*args, **kwargs)


class _AutocastShim(contextlib.AbstractContextManager):
    """`torch.autocast` and its queries for the stand-in device type: disabled regions are no-ops,
    enabled ones are not emulated. Other device types go to torch unchanged."""

    def __enter__(self):
        real_autocast, real_enabled, real_dtype = torch.autocast, torch.is_autocast_enabled, torch.get_autocast_dtype
        self._saved = (real_autocast, real_enabled, real_dtype)

        def autocast(device_type, *args, **kwargs):
            if device_type != STANDIN.type:
                return real_autocast(device_type, *args, **kwargs)
            enabled = kwargs.get("enabled", args[1] if len(args) > 1 else True)
            if enabled:
                raise NotImplementedError("autocast on the stand-in device is not emulated: run fp32, or use a GPU")
            return contextlib.nullcontext()

        def is_autocast_enabled(*args):
            if args and args[0] == STANDIN.type:
                return False
            return real_enabled(*args)

        def get_autocast_dtype(device_type):
            if device_type == STANDIN.type:
                return torch.float32
            return real_dtype(device_type)

        torch.autocast, torch.is_autocast_enabled, torch.get_autocast_dtype = (
            autocast,
            is_autocast_enabled,
            get_autocast_dtype,
        )
        return self

    def __exit__(self, *exc) -> None:
        torch.autocast, torch.is_autocast_enabled, torch.get_autocast_dtype = self._saved
