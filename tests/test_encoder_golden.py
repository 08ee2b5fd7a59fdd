"""Golden fixture: the released small model's function, reproduced through a release-layout checkpoint.

The weights are regenerated from `formula_weights.json`, written as a Lightning-style `.ckpt` in the
release's key layout (`encoder.depth_predictor...`), and loaded through the key-mapping table, so the
test covers the loading path as well as the computation.
"""

from __future__ import annotations

import pytest
import torch
from safetensors.torch import load_file

from surfsplat import Cameras
from surfsplat.model import SurfSplat, load_release_weights
from surfsplat.model.formula_weights import formula_state_dict

pytestmark = pytest.mark.slow

# (ours, golden key, bound on ||ours - golden|| / ||golden||)
INTERMEDIATES = [
    ("dinov2_input_resized_normalized", 1e-4),
    *[(f"dinov2_intermediate_tokens.{i}", 1e-4) for i in range(4)],
    ("features_cnn_all_scales.0", 1e-4),
    ("features_mv.0", 1e-4),
    ("cost_volume", 1e-4),
    ("depth_head_logits", 1e-4),
    ("mv_upsampler_coarse_invdepth", 1e-4),
    ("mv_upsampler_residual_invdepth", 1e-4),
    ("gaussian_head_out", 1e-4),
]


def _rel(ours: torch.Tensor, golden: torch.Tensor) -> float:
    assert ours.shape == golden.shape
    return float((ours.double() - golden.double()).norm() / golden.double().norm())


@pytest.fixture(scope="module")
def golden_run(golden_dir, tmp_path_factory):
    weights = formula_state_dict(golden_dir / "formula_weights.json")
    ckpt = tmp_path_factory.mktemp("release") / "surfsplat-small.ckpt"
    state = {f"encoder.{k}": torch.from_numpy(v) for k, v in weights.items()}
    torch.save({"state_dict": state, "global_step": 0, "epoch": 0}, ckpt)
    del weights, state
    model = SurfSplat.from_preset("small", adapter="official").eval()
    report = load_release_weights(model, ckpt)
    assert report.loaded == 567 and report.ignored == []
    case = load_file(str(golden_dir / "case_identity.safetensors"))
    _, v, _, h, w = case["context.image"].shape
    cameras = Cameras.from_normalized(case["context.extrinsics"][0], case["context.intrinsics"][0], w, h)
    with torch.no_grad():
        pred = model(
            case["context.image"], cameras, case["context.near"], case["context.far"], return_intermediates=True
        )
    return pred, case


@pytest.mark.parametrize("name, bound", INTERMEDIATES)
def test_intermediates_match_the_release(golden_run, name, bound):
    pred, case = golden_run
    err = _rel(pred.intermediates[name], case[f"intermediates.{name}"])
    assert err <= bound, f"{name}: relative L2 error {err:.3e} > {bound:.0e}"


@pytest.mark.parametrize(
    "what, bound",
    [
        ("depths", 1e-4),
        ("gaussians.means", 1e-4),
        ("gaussians.covariances", 1e-3),
        ("gaussians.harmonics", 1e-3),
        ("gaussians.opacities", 1e-3),
        ("gaussians.scales_mul", 1e-3),
        ("gaussians.normals", 1e-3),
        ("visualization_dump.scales", 1e-3),
        ("visualization_dump.rotations", 1e-3),
    ],
)
def test_outputs_match_the_release(golden_run, what, bound):
    pred, case = golden_run
    g, out = pred.gaussians, pred.adapter_output
    ours = {
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
    err = _rel(ours, case[f"outputs.{what}"])
    assert err <= bound, f"{what}: relative L2 error {err:.3e} > {bound:.0e}"
