"""LPIPS-VGG v0.1: the reference package's outputs from both weight-file layouts, lookup, errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from surfsplat.metrics import Lpips, LpipsUnavailable, find_lpips_weights, load_lpips, try_load_lpips
from surfsplat.metrics.lpips import VGG16_FILENAME, lin_shapes, vgg_shapes
from surfsplat.model.formula_weights import formula_tensor  # the golden fixtures' weight formula
from surfsplat.utils.checks import SurfSplatInputError

# Tiny stand-ins for torchvision's classifier keys: a real file carries them and they are ignored.
CLASSIFIER = {"classifier.0.weight": torch.zeros(4, 3), "classifier.0.bias": torch.zeros(4)}


@pytest.fixture(scope="module")
def formula_states(golden_subset_dir: Path) -> tuple[dict, dict]:
    spec = json.loads((golden_subset_dir / "lpips" / "formula_weights.json").read_text())
    state = {
        t["key"]: torch.from_numpy(formula_tensor(t["key"], tuple(t["shape"]), t["mean"], t["std"]))
        for t in spec["tensors"]
    }
    vgg = {k: v for k, v in state.items() if k.startswith("features.")}
    lin = {k: v for k, v in state.items() if k.startswith("lin")}
    assert set(vgg) == set(vgg_shapes()) and set(lin) == set(lin_shapes())
    return vgg, lin


def random_states(seed: int = 0) -> tuple[dict, dict]:
    """Random weights, for tests of structure only (never reported as LPIPS)."""
    g = torch.Generator().manual_seed(seed)
    vgg = {k: 0.1 * torch.randn(s, generator=g) for k, s in vgg_shapes().items()}
    lin = {k: torch.rand(s, generator=g) for k, s in lin_shapes().items()}
    return vgg, lin


@pytest.fixture(scope="module")
def random_model() -> Lpips:
    return Lpips(*random_states(5))


def write_files(folder: Path, vgg: dict, lin: dict, *, legacy: bool, classifier: bool) -> tuple[Path, Path]:
    """Write the trunk in torchvision's layout and the heads in the lpips package's layout."""
    folder.mkdir(parents=True, exist_ok=True)
    vgg_path, lin_path = folder / VGG16_FILENAME, folder / "vgg.pth"
    torch.save({**vgg, **(CLASSIFIER if classifier else {})}, vgg_path, _use_new_zipfile_serialization=not legacy)
    torch.save(lin, lin_path, _use_new_zipfile_serialization=not legacy)
    return vgg_path, lin_path


def test_lpips_matches_reference_package_from_written_files(tmp_path, formula_states, golden_subset_dir):
    vgg_path, lin_path = write_files(tmp_path, *formula_states, legacy=True, classifier=True)
    model = load_lpips(vgg_path, lin_path)
    # The fixture's 64x64 cases, copied unchanged into the repository (tests/data/README.md).
    cases = load_file(str(golden_subset_dir / "lpips" / "cases64.safetensors"))
    with torch.no_grad():
        d64 = model(cases["a64"], cases["b64"])
        same = model(cases["a64"], cases["a64"])
    assert ((d64 - cases["lpips64"]) / cases["lpips64"]).abs().max().item() <= 1e-5
    assert same.abs().max().item() <= 1e-7 and cases["lpips_same"].abs().max().item() == 0.0


def test_lpips_matches_reference_package_at_256_pixels(tmp_path, formula_states, golden_dir):
    """The 256x256 pair (1.5 MB of float32 inputs) lives only in the full fixture."""
    cases = load_file(str(golden_dir / "lpips" / "cases.safetensors"))
    model = load_lpips(*write_files(tmp_path, *formula_states, legacy=True, classifier=True))
    with torch.no_grad():
        d256 = model(cases["a256"], cases["b256"])
    assert ((d256 - cases["lpips256"]) / cases["lpips256"]).abs().max().item() <= 1e-5


@pytest.mark.parametrize("legacy", [True, False])
@pytest.mark.parametrize("classifier", [True, False])
def test_both_serialisations_with_and_without_classifier_load_the_same_weights(tmp_path, legacy, classifier):
    vgg, lin = random_states(1)
    model = load_lpips(*write_files(tmp_path, vgg, lin, legacy=legacy, classifier=classifier))
    for key, value in {**vgg, **lin}.items():
        assert torch.equal(getattr(model, key.replace(".", "_")), value), key


def test_weights_are_found_in_the_standard_locations(tmp_path, monkeypatch):
    vgg, lin = random_states(2)
    # torchvision's cache: $TORCH_HOME/hub/checkpoints; the heads: an installed lpips package.
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    hub = tmp_path / "torch_home" / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    torch.save({**vgg, **CLASSIFIER}, hub / VGG16_FILENAME)
    package = tmp_path / "site" / "lpips"
    (package / "weights" / "v0.1").mkdir(parents=True)
    (package / "__init__.py").write_text("raise ImportError('finding the weights must not import lpips')\n")
    torch.save(lin, package / "weights" / "v0.1" / "vgg.pth")
    monkeypatch.syspath_prepend(str(tmp_path / "site"))

    paths = find_lpips_weights()
    assert paths.vgg == hub / VGG16_FILENAME
    assert paths.lin == package / "weights" / "v0.1" / "vgg.pth"
    model = load_lpips()
    assert torch.equal(model.features_0_weight, vgg["features.0.weight"])

    # Without TORCH_HOME, XDG_CACHE_HOME/torch/hub is torch's cache.
    monkeypatch.delenv("TORCH_HOME")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    xdg_hub = tmp_path / "xdg" / "torch" / "hub" / "checkpoints"
    xdg_hub.mkdir(parents=True)
    torch.save(vgg, xdg_hub / VGG16_FILENAME)
    assert find_lpips_weights().vgg == xdg_hub / VGG16_FILENAME


def test_missing_weights_say_lpips_unavailable(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "empty"))
    with pytest.raises(LpipsUnavailable, match=r"^LPIPS unavailable: VGG16 weights vgg16-397923af.pth not found"):
        load_lpips()
    result = try_load_lpips()
    assert isinstance(result, LpipsUnavailable)
    assert str(result).startswith("LPIPS unavailable: ") and str(tmp_path / "empty") in str(result)
    assert isinstance(result, SurfSplatInputError)  # the CLI prints it as one line

    vgg, lin = random_states(3)
    vgg_path, _ = write_files(tmp_path / "files", vgg, lin, legacy=False, classifier=False)
    with pytest.raises(LpipsUnavailable, match="does not exist"):
        load_lpips(vgg_path, tmp_path / "nowhere.pth")


def test_unreadable_or_wrong_files_are_named(tmp_path):
    vgg, lin = random_states(4)
    vgg_path, lin_path = write_files(tmp_path, vgg, lin, legacy=False, classifier=False)

    corrupt = tmp_path / "corrupt.pth"
    corrupt.write_bytes(vgg_path.read_bytes()[:1000])
    with pytest.raises(LpipsUnavailable, match=r"cannot read VGG16 weights file .*corrupt\.pth"):
        load_lpips(corrupt, lin_path)

    # A file in the wrong layout (the heads given as the trunk) names the missing key.
    with pytest.raises(
        LpipsUnavailable, match=r"missing \['features\.0\.weight'.*unexpected \['lin0\.model\.1\.weight'"
    ):
        load_lpips(lin_path, lin_path)

    bad = dict(lin)
    bad["lin2.model.1.weight"] = torch.zeros(1, 128, 1, 1)
    torch.save(bad, tmp_path / "bad_lin.pth")
    with pytest.raises(
        LpipsUnavailable, match=r"lin2\.model\.1\.weight has shape \(1, 128, 1, 1\), expected \(1, 256, 1, 1\)"
    ):
        load_lpips(vgg_path, tmp_path / "bad_lin.pth")

    # Unexpected extra keys other than torchvision's classifier are an error, not ignored.
    torch.save({**vgg, "features.30.weight": torch.zeros(1)}, tmp_path / "extra.pth")
    with pytest.raises(LpipsUnavailable, match=r"unexpected \['features\.30\.weight'\]"):
        load_lpips(tmp_path / "extra.pth", lin_path)


def test_lpips_is_a_fixed_differentiable_function_of_its_inputs(random_model):
    model = random_model
    assert list(model.parameters()) == [] and model.state_dict() == {}  # never trained, never saved
    g = torch.Generator().manual_seed(6)
    a = torch.rand(2, 3, 16, 24, generator=g)
    b = torch.rand(2, 3, 16, 24, generator=g, requires_grad=True)
    d = model(a, b)
    d.sum().backward()
    assert b.grad is not None and bool(torch.isfinite(b.grad).all()) and b.grad.abs().sum() > 0
    with torch.no_grad():
        # Symmetric by construction, float64 input computes the same float32 function, and batch
        # items are independent: one call checks all three.
        swapped_first = model(b[:1].double(), a[:1].double())
        torch.testing.assert_close(swapped_first, d[:1], rtol=1e-5, atol=0)
        assert (d > 0).all()


def test_lpips_rejects_bad_inputs(random_model):
    model = random_model
    with pytest.raises(SurfSplatInputError, match="at least 16x16"):
        model(torch.rand(1, 3, 15, 32), torch.rand(1, 3, 15, 32))
    with pytest.raises(SurfSplatInputError, match="prediction"):
        model(torch.rand(1, 4, 32, 32), torch.rand(1, 4, 32, 32))
    with pytest.raises(SurfSplatInputError, match="target"):
        model(torch.rand(1, 3, 32, 32), torch.rand(2, 3, 32, 32))


def test_lpips_golden_through_the_weights_names(tmp_path, monkeypatch, formula_states, golden_dir, capsys):
    from surfsplat.cli import main

    # A fake TORCH_HOME holding both files where `surfsplat weights download lpips-vgg16 lpips-vgg-lin`
    # puts them (nothing is downloaded here).
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    hub = tmp_path / "torch_home" / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    vgg, lin = formula_states
    with pytest.raises(LpipsUnavailable, match="run `surfsplat weights download lpips-vgg16`"):
        load_lpips("lpips-vgg16", "lpips-vgg-lin")
    torch.save({**vgg, **CLASSIFIER}, hub / VGG16_FILENAME)
    with pytest.raises(LpipsUnavailable, match="run `surfsplat weights download lpips-vgg-lin`"):
        load_lpips("lpips-vgg16", "lpips-vgg-lin")
    torch.save(lin, hub / "lpips-v0.1-vgg.pth")
    assert main(["weights", "path", "lpips-vgg-lin"]) == 0
    assert capsys.readouterr().out.strip() == str(hub / "lpips-v0.1-vgg.pth")

    model = load_lpips("lpips-vgg16", "lpips-vgg-lin")
    cases = load_file(str(golden_dir / "lpips" / "cases.safetensors"))
    with torch.no_grad():
        d64 = model(cases["a64"], cases["b64"])
        d256 = model(cases["a256"], cases["b256"])
    assert ((d64 - cases["lpips64"]) / cases["lpips64"]).abs().max().item() <= 1e-5
    assert ((d256 - cases["lpips256"]) / cases["lpips256"]).abs().max().item() <= 1e-5
