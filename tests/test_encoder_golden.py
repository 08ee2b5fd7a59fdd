"""Golden fixture: the released small model's function, reproduced through a release-layout checkpoint.

The weights are regenerated from `formula_weights.json`, written as a Lightning-style `.ckpt` in the
release's key layout (`encoder.depth_predictor...`), and loaded through the key-mapping table, so the
test covers the loading path as well as the computation.
"""

from __future__ import annotations

import pytest
import torch

from _golden import OUTPUTS, lightning_release_state, output, rel, run_case
from surfsplat.model import SurfSplat, load_release_weights

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
def golden_run(golden_dir, tmp_path_factory):
    ckpt = tmp_path_factory.mktemp("release") / "surfsplat-small.ckpt"
    torch.save({"state_dict": lightning_release_state(golden_dir), "global_step": 0, "epoch": 0}, ckpt)
    model = SurfSplat.from_preset("small", adapter="official").eval()
    report = load_release_weights(model, ckpt)
    assert report.loaded == 567 and report.ignored == []
    return run_case(model, golden_dir)


@pytest.mark.parametrize("name, bound", INTERMEDIATES)
def test_intermediates_match_the_release(golden_run, name, bound):
    pred, case = golden_run
    err = rel(pred.intermediates[name], case[f"intermediates.{name}"])
    assert err <= bound, f"{name}: relative L2 error {err:.3e} > {bound:.0e}"


@pytest.mark.parametrize("what, bound", OUTPUTS)
def test_outputs_match_the_release(golden_run, what, bound):
    pred, case = golden_run
    err = rel(output(pred, what), case[f"outputs.{what}"])
    assert err <= bound, f"{what}: relative L2 error {err:.3e} > {bound:.0e}"
