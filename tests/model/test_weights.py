"""Named weights without internet: a fake Hugging Face cache and a fake torch hub cache, built here.

The hub's own cache layout (`models--owner--name/snapshots/REV/FILE`, `refs/main`) under a temporary
HF_HUB_CACHE with offline mode on, and a temporary TORCH_HOME, hold files in the real key layouts
(release, Depth Anything V2, UniMatch) with random or formula values. Every socket connection
attempt is recorded and refused, and the tests assert there was none.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import socket
from pathlib import Path

import huggingface_hub.constants
import pytest
import torch

from surfsplat.cli import main
from surfsplat.model import SurfSplat, export_release_state_dict, load_pretrained, save_checkpoint
from surfsplat.model import pretrained as pretrained_module
from surfsplat.model.checkpoint import ours_to_release, release_to_ours, unimatch_to_ours
from surfsplat.model.loading import ModelSpec, load_model
from surfsplat.model.pretrained import WeightsUnavailable, cached_file, check_resolution, fetch, hash_prefix
from surfsplat.model.registry import REGISTRY, Source, known_names, lookup, parse_hf_uri
from surfsplat.model.surfsplat import PRESETS
from surfsplat.train import build_model, train_preset
from surfsplat.train.config import config_from_dict, override, paper_init
from surfsplat.utils.checks import SurfSplatInputError
from tests.helpers.golden import OUTPUTS, lightning_release_state, output, rel, run_case

REVISION = "0123456789abcdef0123456789abcdef01234567"  # a commit hash, as the hub stores snapshots


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture
def no_network(monkeypatch) -> list:
    """Refuse and record every outgoing connection (DNS look-ups included)."""
    attempts: list = []

    def refuse(*args, **kwargs):
        attempts.append(args)
        raise OSError("network access in a test")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)
    return attempts


@pytest.fixture
def hf_cache(tmp_path, monkeypatch, no_network):
    """An empty Hugging Face cache in offline mode; returns put(repo, filename, write) -> file path.

    huggingface_hub reads HF_HUB_CACHE and HF_HUB_OFFLINE from the environment once, at import, into
    `huggingface_hub.constants`, which `hf_hub_download` and `try_to_load_from_cache` consult at each
    call; both the environment (for child processes) and the constants are set.
    """
    cache = tmp_path / "hf-cache"
    cache.mkdir()
    monkeypatch.setenv("HF_HUB_CACHE", str(cache))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(cache))
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)

    def put(repo: str, filename: str, write) -> Path:
        folder = cache / ("models--" + repo.replace("/", "--"))
        (folder / "refs").mkdir(parents=True, exist_ok=True)
        (folder / "refs" / "main").write_text(REVISION)
        path = folder / "snapshots" / REVISION / filename
        path.parent.mkdir(parents=True, exist_ok=True)
        write(path)
        return path

    put.root = cache
    return put


@pytest.fixture
def torch_home(tmp_path, monkeypatch) -> Path:
    """An empty TORCH_HOME; returns its hub/checkpoints folder (torch hub's download cache)."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch-home"))
    folder = tmp_path / "torch-home" / "hub" / "checkpoints"
    folder.mkdir(parents=True)
    return folder


def tiny_release_weights(seed: int = 7) -> dict[str, torch.Tensor]:
    torch.manual_seed(seed)
    with torch.device("meta"):
        names = export_release_state_dict(SurfSplat.from_preset("tiny"))
    return {k: torch.randn(v.shape) for k, v in names.items()}


# Real key layouts, written from the upstream module definitions (not from our modules), with the
# widths of ViT-S / UniMatch's 128-channel GMFlow.
def unimatch_layout() -> dict[str, tuple[int, ...]]:
    """unimatch/unimatch.py UniMatch(num_scales=1, feature_channels=128, upsample_factor=8, task="flow")."""
    shapes: dict[str, tuple[int, ...]] = {"backbone.conv1.weight": (64, 3, 7, 7)}
    previous = 64
    for stage, width in ((1, 64), (2, 96), (3, 128)):
        for block in (0, 1):
            incoming = previous if block == 0 else width
            shapes[f"backbone.layer{stage}.{block}.conv1.weight"] = (width, incoming, 3, 3)
            shapes[f"backbone.layer{stage}.{block}.conv2.weight"] = (width, width, 3, 3)
            if block == 0 and incoming != width:  # the 1x1 shortcut (its InstanceNorm has no weights)
                shapes[f"backbone.layer{stage}.{block}.downsample.0.weight"] = (width, incoming, 1, 1)
                shapes[f"backbone.layer{stage}.{block}.downsample.0.bias"] = (width,)
        previous = width
    shapes["backbone.conv2.weight"] = (128, 128, 1, 1)
    shapes["backbone.conv2.bias"] = (128,)
    for i in range(6):
        for part in ("self_attn", "cross_attn_ffn"):
            for proj in ("q_proj", "k_proj", "v_proj", "merge"):
                shapes[f"transformer.layers.{i}.{part}.{proj}.weight"] = (128, 128)
            shapes[f"transformer.layers.{i}.{part}.norm1.weight"] = (128,)
            shapes[f"transformer.layers.{i}.{part}.norm1.bias"] = (128,)
        shapes[f"transformer.layers.{i}.cross_attn_ffn.mlp.0.weight"] = (1024, 256)
        shapes[f"transformer.layers.{i}.cross_attn_ffn.mlp.2.weight"] = (128, 1024)
        shapes[f"transformer.layers.{i}.cross_attn_ffn.norm2.weight"] = (128,)
        shapes[f"transformer.layers.{i}.cross_attn_ffn.norm2.bias"] = (128,)
    for proj in ("q_proj", "k_proj"):  # SelfAttnPropagation
        shapes[f"feature_flow_attn.{proj}.weight"] = (128, 128)
        shapes[f"feature_flow_attn.{proj}.bias"] = (128,)
    shapes["upsampler.0.weight"] = (256, 2 + 128, 3, 3)  # convex upsampling, 8x
    shapes["upsampler.0.bias"] = (256,)
    shapes["upsampler.2.weight"] = (8**2 * 9, 256, 1, 1)
    shapes["upsampler.2.bias"] = (8**2 * 9,)
    return shapes


def depth_anything_vits_layout() -> dict[str, tuple[int, ...]]:
    """Depth-Anything-V2 DepthAnythingV2(encoder="vits", features=64, out_channels=[48, 96, 192, 384])."""
    d = 384
    shapes: dict[str, tuple[int, ...]] = {
        "pretrained.cls_token": (1, 1, d),
        "pretrained.pos_embed": (1, 37 * 37 + 1, d),
        "pretrained.mask_token": (1, d),
        "pretrained.patch_embed.proj.weight": (d, 3, 14, 14),
        "pretrained.patch_embed.proj.bias": (d,),
        "pretrained.norm.weight": (d,),
        "pretrained.norm.bias": (d,),
    }
    for i in range(12):
        b = f"pretrained.blocks.{i}."
        shapes.update(
            {
                b + "norm1.weight": (d,),
                b + "norm1.bias": (d,),
                b + "attn.qkv.weight": (3 * d, d),
                b + "attn.qkv.bias": (3 * d,),
                b + "attn.proj.weight": (d, d),
                b + "attn.proj.bias": (d,),
                b + "ls1.gamma": (d,),
                b + "norm2.weight": (d,),
                b + "norm2.bias": (d,),
                b + "mlp.fc1.weight": (4 * d, d),
                b + "mlp.fc1.bias": (4 * d,),
                b + "mlp.fc2.weight": (d, 4 * d),
                b + "mlp.fc2.bias": (d,),
                b + "ls2.gamma": (d,),
            }
        )
    out, features = (48, 96, 192, 384), 64
    for i, c in enumerate(out):
        shapes[f"depth_head.projects.{i}.weight"] = (c, d, 1, 1)
        shapes[f"depth_head.projects.{i}.bias"] = (c,)
        shapes[f"depth_head.scratch.layer{i + 1}_rn.weight"] = (features, c, 3, 3)
        r = f"depth_head.scratch.refinenet{i + 1}."
        shapes[r + "out_conv.weight"] = (features, features, 1, 1)
        shapes[r + "out_conv.bias"] = (features,)
        for unit in ("resConfUnit1", "resConfUnit2"):
            for conv in ("conv1", "conv2"):
                shapes[r + f"{unit}.{conv}.weight"] = (features, features, 3, 3)
                shapes[r + f"{unit}.{conv}.bias"] = (features,)
    shapes.update(
        {
            "depth_head.resize_layers.0.weight": (48, 48, 4, 4),
            "depth_head.resize_layers.0.bias": (48,),
            "depth_head.resize_layers.1.weight": (96, 96, 2, 2),
            "depth_head.resize_layers.1.bias": (96,),
            "depth_head.resize_layers.3.weight": (384, 384, 3, 3),
            "depth_head.resize_layers.3.bias": (384,),
            "depth_head.scratch.output_conv1.weight": (32, 64, 3, 3),
            "depth_head.scratch.output_conv1.bias": (32,),
            "depth_head.scratch.output_conv2.0.weight": (32, 32, 3, 3),
            "depth_head.scratch.output_conv2.0.bias": (32,),
            "depth_head.scratch.output_conv2.2.weight": (1, 32, 1, 1),
            "depth_head.scratch.output_conv2.2.bias": (1,),
        }
    )
    return shapes


def random_tensors(shapes: dict[str, tuple[int, ...]], seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {k: torch.randn(s, generator=g) for k, s in shapes.items()}


# ----------------------------------------------------------------------------- the registry
def test_registry_names_the_releases_files_and_the_papers_initialisations():
    release = {n: lookup(n) for n in known_names("model") if lookup(n).layout == "release"}
    assert {n: (e.source.repo, e.source.filename, e.preset, e.resolution, e.adapter) for n, e in release.items()} == {
        "re10k-256x256-small": ("binghe-sjtu/SurfSplat", "re10k-256x256-surfsplat-small.pth", "small", (256, 256), "official"),
        "re10k-256x256-base": ("binghe-sjtu/SurfSplat", "re10k-256x256-surfsplat-base.pth", "base", (256, 256), "official"),
        "re10k-256x256-large": ("binghe-sjtu/SurfSplat", "re10k-256x256-surfsplat-large.pth", "large", (256, 256), "official"),
        "re10k-256x448-base": ("binghe-sjtu/SurfSplat", "re10k-256x448-surfsplat-base.pth", "base", (256, 448), "official"),
    }  # fmt: skip
    for vit, preset, size in (("vits", "small", "Small"), ("vitb", "base", "Base"), ("vitl", "large", "Large")):
        entry = lookup(f"depth-anything-v2-{vit}", "monodepth")
        assert (entry.source.repo, entry.source.filename) == (
            f"depth-anything/Depth-Anything-V2-{size}",
            f"depth_anything_v2_{vit}.pth",
        )
        assert PRESETS[preset].vit.embed_dim == {"vits": 384, "vitb": 768, "vitl": 1024}[vit]
    assert hash_prefix(lookup("unimatch-gmflow-scale1").source.filename) == "e9887eda"
    assert hash_prefix(lookup("lpips-vgg16").source.filename) == "397923af"
    assert hash_prefix(lookup("lpips-vgg-lin").source.filename) is None
    for entry in REGISTRY.values():
        assert entry.licence and entry.description
        assert entry.preset is None or entry.preset in PRESETS


def test_hf_addresses_override_repository_and_file():
    assert parse_hf_uri("hf://me/mirror@v2/ckpts/re10k-256x256-surfsplat-base.pth") == Source(
        "hf", "ckpts/re10k-256x256-surfsplat-base.pth", repo="me/mirror", revision="v2"
    )
    # the same file name as a registry entry: that entry's preset, resolution and adapter
    entry = lookup("hf://me/mirror/ckpts/re10k-256x256-surfsplat-base.pth")
    assert (entry.preset, entry.resolution, entry.adapter, entry.layout) == ("base", (256, 256), "official", "release")
    with pytest.raises(SurfSplatInputError, match="expected hf://owner/repo"):
        parse_hf_uri("hf://only-owner/file.pth")


def test_unknown_names_and_wrong_roles_are_one_line_errors():
    with pytest.raises(
        SurfSplatInputError, match=r"unknown model weights name 're10k-256x256-tiny' \(known: re10k-256x256-small, "
    ):
        load_pretrained("re10k-256x256-tiny")
    with pytest.raises(SurfSplatInputError, match="depth-anything-v2-vits holds monodepth weights .*not model weights"):
        load_pretrained("depth-anything-v2-vits")
    with pytest.raises(FileNotFoundError, match="no/such.pth"):
        load_pretrained("no/such.pth")


# ----------------------------------------------------------------------------- the fake HF cache
def test_a_release_file_in_the_hub_cache_loads_by_address_offline(hf_cache, no_network):
    weights = tiny_release_weights()
    hf_cache("someone/mirror", "dir/tiny-release.pth", lambda p: torch.save(weights, p))
    model = load_pretrained("hf://someone/mirror/dir/tiny-release.pth", preset="tiny")
    assert model.cfg.adapter.mode == "official" and not model.training  # release files: the release's adapter
    state = model.encoder.state_dict()
    assert all(torch.equal(state[release_to_ours(k)], v) for k, v in weights.items())
    assert (
        load_pretrained("hf://someone/mirror/dir/tiny-release.pth", adapter="paper", preset="tiny").cfg.adapter.mode
        == "paper"
    )
    # the evaluation path takes the same strings
    model, label = load_model(ModelSpec("hf://someone/mirror/dir/tiny-release.pth", preset="tiny"))
    assert label == "tiny-release.pth" and torch.equal(model.encoder.cnn.conv1.weight, state["cnn.conv1.weight"])
    assert no_network == []


def test_offline_and_not_cached_names_the_file_the_repository_and_the_command(hf_cache, no_network, capsys):
    with pytest.raises(WeightsUnavailable) as info:
        load_pretrained("re10k-256x256-small")
    message = str(info.value)
    assert "\n" not in message
    assert "re10k-256x256-surfsplat-small.pth" in message and "binghe-sjtu/SurfSplat" in message
    assert "`surfsplat weights download re10k-256x256-small`" in message and "HF_HUB_OFFLINE" in message
    # the same through the command line: one line on stderr, exit code 2
    assert main(["weights", "download", "re10k-256x256-small"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("surfsplat weights: error: re10k-256x256-small: ")
    assert no_network == []


def test_a_truncated_cached_file_says_how_to_fetch_it_again(hf_cache, no_network):
    good = hf_cache.root / "good.pth"
    torch.save(tiny_release_weights(), good)
    data = good.read_bytes()
    hf_cache(
        "binghe-sjtu/SurfSplat", "re10k-256x256-surfsplat-small.pth", lambda p: p.write_bytes(data[: len(data) // 2])
    )
    with pytest.raises(
        SurfSplatInputError,
        match=r"unreadable PyTorch checkpoint \(truncated or corrupt\).*weights download re10k-256x256-small --force",
    ):
        load_pretrained("re10k-256x256-small")


def test_keys_that_do_not_fit_the_preset_are_counted_and_a_preset_mismatch_warns(hf_cache, caplog):
    # a tiny model's file stored under the small model's name
    hf_cache(
        "binghe-sjtu/SurfSplat", "re10k-256x256-surfsplat-small.pth", lambda p: torch.save(tiny_release_weights(), p)
    )
    with caplog.at_level(logging.WARNING, logger="surfsplat.weights"):
        with pytest.raises(SurfSplatInputError) as info:
            load_pretrained("re10k-256x256-small", preset="tiny")
    assert "re10k-256x256-small holds a small model: preset tiny is ignored" in caplog.text
    message = str(info.value)
    assert "does not match the 38," in message and "-parameter encoder (release layout)" in message
    assert (
        "missing " in message
        and "wrong shape " in message
        and "vit.cls_token (1, 1, 64) (expected (1, 1, 384))" in message
    )


def test_the_resolution_warning(hf_cache, caplog):
    hf_cache("someone/mirror", "re10k-256x448-surfsplat-base.pth", lambda p: torch.save(tiny_release_weights(), p))
    with pytest.raises(SurfSplatInputError):  # base metadata, tiny weights: only the metadata matters here
        load_pretrained("hf://someone/mirror/re10k-256x448-surfsplat-base.pth")
    model = SurfSplat.from_preset("tiny")
    model.pretrained_info = pretrained_module.PretrainedInfo(
        "re10k-256x448-base", Path("x"), "base", (256, 448), "official"
    )
    with caplog.at_level(logging.WARNING, logger="surfsplat.weights"):
        assert check_resolution(model, 256, 448) is None
        message = check_resolution(model, 512, 896)
    assert message == (
        "re10k-256x448-base was trained at 256x448 (HxW) and now runs at 512x896; quality may differ from the "
        "published numbers"
    )
    assert message in caplog.text
    assert check_resolution(SurfSplat.from_preset("tiny"), 512, 512) is None  # unknown provenance: nothing to say


@pytest.mark.slow
def test_the_small_release_loads_by_name_and_reproduces_the_golden_case(hf_cache, golden_dir, no_network):
    hf_cache(
        "binghe-sjtu/SurfSplat",
        "re10k-256x256-surfsplat-small.pth",
        lambda p: torch.save({"state_dict": lightning_release_state(golden_dir)}, p),
    )
    model = load_pretrained("re10k-256x256-small")
    assert model.pretrained_info.resolution == (256, 256) and model.cfg.adapter.mode == "official"
    pred, case = run_case(model, golden_dir)
    for what, bound in OUTPUTS:
        err = rel(output(pred, what), case[f"outputs.{what}"])
        assert err <= bound, f"{what}: relative L2 error {err:.3e} > {bound:.0e}"
    assert no_network == []


# ----------------------------------------------------------------------------- downloads (no network)
def test_hub_downloads_go_through_hf_hub_download(hf_cache, monkeypatch, tmp_path):
    calls = []

    def fake_download(repo_id, filename, **kwargs):
        calls.append((repo_id, filename, kwargs))
        target = tmp_path / "downloaded.pth"
        torch.save(tiny_release_weights(), target)
        return str(target)

    monkeypatch.setattr(huggingface_hub, "hf_hub_download", fake_download)
    path = fetch(lookup("depth-anything-v2-vitl"), force=True)
    assert path == tmp_path / "downloaded.pth"
    assert calls == [
        (
            "depth-anything/Depth-Anything-V2-Large",
            "depth_anything_v2_vitl.pth",
            {"revision": None, "force_download": True},
        )
    ]


def test_url_downloads_land_in_torch_hubs_cache_with_the_hash_prefix_checked(tmp_path, torch_home, monkeypatch):
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", False)
    served = tmp_path / "served.pth"
    torch.save({"x": torch.arange(5.0)}, served)
    digest = hashlib.sha256(served.read_bytes()).hexdigest()
    base = lookup("unimatch-gmflow-scale1")
    # a local file:// URL: torch hub's own downloader and hash check, no network
    good = dataclasses.replace(base, source=Source("url", f"gmflow-{digest[:8]}.pth", url=served.as_uri()))
    path = fetch(good)
    assert path == torch_home / f"gmflow-{digest[:8]}.pth" and path.read_bytes() == served.read_bytes()
    assert cached_file(good) == path
    wrong = "0" * 8 if digest[:8] != "0" * 8 else "1" * 8
    bad = dataclasses.replace(base, source=Source("url", f"gmflow-{wrong}.pth", url=served.as_uri()))
    with pytest.raises(
        WeightsUnavailable, match=f'download of .* is corrupt: invalid hash value \\(expected "{wrong}"'
    ):
        fetch(bad)
    assert not (torch_home / f"gmflow-{wrong}.pth").exists()  # nothing half-written under the final name
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    with pytest.raises(WeightsUnavailable, match="offline mode .* `surfsplat weights download unimatch-gmflow-scale1`"):
        fetch(base)


# ----------------------------------------------------------------------------- the paper's initialisation
def test_unimatch_names_map_like_the_releases_strict_false_load():
    # DepthSplat / the release load UniMatch's state dict into `depth_predictor` by name
    for key in unimatch_layout():
        ours = unimatch_to_ours(key)
        if ours is not None:
            assert (
                ours == release_to_ours("depth_predictor." + key) and ours_to_release(ours) == "depth_predictor." + key
            )


def test_paper_initialisation_fills_exactly_what_it_reports(hf_cache, torch_home, no_network):
    unimatch = random_tensors(unimatch_layout(), seed=1)
    torch.save({"model": unimatch}, torch_home / "gmflow-scale1-things-e9887eda.pth")  # UniMatch's {"model": ...}
    depth_anything = random_tensors(depth_anything_vits_layout(), seed=2)
    hf_cache(
        "depth-anything/Depth-Anything-V2-Small", "depth_anything_v2_vits.pth", lambda p: torch.save(depth_anything, p)
    )

    config = override(train_preset("small"), paper_init("small"))
    assert (config.model.init.monodepth, config.model.init.mvdepth) == (
        "depth-anything-v2-vits",
        "unimatch-gmflow-scale1",
    )
    torch.manual_seed(config.seed)
    model = build_model(config)
    torch.manual_seed(config.seed)
    untouched = build_model(override(config, {"model.init.monodepth": None, "model.init.mvdepth": None}))
    ours, before = model.encoder.state_dict(), untouched.encoder.state_dict()

    # every tensor the mappings claim equals the file's
    vit = {
        f"vit.{k[len('pretrained.') :]}": v
        for k, v in depth_anything.items()
        if k.startswith("pretrained.") and k != "pretrained.mask_token"
    }
    mv = {unimatch_to_ours(k): v for k, v in unimatch.items() if unimatch_to_ours(k) is not None}
    assert len(vit) == 4 + 12 * 14 + 2 and len(mv) == 19 + 6 * 16
    for key, value in {**vit, **mv}.items():
        assert torch.equal(ours[key], value), key
    # the whole monocular ViT and multi-view CNN + transformer are filled, everything else is the random init
    filled = set(vit) | set(mv)
    assert filled == {k for k in ours if k.startswith(("vit.", "cnn.", "transformer."))}
    for key in ours:
        if key not in filled:
            assert torch.equal(ours[key], before[key]), key

    def values(tensors, prefix):
        return f"{len([k for k in tensors if k.startswith(prefix)])} tensors, {sum(v.numel() for k, v in tensors.items() if k.startswith(prefix)):,} values"

    ignored_da = ["pretrained.mask_token"] + [k for k in depth_anything if k.startswith("depth_head.")]
    assert model.init_report[:-1] == [
        f"monodepth depth-anything-v2-vits: filled vit ({values(vit, 'vit.')})",
        f"monodepth depth-anything-v2-vits: ignored {len(ignored_da)} tensors of the file ({', '.join(ignored_da[:4])}, "
        f"... and {len(ignored_da) - 4} more)",
        f"mvdepth unimatch-gmflow-scale1: filled cnn ({values(mv, 'cnn.')}), transformer ({values(mv, 'transformer.')})",
        "mvdepth unimatch-gmflow-scale1: ignored 8 tensors of the file (feature_flow_attn.q_proj.weight, "
        "feature_flow_attn.q_proj.bias, feature_flow_attn.k_proj.weight, feature_flow_attn.k_proj.bias, ... and 4 more)",
    ]
    random_line = model.init_report[-1]
    assert random_line.startswith("random initialisation: ")
    groups = dict(part.rstrip(")").split(" (") for part in random_line[len("random initialisation: ") :].split("), "))
    rest = {k: v for k, v in ours.items() if k not in filled}
    assert groups == {g: values(rest, g + ".") for g in dict.fromkeys(k.split(".")[0] for k in rest)}
    assert not {"vit", "cnn", "transformer"} & set(groups)
    assert no_network == []


def test_unimatch_needs_the_matching_widths_and_the_init_needs_a_cache(hf_cache, torch_home):
    torch.save({"model": random_tensors(unimatch_layout(), seed=3)}, torch_home / "gmflow-scale1-things-e9887eda.pth")
    config = override(train_preset("tiny"), {"model.init.mvdepth": "unimatch-gmflow-scale1"})
    with pytest.raises(
        SurfSplatInputError,
        match=r"does not match the multi-view branch \(CNN \(16, 24, 32\) -> 32, 2 transformer layers\); unexpected 64: transformer.layers.2.self_attn.q_proj.weight, .*; wrong shape 51: cnn.conv1.weight \(64, 3, 7, 7\) \(expected \(16, 3, 7, 7\)\)",
    ):
        build_model(config)
    with pytest.raises(SurfSplatInputError, match="--paper-init: preset 'tiny' has no pretrained initialisation"):
        paper_init("tiny")
    missing = override(train_preset("tiny"), {"model.init.monodepth": "depth-anything-v2-vits"})
    with pytest.raises(
        WeightsUnavailable,
        match="depth_anything_v2_vits.pth of the Hugging Face repository depth-anything/Depth-Anything-V2-Small is not in the cache",
    ):
        build_model(missing)


def test_earlier_run_configurations_still_load():
    legacy = json.loads(json.dumps(train_preset("tiny").to_dict()))
    del legacy["model"]["init"]
    legacy["model"]["depth_anything"] = "pretrained/depth_anything_v2_vits.pth"
    config = config_from_dict(legacy)
    assert config.model.init.monodepth == "pretrained/depth_anything_v2_vits.pth" and config.model.init.mvdepth is None


def test_train_flags_set_the_initialisation(tmp_path):
    from surfsplat.cli import build_parser
    from surfsplat.commands.train import build_config

    args = build_parser().parse_args(["train", "--preset", "base", "--paper-init", "--out", str(tmp_path)])
    config, _ = build_config(args)
    assert (config.model.init.monodepth, config.model.init.mvdepth) == (
        "depth-anything-v2-vitb",
        "unimatch-gmflow-scale1",
    )
    args = build_parser().parse_args(
        ["train", "--preset", "small", "--depth-anything", "x.pth", "--init-mvdepth", "y.pth"]
    )
    config, _ = build_config(args)
    assert (config.model.init.monodepth, config.model.init.mvdepth) == ("x.pth", "y.pth")


# ----------------------------------------------------------------------------- our own checkpoints
def test_package_weights_load_by_name_and_carry_their_metadata(tmp_path, monkeypatch, capsys):
    torch.manual_seed(0)
    model = SurfSplat.from_preset("tiny").eval()
    meta = {"preset": "tiny", "resolution": [64, 64], "steps": 200, "source": "surfsplat train on synthetic data"}
    save_checkpoint(model, tmp_path / "tiny-synthetic", metadata=meta)
    monkeypatch.setattr(pretrained_module, "package_file", lambda name: tmp_path / name)
    loaded = load_pretrained("tiny-synthetic")
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), loaded.state_dict().values()))
    assert loaded.pretrained_info.resolution == (64, 64)
    assert main(["weights", "info", "tiny-synthetic", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["cached"] == str(tmp_path / "tiny-synthetic.safetensors")
    assert (info["preset"], info["resolution"], info["adapter"], info["steps"]) == ("tiny", [64, 64], "paper", 200)
    assert info["source"] == "surfsplat train on synthetic data" and info["licence"] == "MIT (this package)"
    assert info["tensors"] == len(model.state_dict())
    (tmp_path / "tiny-synthetic.json").unlink()
    with pytest.raises(WeightsUnavailable, match=r"tiny-synthetic.json is not shipped with this installation"):
        load_pretrained("tiny-synthetic")


def test_paths_keep_working_and_info_reads_training_checkpoints(tmp_path, capsys):
    from surfsplat.train.checkpoint import TrainingState, save_training_checkpoint, weights_metadata

    torch.manual_seed(1)
    model = SurfSplat.from_preset("tiny").eval()
    config = override(train_preset("tiny"), {"model.init.mvdepth": "unimatch-gmflow-scale1"}).to_dict()
    optimizer = torch.optim.AdamW(model.parameters()).state_dict()
    state = TrainingState(step=30, config=config, optimizer=optimizer, rng=[], data=[])
    folder = save_training_checkpoint(tmp_path / "run", model, state)
    loaded = load_pretrained(tmp_path / "run")  # a run folder: its newest checkpoint
    assert torch.equal(loaded.encoder.cnn.conv1.weight, model.encoder.cnn.conv1.weight)
    assert main(["weights", "info", str(folder), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info == {
        "file": str(folder / "model.safetensors"),
        "layout": "surfsplat",
        **json.loads(json.dumps(weights_metadata(state))),
        "tensors": len(model.state_dict()),
        "values": sum(v.numel() for v in model.state_dict().values()),
        "bytes": (folder / "model.safetensors").stat().st_size,
    }
    assert (info["preset"], info["resolution"], info["steps"]) == ("tiny", [64, 64], 30)
    assert info["source"] == "surfsplat train on synthetic data, initialised from mvdepth unimatch-gmflow-scale1"

    release = tmp_path / "release.pth"
    torch.save({"state_dict": {f"encoder.{k}": v for k, v in tiny_release_weights().items()}}, release)
    assert main(["weights", "info", str(release)]) == 0
    text = capsys.readouterr().out
    assert "layout   release" in text and "preset   unknown (ViT width 64)" in text


def test_weights_list_and_path_see_the_caches(hf_cache, torch_home, capsys):
    path = hf_cache("binghe-sjtu/SurfSplat", "re10k-256x448-surfsplat-base.pth", lambda p: p.write_bytes(b"x"))
    (torch_home / "vgg16-397923af.pth").write_bytes(b"y")
    assert main(["weights", "list", "--json"]) == 0
    rows = {r["name"]: r for r in json.loads(capsys.readouterr().out)}
    assert rows["re10k-256x448-base"]["cached"] == str(path) and rows["re10k-256x256-base"]["cached"] is None
    assert rows["lpips-vgg16"]["cached"] == str(torch_home / "vgg16-397923af.pth")
    assert set(rows) == set(REGISTRY)
    assert main(["weights", "path", "re10k-256x448-base"]) == 0
    assert capsys.readouterr().out.strip() == str(path)
    assert main(["weights", "path", "re10k-256x256-base"]) == 2
    assert "not cached on this machine" in capsys.readouterr().err


def test_training_prints_the_initialisation_report_and_records_it(tmp_path, capsys, caplog):
    from surfsplat.train import fit

    # Depth Anything V2's layout at the tiny preset's ViT width (a stand-in: no real file is that small)
    with torch.device("meta"):
        names = SurfSplat.from_preset("tiny").encoder.vit.state_dict()
    weights = {f"pretrained.{k}": torch.randn(v.shape) for k, v in names.items()}
    weights["depth_head.projects.0.weight"] = torch.randn(16, 64, 1, 1)
    path = tmp_path / "depth_anything_tiny.pth"
    torch.save(weights, path)
    quick = {
        "out_dir": str(tmp_path / "run"),
        "steps": 1,
        "checkpoint_every": 1,
        "val_every": 0,
        "image_every": 0,
        "progress": False,
        "data.image_shape": [32, 32],
        "data.num_target_views": 1,
        "data.synthetic_length": 2,
        "model.init.monodepth": str(path),
    }
    with caplog.at_level(logging.INFO, logger="surfsplat"):
        result = fit(override(train_preset("tiny"), quick))
    out = capsys.readouterr().out + caplog.text  # the run's messages: printed, or logged at INFO
    assert f"monodepth {path}: filled vit ({len(names)} tensors, " in out
    assert f"monodepth {path}: ignored 1 tensors of the file (depth_head.projects.0.weight)" in out
    assert "random initialisation: cnn (" in out and "vit (" not in out.split("random initialisation: ")[1]
    assert main(["weights", "info", str(result.checkpoint), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["source"] == f"surfsplat train on synthetic data, initialised from monodepth {path}"
    assert (info["steps"], info["resolution"]) == (1, [32, 32])
