"""Evaluation over an index: sample selection and counts, metrics equal to the metric functions
applied by hand, adapter ablations, checkpoint resolution, result files."""

from __future__ import annotations

import csv
import io
import json

import pytest
import torch

from surfsplat.data.eval_index import EvaluationIndex
from surfsplat.data.synthetic import write_synthetic_chunks
from surfsplat.evaluation import (
    EvalConfig,
    SampleCounts,
    evaluate,
    format_results,
    iter_index_samples,
    per_scene_csv,
    predict_sample,
    write_results,
)
from surfsplat.metrics import psnr, ssim, upsample_ground_truth
from surfsplat.metrics.lpips import LpipsUnavailable
from surfsplat.model import SurfSplat, save_checkpoint
from surfsplat.model.loading import ModelSpec, load_model
from surfsplat.model.pretrained import resolve_checkpoint, with_adapter
from surfsplat.utils.checks import SurfSplatInputError

SIZE = 32


@pytest.fixture(scope="module")
def chunks(tmp_path_factory):
    root = tmp_path_factory.mktemp("chunks")
    keys = write_synthetic_chunks(root, 2, seed=5, image_shape=(SIZE, SIZE), num_frames=4, supersample=1)
    return root, sorted(keys)


@pytest.fixture(scope="module")
def index(chunks):
    _, keys = chunks
    return EvaluationIndex.from_dict(
        {
            keys[0]: {"context": [0, 3], "target": [1, 2]},
            keys[1]: None,
            "absent-scene": {"context": [0, 1], "target": [2]},
        },
        "test index",
    )


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    torch.manual_seed(0)
    model = SurfSplat.from_preset("tiny")
    weights, _ = save_checkpoint(model, tmp_path_factory.mktemp("ckpt") / "model")
    return weights


def test_samples_follow_the_index_and_count_every_skip(chunks, index):
    root, keys = chunks
    counts = SampleCounts()
    samples = list(iter_index_samples([root], index, near=0.5, far=15.0, counts=counts))
    assert [s.key for s in samples] == [keys[0]]
    s = samples[0]
    assert s.context_views == (0, 3) and s.target_views == (1, 2)
    assert s.context_images.shape == (2, 3, SIZE, SIZE) and s.target_images.shape == (2, 3, SIZE, SIZE)
    assert s.context_depths is not None and float(s.context_depths.min()) > 0  # synthetic chunks carry depth
    assert (counts.evaluated, counts.excluded, counts.not_in_index, counts.missing) == (1, 1, 0, ["absent-scene"])


def test_rescale_to_a_size_keeps_k_consistent(chunks, index):
    root, _ = chunks
    full = next(iter_index_samples([root], index, near=0.5, far=15.0))
    half = next(iter_index_samples([root], index, image_shape=(16, 16), near=0.5, far=15.0))
    assert half.target_images.shape[-2:] == (16, 16) and half.context_depths.shape[-2:] == (16, 16)
    torch.testing.assert_close(half.target_cameras.K[:, :2], full.target_cameras.K[:, :2] / 2)


def test_index_entry_beyond_the_scene_is_an_error(chunks):
    root, keys = chunks
    bad = EvaluationIndex.from_dict({keys[0]: {"context": [0, 9], "target": [1]}})
    with pytest.raises(SurfSplatInputError, match="uses view 9 but the scene has 4 views"):
        list(iter_index_samples([root], bad, near=0.5, far=15.0))


@pytest.fixture(scope="module")
def evaluated(chunks, index, model_path):
    """(model, samples, result) of one bicubic evaluation, shared by the tests below."""
    root, _ = chunks
    model, name = load_model(ModelSpec(str(model_path), name="tiny"))
    samples = list(iter_index_samples([root], index, near=0.5, far=15.0))
    result = evaluate(model, samples, EvalConfig(progress=False), lpips=LpipsUnavailable("no weights here"), name=name)
    return model, samples, result


