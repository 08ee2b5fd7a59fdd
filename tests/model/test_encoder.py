"""Encoder: closed-form checks of its parts, slow twins of the fast paths, presets, and the model API."""

from __future__ import annotations

import gzip
import json
import math

import pytest
import torch
import torch.nn.functional as F

from surfsplat import Cameras
from surfsplat.model import PRESETS, SurfSplat, export_release_state_dict
from surfsplat.model.encoder import cost_volume as cv
from surfsplat.model.encoder.mv_transformer import (
    AttentionLayer,
    MultiViewTransformer,
    release_cross_view_mask,
    select_neighbours,
    shifted_window_mask,
    sine_position_code,
    window_order,
)
from surfsplat.model.encoder.unet import CrossViewAttentionBlock
from surfsplat.utils.checks import SurfSplatInputError

# The golden fixture's manifests, reduced to the parameter count and key shapes (tests/data/README.md).
MANIFESTS = {
    "small": "manifest_small.json.gz",
    "base": "manifest_vitb_official_base.json.gz",
    "large": "manifest_vitl_official_large.json.gz",
}


def _cameras(num_views: int, size: int, baseline: float = 0.1, focal: float = 0.9) -> Cameras:
    """Cameras on a horizontal line looking down +z, intrinsics in pixels of size x size images."""
    K = torch.tensor([[focal * size, 0, size / 2], [0, focal * size, size / 2], [0, 0, 1.0]])
    c2w = torch.eye(4).repeat(num_views, 1, 1)
    c2w[:, 0, 3] = baseline * torch.arange(num_views, dtype=torch.float32)
    return Cameras(c2w, K.expand(num_views, 3, 3).clone())


def _tiny(seed: int = 0, **adapter_fields) -> SurfSplat:
    torch.manual_seed(seed)
    return SurfSplat.from_preset("tiny", **adapter_fields).eval()


# ----------------------------------------------------------------------------- presets
@pytest.mark.parametrize("name", ["small", "base", "large"])
def test_presets_have_the_release_parameters(name, golden_subset_dir):
    """Every preset builds the release's state dict: same keys, shapes and parameter count."""
    manifest = json.loads(gzip.decompress((golden_subset_dir / MANIFESTS[name]).read_bytes()))
    with torch.device("meta"):
        model = SurfSplat.from_preset(name, adapter="official")
    assert sum(p.numel() for p in model.parameters()) == manifest["total_parameters"]
    release = export_release_state_dict(model)
    assert sorted(release) == sorted(manifest["keys"])
    for key, entry in manifest["keys"].items():
        assert list(release[key].shape) == entry["shape"], key


def test_small_preset_parameter_count_is_the_release_count():
    with torch.device("meta"):
        model = SurfSplat.from_preset("small")
    assert sum(p.numel() for p in model.parameters()) == 38_337_361


def test_unknown_preset_is_a_clear_error():
    with pytest.raises(SurfSplatInputError, match="preset: expected one of"):
        SurfSplat.from_preset("huge")


