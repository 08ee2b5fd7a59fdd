"""Weights in and out: the formula weights, the release key mapping, file formats and their errors."""

from __future__ import annotations

import json
import zlib

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from surfsplat import Cameras
from surfsplat.model import (
    SurfSplat,
    export_release_state_dict,
    load_checkpoint,
    load_depth_anything_v2,
    load_release_weights,
    read_state_dict,
    save_checkpoint,
)
from surfsplat.model.checkpoint import RELEASE_KEY_RULES, ours_to_release, release_to_ours
from surfsplat.model.formula_weights import formula_tensor, hash_uniform, read_spec
from surfsplat.utils.checks import SurfSplatInputError


def _tiny(seed: int = 0) -> SurfSplat:
    torch.manual_seed(seed)
    return SurfSplat.from_preset("tiny").eval()


def _tiny_release_weights(seed: int = 7) -> dict[str, torch.Tensor]:
    """A tiny model's weights, randomised (zero-initialised layers too), under the release's names."""
    torch.manual_seed(seed)
    return {k: torch.randn_like(v) for k, v in export_release_state_dict(_tiny(seed)).items()}


# ----------------------------------------------------------------------------- formula weights
def test_formula_weights_reproduce_the_fixture_test_vectors(golden_subset_dir):
    spec = read_spec(golden_subset_dir / "formula_weights.json")
    entries = {t["key"]: t for t in spec["tensors"]}
    for vector in spec["test_vectors"]:
        key = vector["key"]
        assert zlib.crc32(key.encode()) == vector["crc32"]
        assert hash_uniform(key, 4).tolist() == vector["h_first4"]
        e = entries[key]
        w = formula_tensor(key, tuple(e["shape"]), e["mean"], e["std"]).ravel()[:4]
        assert [x.tobytes()[::-1].hex() for x in w] == vector["w_first4_float32_hex"]


def test_formula_tensor_statistics_and_constant_case():
    w = formula_tensor("some.weight", (256, 512), mean=0.25, std=2.0)
    assert w.dtype == np.float32 and w.shape == (256, 512)
    # the hash is a scrambled counter: uniform on [-sqrt(3), sqrt(3)] * std around the mean
    assert abs(float(w.mean()) - 0.25) < 0.02 and abs(float(w.std()) - 2.0) < 0.02
    assert float(np.abs(w - 0.25).max()) <= 2.0 * np.sqrt(3.0) + 1e-6
    assert np.all(formula_tensor("b", (3,), mean=0.1, std=0.0) == np.float32(0.1))


def test_formula_spec_errors_name_the_file(tmp_path):
    bad = tmp_path / "w.json"
    bad.write_text(json.dumps({"tensors": [], "num_tensors": 3}))
    with pytest.raises(SurfSplatInputError, match="w.json: 'tensors' lists 0 entries"):
        read_spec(bad)
    bad.write_text("{not json")
    with pytest.raises(SurfSplatInputError, match="w.json: not a readable"):
        read_spec(bad)


# ----------------------------------------------------------------------------- the mapping table
def test_mapping_is_a_bijection_on_every_preset():
    for name in ("tiny", "small", "base", "large"):
        with torch.device("meta"):
            model = SurfSplat.from_preset(name)
        ours = list(model.encoder.state_dict())
        release = [ours_to_release(k) for k in ours]
        assert None not in release
        assert len(set(release)) == len(release)
        assert [release_to_ours(k) for k in release] == ours


def test_mapping_rules_carry_indices_and_reject_unknown_names():
    assert release_to_ours("depth_predictor.regressor.1.3.out.2.weight") == "scales.1.regressor.3.out.2.weight"
    assert release_to_ours("depth_predictor.regressor_residual.0.bias") == "scales.0.residual.bias"
    assert (
        release_to_ours("depth_predictor.transformer.layers.5.cross_attn_ffn.mlp.0.weight")
        == "transformer.layers.5.cross_attn.mlp.0.weight"
    )
    assert release_to_ours("gaussian_head.2.bias") == "gaussian_head.head.2.bias"
    assert release_to_ours("decoder.background") is None
    assert len({src for src, _ in RELEASE_KEY_RULES}) == len(RELEASE_KEY_RULES)