def test_metrics_equal_the_metric_functions_on_the_renders(evaluated):
    model, samples, result = evaluated
    pred = predict_sample(model, samples[0], (1, 2, 4))
    target = samples[0].target_images
    for s in (1, 2, 4):
        truth = upsample_ground_truth(target, s, "bicubic")
        want_psnr = float(psnr(pred.renders[s].color, truth).double().mean())
        want_ssim = float(ssim(pred.renders[s].color.double(), truth.double()).mean())
        got = result.report.mean[s]
        assert got["psnr"] == pytest.approx(want_psnr, abs=1e-5)
        assert got["ssim"] == pytest.approx(want_ssim, abs=1e-6)
        assert got["lpips"] is None
    assert result.report.lpips_unavailable == "LPIPS unavailable: no weights here"
    assert result.depth is not None and result.depth["abs_rel"] > 0
    assert result.seconds_forward > 0 and all(t > 0 for t in result.seconds_render.values())
    assert result.peak_memory_bytes > 0


def test_bilinear_upsampling_changes_only_the_hrrc_columns(evaluated):
    model, samples, result = evaluated
    cubic = result.report.mean
    config = EvalConfig(upsample="bilinear", progress=False)
    linear = evaluate(model, samples, config, lpips=LpipsUnavailable("no weights here")).report.mean
    assert cubic[1]["psnr"] == pytest.approx(linear[1]["psnr"], abs=1e-9)
    assert cubic[2]["psnr"] != pytest.approx(linear[2]["psnr"], abs=1e-4)


def test_without_fab_ablation_turns_alpha_normalization_off(model_path):
    model, _ = load_model(ModelSpec(str(model_path)))
    ablated = with_adapter(model, {"opacity_max": 1.0})
    assert model.adapter.alpha_threshold() == 0.001 and ablated.eval().adapter.alpha_threshold() is None
    for key, value in model.state_dict().items():
        assert torch.equal(ablated.state_dict()[key], value)
    with pytest.raises(SurfSplatInputError, match="unknown fields"):
        with_adapter(model, {"opacity": 1.0})


def test_model_spec_parsing():
    spec = ModelSpec.parse("w/o FAB=runs/x:opacity_max=1.0,prior=none")
    assert spec.name == "w/o FAB" and spec.checkpoint == "runs/x"
    assert spec.adapter_overrides == (("opacity_max", 1.0), ("prior", "none"))
    assert ModelSpec.parse("runs/x").label() == "x"
    with pytest.raises(SurfSplatInputError, match="is not field=value"):
        ModelSpec.parse("runs/x:opacity")


def test_checkpoint_resolution(tmp_path, model_path):
    step = tmp_path / "run" / "checkpoints" / "step-00000010"
    step.mkdir(parents=True)
    (step / "model.json").write_text("{}")
    (tmp_path / "run" / "checkpoints" / "step-00000002").mkdir()
    assert resolve_checkpoint(tmp_path / "run") == step / "model.safetensors"
    assert resolve_checkpoint(step) == step / "model.safetensors"
    assert resolve_checkpoint(model_path) == model_path
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        resolve_checkpoint(tmp_path / "nothing")
    with pytest.raises(FileNotFoundError, match="without model.json"):
        resolve_checkpoint(tmp_path)


