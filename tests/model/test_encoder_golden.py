"""Golden fixture: the released small model's function, reproduced through a release-layout checkpoint.

The weights are regenerated from `formula_weights.json`, written as a Lightning-style `.ckpt` in the
release's key layout (`encoder.depth_predictor...`), and loaded through the key-mapping table, so the
test covers the loading path as well as the computation.

The forward pass runs once, on the golden inputs kept exactly in the repository (tests/data). Its
results are compared with the repository's fixed random subset of the release's outputs and
intermediates (the same relative L2 error and bound, computed over the sampled elements), and, where
the full fixture is present (../shared/golden), with every element.
"""

from __future__ import annotations

import pytest
import torch
from safetensors.torch import load_file

from surfsplat import Cameras
from surfsplat.model import SurfSplat, load_release_weights
from tests.helpers.golden import OUTPUTS, lightning_release_state, output, rel

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


@pytest.fixture(scope="module")
def golden_run(golden_subset, golden_subset_dir, tmp_path_factory):
    ckpt = tmp_path_factory.mktemp("release") / "surfsplat-small.ckpt"
    torch.save({"state_dict": lightning_release_state(golden_subset_dir), "global_step": 0, "epoch": 0}, ckpt)
    model = SurfSplat.from_preset("small", adapter="official").eval()
    report = load_release_weights(model, ckpt)
    assert report.loaded == 567 and report.ignored == []
    case = golden_subset.tensors
    _, v, _, h, w = case["context.image"].shape
    cameras = Cameras.from_normalized(case["context.extrinsics"][0], case["context.intrinsics"][0], w, h)
    with torch.no_grad():
        pred = model(
            case["context.image"], cameras, case["context.near"], case["context.far"], return_intermediates=True
        )
    return pred


@pytest.fixture(scope="module")
def full_case(golden_dir, golden_subset):
    """The full golden fixture; its inputs must be those the forward pass ran on."""
    case = load_file(str(golden_dir / "case_identity.safetensors"))
    for key in ("context.image", "context.intrinsics", "context.extrinsics", "context.near", "context.far"):
        assert torch.equal(case[key], golden_subset.tensors[key]), f"tests/data differs from the full fixture: {key}"
    return case


@pytest.mark.parametrize("name, bound", INTERMEDIATES)
def test_intermediates_match_the_release_at_sampled_elements(golden_run, golden_subset, name, bound):
    d = golden_subset.tensors
    ours = golden_run.intermediates[name]
    assert tuple(ours.shape) == golden_subset.shapes[f"intermediates.{name}"]
    err = rel(ours.flatten()[d[f"index.{name}"].long()], d[f"intermediates.{name}"])
    assert err <= bound, f"{name}: relative L2 error over the sampled elements {err:.3e} > {bound:.0e}"


@pytest.mark.parametrize("what, bound", OUTPUTS)
def test_outputs_match_the_release_at_sampled_rows(golden_run, golden_subset, what, bound):
    d = golden_subset.tensors
    ours = output(golden_run, what)
    shape = golden_subset.shapes[f"outputs.{what}"]
    assert tuple(ours.shape) == shape
    if what == "depths":  # [1, V, H, W] -> [1, V*H*W]: the Gaussians' (view, row, column) order
        ours = ours.reshape(shape[0], -1)
    err = rel(ours[:, d["rows"].long()], d[f"outputs.{what}"])
    assert err <= bound, f"{what}: relative L2 error over the sampled rows {err:.3e} > {bound:.0e}"


@pytest.mark.parametrize("name, bound", INTERMEDIATES)
def test_intermediates_match_the_release(golden_run, full_case, name, bound):
    err = rel(golden_run.intermediates[name], full_case[f"intermediates.{name}"])
    assert err <= bound, f"{name}: relative L2 error {err:.3e} > {bound:.0e}"


@pytest.mark.parametrize("what, bound", OUTPUTS)
def test_outputs_match_the_release(golden_run, full_case, what, bound):
    err = rel(output(golden_run, what), full_case[f"outputs.{what}"])
    assert err <= bound, f"{what}: relative L2 error {err:.3e} > {bound:.0e}"