# ----------------------------------------------------------------------------- release checkpoints
@pytest.mark.parametrize("layout", ["bare-pth", "lightning-ckpt", "safetensors"])
def test_release_checkpoints_load_in_every_layout(tmp_path, layout):
    weights = _tiny_release_weights()
    if layout == "bare-pth":
        path = tmp_path / "model.pth"
        torch.save(weights, path)
    elif layout == "lightning-ckpt":
        path = tmp_path / "model.ckpt"
        state = {f"encoder.{k}": v for k, v in weights.items()}
        state["losses.1.lpips.net.slice1.0.weight"] = torch.zeros(2)  # not the encoder's
        torch.save({"state_dict": state, "epoch": 3, "global_step": 1000}, path)
    else:
        path = tmp_path / "model.safetensors"
        save_file(weights, str(path))
    model = _tiny(seed=1)
    report = load_release_weights(model, path)
    assert report.loaded == len(weights)
    assert report.ignored == (["losses.1.lpips.net.slice1.0.weight"] if layout == "lightning-ckpt" else [])
    ours = model.encoder.state_dict()
    for key, value in weights.items():
        assert torch.equal(ours[release_to_ours(key)], value), key
    assert all(torch.equal(a, b) for a, b in zip(export_release_state_dict(model).values(), weights.values()))


def test_missing_unexpected_and_misshaped_keys_are_listed_in_one_error():
    weights = _tiny_release_weights()
    del weights["depth_predictor.backbone.conv1.weight"]
    weights["depth_predictor.upsampler.scratch.layer9_rn.weight"] = torch.zeros(1)
    weights["gaussian_head.2.bias"] = torch.zeros(5)
    model = _tiny()
    before = {k: v.clone() for k, v in model.state_dict().items()}
    with pytest.raises(SurfSplatInputError) as info:
        load_release_weights(model, weights)
    message = str(info.value)
    assert "missing 1: cnn.conv1.weight" in message
    assert "unexpected 1: depth_upsampler.scratch.layer9_rn.weight" in message
    assert "wrong shape 1: gaussian_head.head.2.bias (5,) (expected (32,))" in message
    # nothing was loaded partially
    assert all(torch.equal(before[k], v) for k, v in model.state_dict().items())


def test_keys_outside_the_release_layout_are_an_error():
    weights = _tiny_release_weights()
    weights["model.something"] = torch.zeros(1)
    with pytest.raises(SurfSplatInputError, match="1 keys are not release encoder names: model.something"):
        load_release_weights(_tiny(), weights)


def test_a_small_release_checkpoint_does_not_fit_the_tiny_model():
    with torch.device("meta"):
        small = export_release_state_dict(SurfSplat.from_preset("small"))
    weights = {k: torch.zeros(v.shape) for k, v in list(small.items())[:3]}
    with pytest.raises(SurfSplatInputError, match="wrong shape 3"):
        load_release_weights(_tiny(), weights)


# ----------------------------------------------------------------------------- broken files
def test_truncated_and_foreign_files_are_clear_errors(tmp_path):
    good = tmp_path / "good.pth"
    torch.save(_tiny_release_weights(), good)
    data = good.read_bytes()
    truncated = tmp_path / "truncated.pth"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(SurfSplatInputError, match="truncated.pth: unreadable PyTorch checkpoint"):
        read_state_dict(truncated)

    st = tmp_path / "good.safetensors"
    save_file({"a": torch.ones(1000)}, str(st))
    cut = tmp_path / "cut.safetensors"
    cut.write_bytes(st.read_bytes()[:200])
    with pytest.raises(SurfSplatInputError, match="cut.safetensors: unreadable safetensors file"):
        read_state_dict(cut)

    text = tmp_path / "notes.ckpt"
    text.write_text("this is not a checkpoint")
    with pytest.raises(SurfSplatInputError, match="notes.ckpt: not a checkpoint"):
        read_state_dict(text)
    empty = tmp_path / "empty.pth"
    empty.write_bytes(b"")
    with pytest.raises(SurfSplatInputError, match="empty.pth: not a checkpoint"):
        read_state_dict(empty)
    with pytest.raises(FileNotFoundError, match="absent.ckpt"):
        read_state_dict(tmp_path / "absent.ckpt")


class _Opaque:
    """Stands in for pickled Python objects of a foreign training setup (e.g. OmegaConf configs)."""


def test_pickled_objects_need_explicit_trust(tmp_path):
    path = tmp_path / "with_objects.ckpt"
    torch.save({"state_dict": _tiny_release_weights(), "hyper_parameters": _Opaque()}, path)
    with pytest.raises(SurfSplatInputError, match="trust_pickle=True"):
        read_state_dict(path)
    assert len(read_state_dict(path, trust_pickle=True)) == len(_tiny_release_weights())


