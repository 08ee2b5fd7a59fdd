"""Shared by the golden-fixture tests: the release-layout state dict of the formula weights, the
golden case run through a model, and the relative errors against the release's outputs."""

from __future__ import annotations

from pathlib import Path

import torch
from safetensors.torch import load_file

from surfsplat import Cameras
from surfsplat.model import SurfSplat, SurfSplatPrediction
from surfsplat.model.formula_weights import formula_state_dict

# (golden key, bound on ||ours - golden|| / ||golden||) of the outputs
OUTPUTS = [
    ("depths", 1e-4),
    ("gaussians.means", 1e-4),
    ("gaussians.covariances", 1e-3),
    ("gaussians.harmonics", 1e-3),
    ("gaussians.opacities", 1e-3),
    ("gaussians.scales_mul", 1e-3),
    ("gaussians.normals", 1e-3),
    ("visualization_dump.scales", 1e-3),
    ("visualization_dump.rotations", 1e-3),
]


def rel(ours: torch.Tensor, golden: torch.Tensor) -> float:
    assert ours.shape == golden.shape
    return float((ours.double() - golden.double()).norm() / golden.double().norm())


def lightning_release_state(golden_dir: Path) -> dict[str, torch.Tensor]:
    """The formula weights under the release's names with Lightning's `encoder.` prefix."""
    weights = formula_state_dict(golden_dir / "formula_weights.json")
    return {f"encoder.{k}": torch.from_numpy(v) for k, v in weights.items()}


def run_case(model: SurfSplat, golden_dir: Path) -> tuple[SurfSplatPrediction, dict[str, torch.Tensor]]:
    """The model on the golden case (intermediates included) and the case's tensors."""
    case = load_file(str(golden_dir / "case_identity.safetensors"))
    _, v, _, h, w = case["context.image"].shape
    cameras = Cameras.from_normalized(case["context.extrinsics"][0], case["context.intrinsics"][0], w, h)
    with torch.no_grad():
        pred = model(
            case["context.image"], cameras, case["context.near"], case["context.far"], return_intermediates=True
        )
    return pred, case


def output(pred: SurfSplatPrediction, what: str) -> torch.Tensor:
    """Our tensor for a golden output key."""
    g, out = pred.gaussians, pred.adapter_output
    return {
        "depths": pred.depths,
        "gaussians.means": g.means,
        "gaussians.covariances": g.covariances,
        "gaussians.harmonics": g.sh,
        "gaussians.opacities": g.opacities,
        "gaussians.scales_mul": out.scales_mul,
        "gaussians.normals": out.normals,
        "visualization_dump.scales": out.scales,
        "visualization_dump.rotations": out.rotations,
    }[what]
