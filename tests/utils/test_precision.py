"""bf16 precision: choosing it (`surfsplat.utils.precision`), the fast exact paths it uses, and the
released model's function under `torch.autocast(..., dtype=torch.bfloat16)`.

The bf16 bounds are the issue's: relative L2 to the release's float32 outputs <= 5e-3 for depths
and means, <= 1e-2 for opacities. The float32 function is proven bit for bit unchanged by
tests/model/test_encoder_golden.py (same bounds as before) and here by exact equalities.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from safetensors.torch import load_file

from surfsplat import Cameras
from surfsplat.model import SurfSplat, load_release_weights
from surfsplat.model.encoder.conv import ReplicateConv2d
from surfsplat.model.encoder.cost_volume import (
    gathered_cost_volume,
    linear_inverse_depth_candidates,
    local_inverse_depth_candidates,
    plane_sweep_cost_volume,
)
from surfsplat.model.encoder.encoder import PARTS
from surfsplat.utils import precision
from surfsplat.utils.checks import SurfSplatInputError
from tests.helpers.golden import lightning_release_state, output, rel

BF16_BOUNDS = [("depths", 5e-3), ("gaussians.means", 5e-3), ("gaussians.opacities", 1e-2)]


# ------------------------------------------------------------------ choosing the precision
@pytest.mark.parametrize("text, expected", [("auto", "auto"), ("fp32", "fp32"), ("BF16", "bf16"), (" bf16 ", "bf16")])
def test_parse_precision(text, expected):
    assert precision.parse_precision(text) == expected


@pytest.mark.parametrize("text", ["fp16", "float32", "", "bfloat16"])
def test_parse_precision_rejects_other_names_naming_the_option(text):
    with pytest.raises(SurfSplatInputError, match=r"--precision: expected one of auto, fp32, bf16"):
        precision.parse_precision(text)


def test_cpu_flags_are_read_from_cpuinfo(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx512f avx512_bf16 amx_tile amx_bf16\n\nprocessor\t: 1\n")
    assert precision.cpu_bf16_flags(str(info)) == {"avx512_bf16", "amx_bf16"}
    info.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f\n")
    precision.cpu_bf16_flags.cache_clear()
    assert precision.cpu_bf16_flags(str(info)) == frozenset()
    assert precision.cpu_bf16_flags(str(tmp_path / "absent")) == frozenset()


@pytest.mark.parametrize("flags, expected", [({"amx_bf16"}, "bf16"), ({"avx512_bf16"}, "bf16"), (set(), "fp32")])
def test_auto_picks_bf16_only_on_cpus_with_native_bf16(monkeypatch, flags, expected):
    monkeypatch.setattr(precision, "cpu_bf16_flags", lambda: frozenset(flags))
    assert precision.resolve_precision("auto", torch.device("cpu")) == expected
    # an explicit choice is kept whatever the hardware
    assert precision.resolve_precision("fp32", "cpu") == "fp32"
    assert precision.resolve_precision("bf16", "cpu") == "bf16"


def test_auto_on_cuda_follows_native_bf16_support(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    for native in (True, False):
        monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda including_emulation=True, n=native: n)
        assert precision.resolve_precision("auto", "cuda") == ("bf16" if native else "fp32")


def test_autocast_context_runs_what_it_reports(monkeypatch):
    monkeypatch.setattr(precision, "cpu_bf16_flags", lambda: frozenset({"amx_bf16"}))
    a, b = torch.randn(8, 8), torch.randn(8, 8)
    with precision.autocast("auto", "cpu") as ran:
        assert ran == "bf16" and (a @ b).dtype == torch.bfloat16
    with precision.autocast("fp32", "cpu") as ran:
        assert ran == "fp32" and (a @ b).dtype == torch.float32
    assert precision.autocast_dtype("bf16") == torch.bfloat16 and precision.autocast_dtype("fp32") is None


def test_cat_keeps_bf16_inside_autocast_and_is_torch_cat_outside():
    a, b = torch.randn(2, 3, 4), torch.randn(2, 5, 4).bfloat16()
    assert torch.equal(precision.cat([a, a], dim=1), torch.cat([a, a], dim=1))
    assert precision.cat([a, b], dim=1).dtype == torch.float32  # outside autocast: torch's promotion
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = precision.cat([a, b], dim=1)
    assert out.dtype == torch.bfloat16
    assert torch.equal(out, torch.cat([a.bfloat16(), b], dim=1))


# ------------------------------------------------------------------ fast paths and their references
def test_replicate_conv_is_nn_conv_bit_for_bit_and_stays_bf16_under_autocast():
    torch.manual_seed(0)
    ours = ReplicateConv2d(5, 7, 3, padding=1)
    reference = torch.nn.Conv2d(5, 7, 3, padding=1, padding_mode="replicate")
    reference.load_state_dict(ours.state_dict())
    x = torch.randn(2, 5, 9, 11)
    assert torch.equal(ours(x), reference(x))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = ours(x.bfloat16())
        expected = F.conv2d(F.pad(x.bfloat16(), (1, 1, 1, 1), mode="replicate"), ours.weight, ours.bias)
    assert y.dtype == torch.bfloat16
    assert torch.equal(y, expected)


def _views(n: int, m: int, c: int, h: int, w: int, seed: int):
    """Random features and cameras looking roughly the same way, some samples off the map."""
    g = torch.Generator().manual_seed(seed)
    ref = torch.randn(n, c, h, w, generator=g, dtype=torch.float64)
    src = torch.randn(n, m, c, h, w, generator=g, dtype=torch.float64)
    K = torch.tensor([[0.9 * w, 0, w / 2], [0, 0.9 * h, h / 2], [0, 0, 1.0]], dtype=torch.float64).repeat(n, 1, 1)

    def pose() -> torch.Tensor:
        angle = 0.1 * torch.randn(3, generator=g, dtype=torch.float64)
        x = torch.zeros(3, 3, dtype=torch.float64)
        x[0, 1], x[0, 2], x[1, 2] = -angle[2], angle[1], -angle[0]
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, :3] = torch.linalg.matrix_exp(x - x.T)
        c2w[:3, 3] = 0.3 * torch.randn(3, generator=g, dtype=torch.float64)
        return c2w

    ref_c2w = torch.stack([pose() for _ in range(n)])
    src_c2w = torch.stack([torch.stack([pose() for _ in range(m)]) for _ in range(n)])
    return ref, src, K, ref_c2w, src_c2w


@pytest.mark.parametrize("per_pixel", [False, True])
def test_gathered_cost_volume_matches_the_warping_reference(per_pixel):
    n, m, c, h, w, d = 2, 2, 8, 12, 16, 10
    ref, src, K, ref_c2w, src_c2w = _views(n, m, c, h, w, seed=1)
    inv = linear_inverse_depth_candidates(torch.full((n,), 0.05, dtype=torch.float64), torch.full((n,), 2.0), d)
    if per_pixel:  # the cascade's finer scale: candidates around a coarse inverse depth per pixel
        coarse = 0.2 + torch.rand(n, 1, h, w, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
        inv = local_inverse_depth_candidates(coarse, inv[:, 0], inv[:, -1], d, torch.full((n,), 0.05))
    expected = plane_sweep_cost_volume(ref, src, K, ref_c2w, src_c2w, inv)
    got = gathered_cost_volume(ref, src, K, ref_c2w, src_c2w, inv)
    assert got.shape == (n, d, h, w)
    # some samples fall off the map (zero padding) and some inside: both paths are exercised
    assert (expected == 0).any() and (expected != 0).float().mean() > 0.5
    torch.testing.assert_close(got, expected, rtol=1e-10, atol=1e-10)


def test_gathered_cost_volume_gradients_match_the_reference_and_gradcheck():
    n, m, c, h, w, d = 1, 1, 3, 5, 6, 4
    ref, src, K, ref_c2w, src_c2w = _views(n, m, c, h, w, seed=3)
    inv = linear_inverse_depth_candidates(torch.full((n,), 0.1, dtype=torch.float64), torch.full((n,), 1.5), d)
    ref.requires_grad_(True)
    src.requires_grad_(True)
    weights = torch.randn(n, d, h, w, dtype=torch.float64)
    grads = []
    for fn in (plane_sweep_cost_volume, gathered_cost_volume):
        (fn(ref, src, K, ref_c2w, src_c2w, inv) * weights).sum().backward()
        grads.append((ref.grad.clone(), src.grad.clone()))
        ref.grad = src.grad = None
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)
    assert torch.autograd.gradcheck(lambda r, s: gathered_cost_volume(r, s, K, ref_c2w, src_c2w, inv), (ref, src))


def test_keep_float32_names_parts_and_rejects_unknown_ones():
    model = SurfSplat.from_preset("tiny")
    model.encoder.keep_float32(["vit", "gaussian_head"])
    assert model.encoder.float32_parts == {"vit", "gaussian_head"}
    with pytest.raises(SurfSplatInputError, match="float32 parts.*unet"):
        model.encoder.keep_float32(["unet"])
    assert set(PARTS) >= model.encoder.float32_parts


def test_tiny_model_under_autocast_is_float32_where_it_must_be():
    torch.manual_seed(0)
    model = SurfSplat.from_preset("tiny").eval()
    images = torch.rand(1, 2, 3, 64, 64)
    K = torch.tensor([[58.0, 0, 32], [0, 58.0, 32], [0, 0, 1]]).repeat(2, 1, 1)
    c2w = torch.eye(4).repeat(2, 1, 1)
    c2w[1, 0, 3] = 0.2
    with torch.no_grad():
        fp32 = model(images, Cameras(c2w, K), 0.5, 50.0)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            bf16 = model(images, Cameras(c2w, K), 0.5, 50.0)
        again = model(images, Cameras(c2w, K), 0.5, 50.0)
    g = bf16.gaussians
    for t in (bf16.depths, g.means, g.covariances, g.opacities, g.sh):
        assert t.dtype == torch.float32  # the renderer gets float32 surfels
    assert torch.equal(fp32.depths, again.depths)  # autocast leaves no state behind
    assert rel(bf16.depths, fp32.depths) < 2e-2


# ------------------------------------------------------------------ the released function in bf16
@pytest.fixture(scope="module")
def release_model(golden_subset_dir, tmp_path_factory):
    ckpt = tmp_path_factory.mktemp("release") / "surfsplat-small.ckpt"
    torch.save({"state_dict": lightning_release_state(golden_subset_dir), "global_step": 0, "epoch": 0}, ckpt)
    model = SurfSplat.from_preset("small", adapter="official").eval()
    load_release_weights(model, ckpt)
    return model


def _bf16_run(model, tensors):
    _, _, _, h, w = tensors["context.image"].shape
    cameras = Cameras.from_normalized(tensors["context.extrinsics"][0], tensors["context.intrinsics"][0], w, h)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        return model(tensors["context.image"], cameras, tensors["context.near"], tensors["context.far"])


@pytest.fixture(scope="module")
def bf16_run(release_model, golden_subset):
    return _bf16_run(release_model, golden_subset.tensors)


@pytest.mark.slow
@pytest.mark.parametrize("what, bound", BF16_BOUNDS)
def test_bf16_outputs_match_the_release_at_sampled_rows(bf16_run, golden_subset, what, bound):
    d = golden_subset.tensors
    ours = output(bf16_run, what)
    assert ours.dtype == torch.float32
    if what == "depths":
        ours = ours.reshape(1, -1)
    err = rel(ours[:, d["rows"].long()], d[f"outputs.{what}"])
    assert err <= bound, f"{what} in bf16: relative L2 error over the sampled rows {err:.3e} > {bound:.0e}"


@pytest.mark.slow
@pytest.mark.parametrize("what, bound", BF16_BOUNDS)
def test_bf16_outputs_match_the_release(bf16_run, golden_dir, golden_subset, what, bound):
    case = load_file(str(golden_dir / "case_identity.safetensors"))
    assert torch.equal(case["context.image"], golden_subset.tensors["context.image"])
    err = rel(output(bf16_run, what), case[f"outputs.{what}"])
    assert err <= bound, f"{what} in bf16: relative L2 error {err:.3e} > {bound:.0e}"


# ------------------------------------------------------------------ the commands' --precision
@pytest.mark.parametrize("command", ["reconstruct", "eval", "train", "demo"])
def test_every_command_takes_precision(command, capsys):
    from surfsplat.cli import build_parser

    parser = build_parser()
    required = {
        "reconstruct": ["--checkpoint", "m.ckpt", "--images", "a.png", "b.png"],
        "eval": ["--data", "chunks", "--index", "index.json"],
        "train": [],
        "demo": [],
    }[command]
    for value in ("auto", "fp32", "bf16"):
        assert parser.parse_args([command, *required, "--precision", value]).precision == value
    if command != "train":  # train keeps its configuration's value unless the option is given
        assert parser.parse_args([command, *required]).precision == "auto"
    with pytest.raises(SystemExit):
        parser.parse_args([command, *required, "--precision", "int8"])
    assert "--precision" in capsys.readouterr().err