def test_result_files(tmp_path, chunks, evaluated):
    _, keys = chunks
    model, samples, result = evaluated
    config = EvalConfig(factors=(1, 2), progress=False)
    results = {"a": evaluate(model, samples, config, lpips=LpipsUnavailable("none"), name="a"), "b": result}
    counts = SampleCounts(evaluated=1, excluded=1, missing=["absent-scene"])
    with pytest.raises(SurfSplatInputError, match="same factors"):
        write_results(results, tmp_path, counts)  # one table needs one set of factors
    assert list(tmp_path.iterdir()) == []  # and nothing was written
    results["b"] = evaluate(model, samples, config, lpips=LpipsUnavailable("none"), name="b")
    paths = write_results(results, tmp_path, counts)
    document = json.loads(paths["metrics"].read_text())
    assert document["entries"] == {
        "evaluated_per_model": 1,
        "excluded_null": 1,
        "scenes_not_in_index": 0,
        "missing_from_data": 1,
    }
    assert document["models"]["a"]["mean"]["x2"]["psnr"] == pytest.approx(results["a"].report.mean[2]["psnr"])
    rows = list(csv.DictReader(io.StringIO(per_scene_csv(results))))
    assert len(rows) == 2 * 1 * 2  # models x entries x factors
    assert {r["entry"] for r in rows} == {keys[0]} and rows[0]["lpips"] == ""
    table = paths["table"].read_text()
    assert "32x32 (Standard)" in table and "64x64 (HRRC)" in table and "LPIPS unavailable: none" in table


def test_release_lightning_checkpoint_loads_into_the_official_adapter(tmp_path):
    from surfsplat.model import export_release_state_dict

    torch.manual_seed(1)
    source = SurfSplat.from_preset("tiny", adapter="official")
    state = {f"encoder.{k}": v for k, v in export_release_state_dict(source).items()}
    state["decoder.background"] = torch.zeros(3)  # Lightning files also hold modules that are not the encoder
    torch.save({"state_dict": state, "global_step": 10}, tmp_path / "release.ckpt")
    model, name = load_model(ModelSpec(str(tmp_path / "release.ckpt"), preset="tiny"))
    assert name == "release.ckpt" and model.cfg.adapter.mode == "official"
    for key, value in source.state_dict().items():
        assert torch.equal(model.state_dict()[key], value), key
    with pytest.raises(SurfSplatInputError, match="does not match"):
        load_model(ModelSpec(str(tmp_path / "release.ckpt"), preset="small"))


def test_compact_option_scores_the_compacted_reconstruction(evaluated):
    # The renders of `compact=LEVEL` are those of surfsplat.compact applied to the model's own output.
    from surfsplat import compact
    from surfsplat.render import render

    model, samples, _ = evaluated
    sample = samples[0]
    plain = predict_sample(model, sample, (1,))
    small = predict_sample(model, sample, (1,), compact=5)
    h, w = sample.context_images.shape[-2:]
    want = compact(
        plain.gaussians, sample.context_cameras.to(torch.float32), h, w, 5, alpha_threshold=plain.alpha_threshold
    )
    assert small.surfels == len(small.gaussians) == len(want) < len(plain.gaussians) == plain.surfels
    target = render(want, sample.target_cameras.to(torch.float32), w, h, alpha_threshold=plain.alpha_threshold)
    torch.testing.assert_close(small.renders[1].color, target.color)
    result = evaluate(
        model, samples, EvalConfig(factors=(1,), progress=False, compact=5), lpips=LpipsUnavailable("none"), name="c"
    )
    assert result.compact == 5 and result.surfels_mean == len(want)
    assert result.to_json()["compact_level"] == 5


def test_closure_is_measured_on_the_same_renders(evaluated):
    """The evaluation's closure figures are those of the metric on its own renders and surfels."""
    from surfsplat.metrics.closure import ClosureAccumulator

    model, samples, result = evaluated
    acc = ClosureAccumulator()
    for sample in samples:
        pred = predict_sample(model, sample, (1, 2, 4))
        acc.add_alpha({s: r.alpha for s, r in pred.renders.items()})
        acc.add_surfels(pred.gaussians, *pred.closure_surfels())
    want = acc.report()
    got = result.closure
    assert got.mean_alpha == pytest.approx(want.mean_alpha)
    assert got.closure == pytest.approx(want.mean_alpha[4] / want.mean_alpha[1])
    assert got.undersized == pytest.approx(want.undersized)
    assert got.multiplier_at_low is not None and 0 <= got.multiplier_at_low <= 1
    assert result.to_json()["closure"]["closure"] == pytest.approx(got.closure)
    assert "Closure (target views" in format_results({"m": result})
