"""A network to run, by spec: `ModelSpec` (a weights name, an hf:// address or a path, with adapter
overrides for ablations) and `load_model`, which `reconstruct`, `eval` and the demo share.

    model, label = load_model(ModelSpec("tiny-synthetic"))
    model, label = load_model(ModelSpec.parse("w/o FAB=runs/tiny:opacity_max=1.0"))
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch

from ..utils.checks import SurfSplatInputError
from .pretrained import load_pretrained, with_adapter
from .surfsplat import SurfSplat


# ----------------------------------------------------------------------------------------- models
@dataclass(frozen=True)
class ModelSpec:
    """Which network to evaluate: a checkpoint, and how to read it."""

    checkpoint: str  # a weights name (`surfsplat weights list`), hf://owner/repo/file, our .safetensors/.json
    # pair, a training checkpoint folder, a run folder, or a release .ckpt/.pth
    name: str | None = None  # label in tables (default: derived from the path and overrides)
    preset: str | None = None  # encoder preset of a release file given by path (None: small); names know theirs
    adapter_overrides: tuple[
        tuple[str, object], ...
    ] = ()  # AdapterConfig fields to change, e.g. (("opacity_max", 1.0),)
    trust_pickle: bool = False  # release .ckpt files pickle their hyper-parameters; allow unpickling them

    @staticmethod
    def parse(text: str, preset: str | None = None, trust_pickle: bool = False) -> ModelSpec:
        """`[NAME=]CHECKPOINT[:field=value,field=value]`, e.g. `w/o FAB=runs/tiny:opacity_max=1.0`.

        Values are JSON (numbers, true/false) or bare words (strings such as prior=none).
        """
        name = None
        head, _, tail = text.partition(":")
        if "=" in head:
            name, head = head.split("=", 1)
        if not head:
            raise SurfSplatInputError(f"--compare {text!r}: expected [NAME=]CHECKPOINT[:field=value,...]")
        overrides = []
        for item in filter(None, tail.split(",")):
            if "=" not in item:
                raise SurfSplatInputError(f"--compare {text!r}: adapter override {item!r} is not field=value")
            key, value = item.split("=", 1)
            try:
                parsed: object = json.loads(value)
            except ValueError:
                parsed = value
            overrides.append((key.strip(), parsed))
        return ModelSpec(
            checkpoint=head,
            name=name or None,
            preset=preset,
            adapter_overrides=tuple(overrides),
            trust_pickle=trust_pickle,
        )

    def label(self) -> str:
        if self.name:
            return self.name
        path = Path(self.checkpoint)
        base = path.parent.parent.name + "/" + path.name if path.parent.name == "checkpoints" else path.name
        extra = ",".join(f"{k}={v}" for k, v in self.adapter_overrides)
        return base + (f" [{extra}]" if extra else "")


def load_model(spec: ModelSpec, device: torch.device | str = "cpu") -> tuple[SurfSplat, str]:
    """(model in eval mode, table label) for a ModelSpec: a weights name, an hf:// address or a path."""
    model = load_pretrained(spec.checkpoint, preset=spec.preset, trust_pickle=spec.trust_pickle)
    if spec.adapter_overrides:
        info = model.pretrained_info
        model = with_adapter(model, dict(spec.adapter_overrides))
        model.pretrained_info = info
    return model.to(device).eval(), spec.label()


# ----------------------------------------------------------------------------------------- inference
def prepare_for_inference(model: SurfSplat, *, channels_last: bool = False, compile: bool = False) -> SurfSplat:
    """The model in eval mode with the CPU levers asked for (in place). Callers run the forward
    under `torch.inference_mode()`.

    Measured with `benchmarks/encoder.py --levers` (small preset, 2 x 256 x 256, 2 cores, one run
    each): inference_mode leaves the time as it is and lowers peak memory by a tenth, so every
    inference path uses it. channels_last (convolution weights in NHWC) made the fp32 forward 2 %
    slower, so nothing turns it on. compile (the encoder through `torch.compile`, inductor) made the
    bf16 forward 19 % faster and the fp32 one 15 % slower, after a compilation of about two minutes
    at the first forward: it pays where one process runs many forwards of one size, so it is off
    unless asked for (`reconstruct(compile=True)`, `--compile`).
    """
    model.eval()
    if channels_last:
        model.to(memory_format=torch.channels_last)
    if compile and not getattr(model.encoder, "_surfsplat_compiled", False):
        model.encoder = torch.compile(model.encoder)
        model.encoder._surfsplat_compiled = True
    return model