def test_non_tensor_entries_are_an_error(tmp_path):
    path = tmp_path / "mixed.pth"
    torch.save({"a": torch.zeros(1), "b": 3}, path)
    with pytest.raises(SurfSplatInputError, match="entries that are not tensors: b"):
        read_state_dict(path)
    legacy = tmp_path / "legacy.pth"
    torch.save({"a": torch.zeros(2)}, legacy, _use_new_zipfile_serialization=False)
    assert torch.equal(read_state_dict(legacy)["a"], torch.zeros(2))


# ----------------------------------------------------------------------------- Depth Anything V2
def test_depth_anything_v2_weights_initialise_the_vit_only(tmp_path):
    torch.manual_seed(3)
    donor = _tiny(seed=3)
    vit = {f"pretrained.{k}": torch.randn_like(v) for k, v in donor.encoder.vit.state_dict().items()}
    vit["pretrained.mask_token"] = torch.zeros(1, 64)
    vit["depth_head.projects.0.weight"] = torch.zeros(4, 64, 1, 1)
    path = tmp_path / "depth_anything_v2_vits.pth"
    torch.save(vit, path)
    model = _tiny()
    cnn_before = model.encoder.cnn.conv1.weight.clone()
    report = load_depth_anything_v2(model, path)
    assert report.loaded == len(donor.encoder.vit.state_dict())
    assert sorted(report.ignored) == ["depth_head.projects.0.weight", "pretrained.mask_token"]
    for key, value in model.encoder.vit.state_dict().items():
        assert torch.equal(value, vit[f"pretrained.{key}"])
    assert torch.equal(model.encoder.cnn.conv1.weight, cnn_before)

    del vit["pretrained.norm.bias"]
    vit["backbone.conv1.weight"] = torch.zeros(1)
    torch.save(vit, path)
    with pytest.raises(
        SurfSplatInputError, match="not a Depth Anything V2 file; unexpected keys: backbone.conv1.weight"
    ):
        load_depth_anything_v2(model, path)
    del vit["backbone.conv1.weight"]
    with pytest.raises(SurfSplatInputError, match="missing 1: norm.bias"):
        load_depth_anything_v2(model, vit)


# ----------------------------------------------------------------------------- our own format
def test_save_and_load_round_trip(tmp_path):
    torch.manual_seed(0)
    model = SurfSplat.from_preset("tiny", adapter="paper", opacity_max=0.8).eval()
    for p in model.parameters():
        p.data.normal_(0, 0.02)
    weights_path, config_path = save_checkpoint(model, tmp_path / "run" / "model")
    assert weights_path.name == "model.safetensors" and config_path.name == "model.json"
    meta = json.loads(config_path.read_text())
    assert meta["config"]["adapter"]["opacity_max"] == 0.8
    assert meta["config"]["encoder"]["vit"]["taps"] == [0, 1, 2, 3]
    loaded = load_checkpoint(weights_path).eval()
    assert loaded.cfg == model.cfg
    for (ka, a), (kb, b) in zip(model.state_dict().items(), loaded.state_dict().items()):
        assert ka == kb and torch.equal(a, b)
    images = torch.rand(1, 2, 3, 64, 64)
    K = torch.tensor([[60.0, 0, 32], [0, 60, 32], [0, 0, 1]]).expand(2, 3, 3)
    c2w = torch.eye(4).repeat(2, 1, 1)
    c2w[1, 0, 3] = 0.2
    with torch.no_grad():
        a = model(images, Cameras(c2w, K), 0.5, 100.0)
        b = loaded(images, Cameras(c2w, K), 0.5, 100.0)
    assert torch.equal(a.gaussians.means, b.gaussians.means)


def test_own_checkpoint_errors(tmp_path):
    model = _tiny()
    weights_path, config_path = save_checkpoint(model, tmp_path / "m.safetensors")
    meta = json.loads(config_path.read_text())

    config_path.write_text(json.dumps({**meta, "format": "other"}))
    with pytest.raises(SurfSplatInputError, match="m.json: not a SurfSplat model configuration"):
        load_checkpoint(weights_path)
    meta["config"]["encoder"]["num_layers_typo"] = 3
    config_path.write_text(json.dumps(meta))
    with pytest.raises(SurfSplatInputError, match=r"unknown fields \['num_layers_typo'\] for EncoderConfig"):
        load_checkpoint(weights_path)
    del meta["config"]["encoder"]["num_layers_typo"]
    meta["config"]["encoder"]["feature_channels"] = 48  # weights no longer fit the described model
    config_path.write_text(json.dumps(meta))
    with pytest.raises(SurfSplatInputError, match="m.safetensors: does not match the model described by m.json"):
        load_checkpoint(weights_path)
    config_path.unlink()
    with pytest.raises(FileNotFoundError, match="m.json"):
        load_checkpoint(weights_path)