# ----------------------------------------------------------------------------- transformer pieces
def test_sine_position_code_matches_its_formula():
    h, w, c = 4, 6, 8
    code = sine_position_code(h, w, c, "cpu", torch.float32)
    npf = c // 2
    for i in range(h):
        for j in range(w):
            y = (i + 1) / (h + 1e-6) * 2 * math.pi
            x = (j + 1) / (w + 1e-6) * 2 * math.pi
            for k in range(npf):
                freq = 10000 ** (2 * (k // 2) / npf)
                fn = math.sin if k % 2 == 0 else math.cos
                assert code[k, i, j].item() == pytest.approx(fn(y / freq), abs=1e-6)
                assert code[npf + k, i, j].item() == pytest.approx(fn(x / freq), abs=1e-6)


@pytest.mark.parametrize("shift", [False, True])
def test_window_order_is_roll_then_partition(shift):
    h, w, s = 8, 12, 2
    tokens = torch.arange(h * w)
    grid = tokens.view(h, w)
    if shift:
        grid = torch.roll(grid, shifts=(-(h // s // 2), -(w // s // 2)), dims=(0, 1))
    windows = grid.view(s, h // s, s, w // s).permute(0, 2, 1, 3).reshape(-1)
    assert torch.equal(window_order(h, w, s, shift, "cpu"), windows)


def test_shifted_window_mask_separates_regions():
    h = w = 8
    mask = shifted_window_mask(h, w, 2, "cpu")  # windows 4x4, shift 2
    assert mask.shape == (4, 16, 16)
    assert torch.all(mask[0] == 0)  # the top-left window never wraps around
    # bottom-right window: four 2x2 regions, so each token sees exactly 4 tokens
    assert torch.equal((mask[3] == 0).sum(-1), torch.full((16,), 4))
    assert set(mask.unique().tolist()) == {-100.0, 0.0}


def _release_window_attention(layer: AttentionLayer, source, target, h, w, splits, shift, mask):
    """Slow twin of the release's attention: roll, split, matmul, -100 mask tiled over the
    (pixel, view)-interleaved keys, softmax, merge, roll back. source [B, L, C]; target [B, M, L, C]."""
    b, _, c = source.shape
    m = target.shape[1]
    q = layer.q_proj(source).view(b, h, w, c)
    k = layer.k_proj(target).view(b, m, h, w, c)
    v = layer.v_proj(target).view(b, m, h, w, c)
    wh, ww = h // splits, w // splits
    if shift:
        q = torch.roll(q, (-(wh // 2), -(ww // 2)), (1, 2))
        k = torch.roll(k, (-(wh // 2), -(ww // 2)), (2, 3))
        v = torch.roll(v, (-(wh // 2), -(ww // 2)), (2, 3))
    out = torch.zeros(b, h, w, c)
    for bi in range(b):
        for ki in range(splits):
            for kj in range(splits):
                rows, cols = slice(ki * wh, (ki + 1) * wh), slice(kj * ww, (kj + 1) * ww)
                qw = q[bi, rows, cols].reshape(-1, c)
                kw = k[bi, :, rows, cols].permute(1, 2, 0, 3).reshape(-1, c)  # key index = pixel * m + view
                vw = v[bi, :, rows, cols].permute(1, 2, 0, 3).reshape(-1, c)
                scores = qw @ kw.T / c**0.5
                if shift:
                    scores = scores + mask[ki * splits + kj].repeat(1, m)
                out[bi, rows, cols] = (scores.softmax(-1) @ vw).view(wh, ww, c)
    if shift:
        out = torch.roll(out, (wh // 2, ww // 2), (1, 2))
    message = layer.norm1(layer.merge(out.view(b, h * w, c)))
    if layer.mlp is not None:
        message = layer.norm2(layer.mlp(torch.cat((source, message), dim=-1)))
    return source + message


@pytest.mark.parametrize("num_neighbours", [1, 2])
@pytest.mark.parametrize("shift", [False, True])
def test_window_attention_matches_the_release_loop(num_neighbours, shift):
    """Fast path (window-order gather + SDPA) == the release's roll/split/matmul attention,
    including its misaligned mask for several neighbours."""
    torch.manual_seed(0)
    h, w, c, s = 8, 8, 16, 2
    layer = AttentionLayer(c, ffn=True).eval()
    source = torch.randn(2, h * w, c)
    target = torch.randn(2, num_neighbours, h * w, c)
    mask = shifted_window_mask(h, w, s, "cpu")
    order = window_order(h, w, s, shift, "cpu")
    windows = s * s
    src_w = source[:, order].reshape(2, windows, -1, c)
    tgt_w = target[:, :, order].reshape(2, num_neighbours, windows, -1, c).transpose(1, 2).flatten(2, 3)
    fast_mask = release_cross_view_mask(mask, num_neighbours)[None] if shift else None
    fast = layer(src_w, layer.k_proj(tgt_w), layer.v_proj(tgt_w), fast_mask)
    fast = fast.reshape(2, h * w, c)[:, torch.argsort(order)]
    slow = _release_window_attention(layer, source, target, h, w, s, shift, mask)
    torch.testing.assert_close(fast, slow, rtol=1e-5, atol=1e-5)


def test_window_attention_gradients_float64():
    torch.manual_seed(0)
    layer = AttentionLayer(4, ffn=True).double()
    mask = release_cross_view_mask(shifted_window_mask(4, 4, 2, "cpu"), 2)[None].double()
    source = torch.randn(1, 4, 4, 4, dtype=torch.float64, requires_grad=True)
    keys = torch.randn(1, 4, 8, 4, dtype=torch.float64, requires_grad=True)
    values = torch.randn(1, 4, 8, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda s, k, v: layer(s, k, v, mask), (source, keys, values), fast_mode=True)


def test_release_cross_view_mask_is_misaligned_for_several_neighbours():
    mask = shifted_window_mask(8, 8, 2, "cpu")
    assert torch.equal(release_cross_view_mask(mask, 1), mask)
    two = release_cross_view_mask(mask, 2)
    # key (pixel p, neighbour j) in neighbour-major layout gets the interleaved column (2p + j) mod L
    length = mask.shape[-1]
    for p in range(length):
        for j in range(2):
            assert torch.equal(two[:, :, j * length + p], mask[:, :, (2 * p + j) % length])


def test_transformer_swapping_two_views_swaps_the_outputs():
    torch.manual_seed(0)
    tr = MultiViewTransformer(dim=16, num_layers=2, splits=2).eval()
    x = torch.randn(1, 2, 16, 8, 8)
    nb = select_neighbours(torch.randn(1, 2, 3), 2)
    with torch.no_grad():
        out = tr(x, nb)
        swapped = tr(x.flip(1), nb)
    torch.testing.assert_close(swapped, out.flip(1), rtol=1e-5, atol=1e-5)
    assert not torch.allclose(out[:, 0], out[:, 1])


def test_transformer_attends_only_to_the_selected_neighbours():
    """With four views each view sees its two nearest cameras; a one-layer transformer's output for
    view 0 must ignore the far view 3 and react to its neighbour view 1."""
    torch.manual_seed(0)
    tr = MultiViewTransformer(dim=16, num_layers=1, splits=2).eval()
    centers = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [10, 0, 0]]])
    nb = select_neighbours(centers, 2)
    assert nb[0, 0].tolist() == [1, 2]
    x = torch.randn(1, 4, 16, 8, 8)
    with torch.no_grad():
        base = tr(x, nb)
        far = x.clone()
        far[:, 3] = torch.randn(16, 8, 8)
        near = x.clone()
        near[:, 1] = torch.randn(16, 8, 8)
        torch.testing.assert_close(tr(far, nb)[:, 0], base[:, 0], rtol=0, atol=0)
        assert not torch.allclose(tr(near, nb)[:, 0], base[:, 0], atol=1e-3)


def test_neighbours_are_the_others_up_to_three_views_then_the_nearest_cameras():
    centers = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [5, 0, 0]]])
    assert select_neighbours(centers, 2).tolist() == [[[1, 2], [0, 2], [0, 1]]]
    centers = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [3, 0, 0], [10, 0, 0]]])
    assert select_neighbours(centers, 2).tolist() == [[[1, 2], [0, 2], [1, 0], [2, 1]]]


# ----------------------------------------------------------------------------- cost volume
def test_cost_volume_peaks_at_the_true_depth_plane():
    """Partner = reference shifted by the disparity of depth z: at candidate z the warped features
    equal the reference, so the cost there is |f|^2 / sqrt(C) (closed form) and the largest."""
    torch.manual_seed(0)
    n, c, h, w = 1, 8, 16, 24
    f, baseline, shift_px = 10.0, 0.5, 2
    z = f * baseline / shift_px  # 2.5: disparity of exactly shift_px pixels
    ref = F.normalize(torch.randn(n, c, h, w), dim=1)  # unit features: the dot product peaks at 1
    src = torch.zeros_like(ref)
    src[..., : w - shift_px] = ref[..., shift_px:]  # the partner sees reference pixel x at x - shift_px
    K = torch.tensor([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])[None]
    ref_c2w = torch.eye(4)[None]
    src_c2w = torch.eye(4)[None, None].clone()
    src_c2w[..., 0, 3] = baseline
    inv = torch.tensor([[1 / 5.0, 1 / z, 1 / 1.0]])
    cost = cv.plane_sweep_cost_volume(ref, src[:, None], K, ref_c2w, src_c2w, inv)[..., shift_px:]
    torch.testing.assert_close(cost[:, 1], torch.full_like(cost[:, 1], 1 / c**0.5), rtol=1e-5, atol=1e-6)
    assert bool((cost[:, 1] > cost[:, 0]).all()) and bool((cost[:, 1] > cost[:, 2]).all())


def test_cost_volume_chunking_does_not_change_the_result(monkeypatch):
    torch.manual_seed(1)
    ref, src = torch.randn(2, 8, 8, 8), torch.randn(2, 2, 8, 8, 8)
    K = torch.tensor([[8.0, 0, 4], [0, 8.0, 4], [0, 0, 1]]).expand(2, 3, 3)
    ref_c2w = torch.eye(4).expand(2, 4, 4)
    src_c2w = torch.eye(4).repeat(2, 2, 1, 1)
    src_c2w[..., 0, 3] = torch.tensor([[0.1, -0.2], [0.3, 0.05]])
    inv = cv.linear_inverse_depth_candidates(torch.full((2,), 0.01), torch.full((2,), 2.0), 12)
    whole = cv.plane_sweep_cost_volume(ref, src, K, ref_c2w, src_c2w, inv)
    monkeypatch.setattr(cv, "WARP_CHUNK_BYTES", 1)  # one depth candidate at a time
    chunked = cv.plane_sweep_cost_volume(ref, src, K, ref_c2w, src_c2w, inv)
    torch.testing.assert_close(chunked, whole, rtol=0, atol=1e-6)


def test_cost_volume_gradients_float64():
    torch.manual_seed(2)
    ref = torch.randn(1, 3, 4, 5, dtype=torch.float64, requires_grad=True)
    src = torch.randn(1, 2, 3, 4, 5, dtype=torch.float64, requires_grad=True)
    K = torch.tensor([[4.0, 0, 2.5], [0, 4.0, 2], [0, 0, 1]], dtype=torch.float64)[None]
    ref_c2w = torch.eye(4, dtype=torch.float64)[None]
    src_c2w = torch.eye(4, dtype=torch.float64).repeat(1, 2, 1, 1)
    src_c2w[..., 0, 3] = torch.tensor([0.3, -0.2], dtype=torch.float64)
    inv = torch.tensor([[0.2, 0.45, 0.9]], dtype=torch.float64)
    assert torch.autograd.gradcheck(
        lambda r, s: cv.plane_sweep_cost_volume(r, s, K, ref_c2w, src_c2w, inv), (ref, src), fast_mode=True
    )


def test_depth_candidates_are_linear_in_inverse_depth():
    cand = cv.linear_inverse_depth_candidates(torch.tensor([1 / 100.0]), torch.tensor([1 / 0.5]), 128)
    assert cand[0, 0].item() == pytest.approx(0.01)
    assert cand[0, -1].item() == pytest.approx(2.0)
    torch.testing.assert_close(cand.diff(dim=1), torch.full((1, 127), (2.0 - 0.01) / 127))
    local = cv.local_inverse_depth_candidates(
        torch.full((1, 1, 2, 2), 1.0), torch.tensor([0.01]), torch.tensor([2.0]), 32, torch.tensor([0.001])
    )
    # 16 intervals below, 15 above the coarse value, resampled linearly
    torch.testing.assert_close(local[0, :, 0, 0], torch.linspace(1.0 - 0.016, 1.0 + 0.015, 32))


# ----------------------------------------------------------------------------- U-Net attention
def test_unet_attention_of_identical_views_equals_single_view_attention():
    """Softmax over V duplicated key sets = softmax over one set: cross-view attention of identical
    views reduces to per-view attention."""
    torch.manual_seed(0)
    block = CrossViewAttentionBlock(16, head_channels=8)
    torch.nn.init.normal_(block.proj_out.weight)  # zero-initialised in the release
    x = torch.randn(1, 16, 4, 4)
    single = block(x, num_views=1)
    both = block(x.repeat(2, 1, 1, 1), num_views=2)
    torch.testing.assert_close(both[0], single[0], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(both[1], single[0], rtol=1e-5, atol=1e-5)
    other = block(torch.cat((x, torch.randn_like(x))), num_views=2)
    assert not torch.allclose(other[0], single[0], atol=1e-3)


# ----------------------------------------------------------------------------- the whole model
def _randomise_zero_inits(model: torch.nn.Module) -> None:
    """The release zero-initialises residual branches; give them weights so every path is live."""
    with torch.no_grad():
        for p in model.parameters():
            if p.dim() > 1 and torch.count_nonzero(p) == 0:
                p.normal_(0, 0.05)


def test_tiny_forward_backward_reaches_every_parameter():
    model = _tiny(adapter="paper")
    model.train()
    _randomise_zero_inits(model)
    torch.manual_seed(1)
    images = torch.rand(1, 2, 3, 64, 64)
    pred = model(images, _cameras(2, 64), 0.5, 100.0)
    g = pred.gaussians
    assert g.means.shape == (1, 2 * 64 * 64, 3) and pred.depths.shape == (1, 2, 64, 64)
    loss = g.means.square().mean() + g.sh.square().mean() + g.opacities.mean() + g.scales.mean()
    loss.backward()
    dead = [n for n, p in model.named_parameters() if p.grad is None or not bool(p.grad.abs().sum() > 0)]
    assert dead == []
    assert all(bool(torch.isfinite(p.grad).all()) for p in model.parameters())


def test_depths_lie_between_near_and_far_and_means_on_the_rays():
    model = _tiny()
    torch.manual_seed(2)
    images = torch.rand(1, 2, 3, 64, 64)
    cams = _cameras(2, 64)
    near, far = 0.8, 20.0
    with torch.no_grad():
        pred = model(images, cams, near, far)
    assert float(pred.depths.min()) >= near * (1 - 1e-6) and float(pred.depths.max()) <= far * (1 + 1e-6)
    # paper adapter: a mean's camera z equals the predicted depth of its pixel
    means = pred.gaussians.means.view(1, 2, 64, 64, 3)
    cam_z = means[..., 2]  # cameras look down +z with identity rotation
    torch.testing.assert_close(cam_z, pred.depths, rtol=1e-5, atol=1e-5)


def test_batch_of_scenes_equals_scenes_one_by_one():
    model = _tiny()
    torch.manual_seed(3)
    images = torch.rand(2, 2, 3, 64, 64)
    cams = _cameras(2, 64)
    both = Cameras(cams.c2w.repeat(2, 1, 1), cams.K.repeat(2, 1, 1))
    near = torch.tensor([[0.5, 0.5], [1.0, 1.0]])
    far = torch.tensor([[50.0, 50.0], [10.0, 10.0]])
    with torch.no_grad():
        batched = model(images, both, near, far)
        for i in range(2):
            one = model(images[i : i + 1], cams, near[i : i + 1], far[i : i + 1])
            torch.testing.assert_close(batched.depths[i], one.depths[0], rtol=1e-4, atol=1e-5)
            torch.testing.assert_close(batched.gaussians.means[i], one.gaussians.means[0], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("num_views", [3, 4])
def test_three_and_four_view_forward(num_views):
    model = _tiny()
    torch.manual_seed(4)
    images = torch.rand(1, num_views, 3, 64, 96)
    cams = _cameras(num_views, 64)
    cams = Cameras(cams.c2w, cams.K.clone())
    cams.K[:, 0, 2] = 48.0
    with torch.no_grad():
        pred = model(images, cams, 0.5, 50.0, return_intermediates=True)
    assert pred.gaussians.means.shape == (1, num_views * 64 * 96, 3)
    assert bool(torch.isfinite(pred.gaussians.means).all())
    assert pred.intermediates["cost_volume"].shape == (num_views, 32, 16, 24)
    # views see different content, so their depth maps differ
    assert not torch.allclose(pred.depths[0, 0], pred.depths[0, 1])


def test_intermediates_are_only_collected_on_request():
    model = _tiny()
    images = torch.rand(1, 2, 3, 64, 64)
    with torch.no_grad():
        plain = model(images, _cameras(2, 64), 0.5, 100.0)
        full = model(images, _cameras(2, 64), 0.5, 100.0, return_intermediates=True)
    assert plain.intermediates is None
    torch.testing.assert_close(full.depths, plain.depths)
    expected = {
        "dinov2_input_resized_normalized",
        "features_cnn_all_scales.0",
        "features_mv.0",
        "cost_volume",
        "depth_head_logits",
        "mv_upsampler_coarse_invdepth",
        "mv_upsampler_residual_invdepth",
        "gaussian_head_out",
    } | {f"dinov2_intermediate_tokens.{i}" for i in range(4)}
    assert set(full.intermediates) == expected
    # the coarse depth is a softmax average of candidates, so it lies inside the candidate range
    coarse = full.intermediates["mv_upsampler_coarse_invdepth"]
    assert float(coarse.min()) >= 1 / 100.0 - 1e-6 and float(coarse.max()) <= 1 / 0.5 + 1e-6
    # ViT input: 64 px resized down to the nearest multiple of 14
    assert full.intermediates["dinov2_input_resized_normalized"].shape[-2:] == (56, 56)


def test_two_scale_cascade_runs():
    """A base/large-style cascade (second cost volume at 1/2 around the first depth) on tiny widths."""
    from dataclasses import replace

    from surfsplat.model.surfsplat import SurfSplatConfig

    torch.manual_seed(5)
    # a CNN stage width different from the matching width checks every concatenation's bookkeeping
    cfg = SurfSplatConfig(encoder=replace(PRESETS["tiny"], num_scales=2, cnn_dims=(16, 24, 40)))
    model = SurfSplat(cfg).eval()
    images = torch.rand(1, 2, 3, 64, 64)
    with torch.no_grad():
        pred = model(images, _cameras(2, 64), 0.5, 100.0, return_intermediates=True)
    assert pred.intermediates["cost_volume.1"].shape == (2, 32 // 4, 32, 32)
    assert bool(torch.isfinite(pred.depths).all())


# ----------------------------------------------------------------------------- input validation
@pytest.mark.parametrize(
    "images, match",
    [
        (torch.rand(1, 2, 3, 60, 64), "multiples of 16"),
        (torch.rand(1, 1, 3, 64, 64), "at least 2 views"),
        (torch.rand(1, 2, 4, 64, 64), "images: expected shape"),
        (torch.rand(1, 2, 3, 64, 64) * 255, r"values in \[0, 1\]"),
    ],
)
def test_bad_images_are_named_in_the_error(images, match):
    model = _tiny()
    cams = _cameras(images.shape[0] * images.shape[1], 64)
    with pytest.raises(SurfSplatInputError, match=match):
        model(images, cams, 0.5, 100.0)


def test_bad_cameras_and_planes_are_named_in_the_error():
    model = _tiny()
    images = torch.rand(1, 2, 3, 64, 64)
    with pytest.raises(SurfSplatInputError, match="cameras: expected 2 cameras"):
        model(images, _cameras(3, 64), 0.5, 100.0)
    with pytest.raises(SurfSplatInputError, match="near < far"):
        model(images, _cameras(2, 64), 10.0, 1.0)
    with pytest.raises(SurfSplatInputError, match="near: expected finite positive"):
        model(images, _cameras(2, 64), 0.0, 1.0)
    with pytest.raises(SurfSplatInputError, match=r"far: expected a float or a \[1, 2\] tensor"):
        model(images, _cameras(2, 64), 0.5, torch.ones(2))


def test_cpu_blocks_bound_the_largest_tensor():
    from surfsplat.model.encoder.chunking import CPU_BLOCK_BYTES, items_per_block

    cpu = torch.device("cpu")
    assert items_per_block(2, 132 * 256 * 256 * 4, cpu) == 1  # one 256x256 head input is 34.6 MB
    assert items_per_block(8, 4 * 2**20, cpu) == 7  # 7 * 4 MiB < 32 MiB <= 8 * 4 MiB
    assert items_per_block(3, CPU_BLOCK_BYTES * 4, cpu) == 1
    assert items_per_block(32, 1024, cpu) == 32
    assert items_per_block(16, 2**30, torch.device("meta")) == 16  # other devices: whole batches


def test_blockwise_cpu_evaluation_does_not_change_the_outputs(monkeypatch):
    """Image-by-image (forced) and whole-batch evaluation of the tail and the MLP agree."""
    import surfsplat.model.encoder.chunking as chunking

    model = _tiny()
    torch.manual_seed(6)
    images = torch.rand(2, 2, 3, 64, 64)
    cams = _cameras(2, 64)
    both = Cameras(cams.c2w.repeat(2, 1, 1), cams.K.repeat(2, 1, 1))
    with torch.no_grad():
        whole = model(images, both, 0.5, 100.0)
        monkeypatch.setattr(chunking, "CPU_BLOCK_BYTES", 1)
        blocks = model(images, both, 0.5, 100.0)
    torch.testing.assert_close(blocks.depths, whole.depths, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(blocks.gaussians.sh, whole.gaussians.sh, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(blocks.gaussians.means, whole.gaussians.means, rtol=1e-5, atol=1e-6)


def test_vit_position_grid_is_used_unchanged_at_its_native_size():
    model = _tiny()
    vit = model.encoder.vit
    m = vit.cfg.pos_grid
    assert vit._position_embedding(m, m) is vit.pos_embed
    resized = vit._position_embedding(4, 6)
    assert resized.shape == (1, 1 + 24, vit.cfg.embed_dim)
    torch.testing.assert_close(resized[:, 0], vit.pos_embed[:, 0])  # class token untouched
    # bicubic resize keeps a constant grid constant
    with torch.no_grad():
        vit.pos_embed[:, 1:] = 0.25
    torch.testing.assert_close(vit._position_embedding(4, 6)[:, 1:], torch.full((1, 24, vit.cfg.embed_dim), 0.25))


def test_gaussian_head_starts_from_image_colours():
    """At initialisation the head's SH and scale rows are zero, so colour comes from the image."""
    model = _tiny()
    head = model.encoder.gaussian_head.head[-1]
    assert torch.count_nonzero(head.weight[3:]) == 0 and torch.count_nonzero(head.bias[3:]) == 0
    assert torch.count_nonzero(head.weight[:3]) > 0
