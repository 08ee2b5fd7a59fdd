"""Training options that keep surfaces closed: footprint-relative tangent clamp, the multipliers'
inward gradient, native high-resolution truth windows, the close-up loss terms, and validation's
closure figures."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from surfsplat import Cameras
from surfsplat.data.synthetic import SyntheticDataset, SyntheticDatasetConfig, render_synthetic
from surfsplat.model.adapter import (
    AdapterConfig,
    GaussianAdapter,
    clamp_multipliers,
    floor_scales,
    footprint_bounds,
    surface_frames,
    unproject_depth,
)
from surfsplat.train import fit, train_preset
from surfsplat.train.config import override
from surfsplat.train.data import TrainBatch, ViewBatch, flip_views
from surfsplat.train.losses import LossConfig, alpha_at_window, highres_loss
from surfsplat.utils.checks import SurfSplatInputError


def _K(f: float = 20.0, c: float = 8.0) -> torch.Tensor:
    return torch.tensor([[f, 0, c], [0, f, c], [0, 0, 1.0]])


# ------------------------------------------------------------------------------------------ adapter
def test_footprint_clamp_leaves_planes_alone_and_bounds_edges_in_pixels():
    K = _K()
    depth = torch.full((16, 16), 6.0)
    depth[:, 8:] = 60.0  # a depth edge: tangents there span tens of pixels' worth of surface
    points = unproject_depth(depth, K)
    bounds = footprint_bounds(points, K, 4.0)
    frames = surface_frames(points, bounds)
    plain = surface_frames(points, None)
    footprint = depth / 20.0
    # Away from the edge a fronto-parallel plane keeps its exact per-pixel step z / f, unclamped.
    assert torch.allclose(frames.base_scales[:, 2:6], footprint[:, 2:6, None].expand(-1, -1, 2), rtol=1e-5)
    assert torch.allclose(frames.base_scales[:, 11:14], plain.base_scales[:, 11:14])
    # At the edge the rightward scale is bounded by sqrt(2) * 4 footprints (x and z components each
    # at most 4), whatever the scene's units: scaling the whole scene scales the bound with it.
    edge = frames.base_scales[:, 7:9, 0] / footprint[:, 7:9]
    assert bool((edge <= 4 * 2**0.5 + 1e-4).all()) and bool(
        (plain.base_scales[:, 7:9, 0] / footprint[:, 7:9] > 8).all()
    )
    scaled = surface_frames(unproject_depth(depth * 100, K), footprint_bounds(unproject_depth(depth * 100, K), K, 4.0))
    assert torch.allclose(scaled.base_scales, frames.base_scales * 100, rtol=1e-4)


def test_inward_clamp_has_the_clamps_values_and_passes_only_inward_gradients():
    x = torch.tensor([0.1, 0.1, 1.0, 5.0, 5.0], requires_grad=True)
    y = clamp_multipliers(x, 1 / 3, 3.0, "inward")
    assert torch.equal(y, x.detach().clamp(1 / 3, 3.0))
    # Gradients: descent moves x by -grad; below the range a negative gradient moves it up (passes),
    # a positive one would push it further out (blocked); mirrored above.
    y.backward(torch.tensor([-1.0, 1.0, 2.0, 1.0, -1.0]))
    assert x.grad.tolist() == [-1.0, 0.0, 2.0, 1.0, 0.0]
    z = torch.tensor([0.1, 5.0], requires_grad=True)
    clamp_multipliers(z, 1 / 3, 3.0, "clamp").backward(torch.tensor([-1.0, 1.0]))
    assert z.grad.tolist() == [0.0, 0.0]


def test_release_mode_refuses_the_new_rules():
    with pytest.raises(SurfSplatInputError, match="tangent_clamp_unit"):
        AdapterConfig(mode="official", tangent_clamp_unit="footprint")
    with pytest.raises(SurfSplatInputError, match="multiplier_gradient"):
        AdapterConfig(multiplier_gradient="straight")


def test_floor_scales_has_maximums_values_and_the_multipliers_gradient_rule():
    x = torch.tensor([0.1, 0.1, 1.0, 5.0], requires_grad=True)
    floor = torch.tensor([0.5, 0.5, 0.5, 0.5])
    y = floor_scales(x, floor, "inward")
    assert torch.equal(y, torch.maximum(x.detach(), floor))
    # Below the floor only a gradient that grows the scale passes; above it every gradient does.
    y.backward(torch.tensor([-1.0, 1.0, 2.0, -3.0]))
    assert x.grad.tolist() == [-1.0, 0.0, 2.0, -3.0]
    z = torch.tensor([0.1, 5.0], requires_grad=True)
    floor_scales(z, floor[:2], "clamp").backward(torch.tensor([-1.0, 1.0]))
    assert z.grad.tolist() == [0.0, 1.0]


def _shrunk_plane(scale_floor):
    """The adapter on a fronto-parallel plane 4 units away (f = 30, so a footprint of 4 / 30) with
    every multiplier forced to Eq. 9's lower bound 1/3; scales as [V, H, W, 3]."""
    torch.manual_seed(0)
    adapter = GaussianAdapter(AdapterConfig(scale_floor=scale_floor)).eval()
    c2w = torch.eye(4).expand(1, 2, 4, 4).clone()
    c2w[0, 1, 0, 3] = 0.3
    K = _K(30.0, 16.0).expand(1, 2, 3, 3).clone()
    raw = torch.randn(1, 2, adapter.num_raw_channels, 32, 32)
    raw[:, :, adapter.channel_slices()["scale"]] = -20.0  # softplus ~ 0: clamped to 1/3
    out = adapter(torch.full((1, 2, 32, 32), 4.0), raw, torch.rand(1, 2, 3, 32, 32), K, c2w)
    return out, out.scales.reshape(2, 32, 32, 3), 4.0 / 30.0


@pytest.mark.parametrize("floor", [0.5, 0.75])
def test_scale_floor_keeps_shrunk_surfels_at_their_footprint_fraction(floor):
    plain, plain_scales, footprint = _shrunk_plane(None)
    floored, floored_scales, _ = _shrunk_plane(floor)
    # Without the floor the plane's surfels are about a third of their footprint (Eq. 9's bound; the
    # random offsets move the points within their pixels); with it no tangent scale is under the
    # floor, the ones that were sit exactly on it, and nothing else changes.
    inner_plain, inner_floored = plain_scales[:, 2:-2, 2:-2, :2], floored_scales[:, 2:-2, 2:-2, :2]
    assert 0.15 < float(inner_plain.median()) / footprint < 0.45
    assert bool((floored_scales[..., :2] >= floor * footprint * (1 - 1e-6)).all())
    below = inner_plain < floor * footprint
    assert bool(below.all()) and torch.allclose(inner_floored, torch.tensor(floor * footprint), rtol=1e-6)
    assert torch.equal(plain.gaussians.means, floored.gaussians.means)
    assert torch.equal(plain.gaussians.opacities, floored.gaussians.opacities)
    assert torch.equal(plain.scales_mul, floored.scales_mul) and torch.equal(plain.normals, floored.normals)


def test_scale_floor_is_validated_and_refused_by_the_release_mode():
    with pytest.raises(SurfSplatInputError, match="scale_floor"):
        AdapterConfig(mode="official", scale_floor=0.5)
    for bad in (0.0, -1.0, 4.0, float("nan"), True, "0.5"):
        with pytest.raises(SurfSplatInputError, match="scale_floor"):
            AdapterConfig(scale_floor=bad)


def test_default_adapter_is_unchanged_by_the_new_fields():
    from surfsplat.model.surfsplat import SurfSplat

    torch.manual_seed(0)
    model = SurfSplat.from_preset("tiny").eval()
    images = torch.rand(1, 2, 3, 32, 32)
    c2w = torch.eye(4).expand(2, 4, 4).clone()
    c2w[1, 0, 3] = 0.3
    cams = Cameras(c2w, _K(30.0, 16.0).expand(2, 3, 3).clone())
    with torch.no_grad():
        a = model(images, cams, 0.5, 15.0).gaussians
        model.adapter.cfg = AdapterConfig(multiplier_gradient="inward")  # same values, other gradient
        b = model(images, cams, 0.5, 15.0).gaussians
    assert torch.equal(a.scales, b.scales) and torch.equal(a.means, b.means)


# ------------------------------------------------------------------------------------------ data
def test_highres_window_is_the_crop_of_the_native_render():
    config = SyntheticDatasetConfig(
        length=2, seed=5, image_shape=(16, 16), num_target_views=2, supersample=1, highres_factor=4, highres_crop=24
    )
    dataset = SyntheticDataset(config)
    sample = dataset[1]
    target = sample["target"]
    assert target["image_hr"].shape == (2, 3, 24, 24)
    x0, y0, cw, ch = dataset.highres_window(1, 2)
    _, cams = dataset.cameras(1)
    full = render_synthetic(dataset.scene(1), cams.scaled(4.0), 64, 64).image
    for v in range(2):
        crop = full[v, :, int(y0[v]) : int(y0[v]) + ch, int(x0[v]) : int(x0[v]) + cw]
        assert float((target["image_hr"][v] - crop).abs().max()) < 1e-4
        assert target["K_hr"][v, 0, 2] == pytest.approx(4 * float(cams.K[v, 0, 2]) - int(x0[v]))
    with pytest.raises(SurfSplatInputError, match="highres_factor"):
        SyntheticDataset(SyntheticDatasetConfig(highres_factor=1))


def test_flip_mirrors_the_window_with_its_camera():
    images = torch.rand(1, 1, 3, 8, 8)
    hr = torch.rand(1, 1, 3, 6, 6)
    K = _K(10.0, 4.0)[None, None]
    K_hr = K.clone() * torch.tensor([4.0, 4.0, 1.0])[:, None]
    K_hr[..., 0, 2] -= 11.0
    views = ViewBatch(images, torch.eye(4)[None, None], K, torch.ones(1, 1), torch.ones(1, 1) * 9, None, hr, K_hr)
    flipped = flip_views(views, torch.tensor([True]))
    assert torch.equal(flipped.images_hr, hr.flip(-1))
    assert flipped.K_hr[0, 0, 0, 2] == pytest.approx(6 - float(K_hr[0, 0, 0, 2]))
    # The window still sits where the mirrored x1 image's pixels map: x0' = s * cx' - cx_hr'.
    x0 = 4 * float(flipped.K[0, 0, 0, 2]) - float(flipped.K_hr[0, 0, 0, 2])
    assert x0 == pytest.approx(4 * 8 - 6 - 11)


# ------------------------------------------------------------------------------------------ losses
def test_alpha_at_window_samples_the_x1_map_at_the_window_pixels():
    h = w = 8
    K = _K(10.0, 4.0)[None, None]
    K_hr = K.clone() * torch.tensor([2.0, 2.0, 1.0])[:, None]
    K_hr[..., 0, 2] -= 3.0  # window starts 3 pixels right in the x2 image
    ramp = (torch.arange(w, dtype=torch.float32) + 0.5).expand(h, w)  # alpha = x-coordinate of the centre
    alpha = ramp[None, None, None] / 10
    sampled = alpha_at_window(alpha, K, K_hr, (4, 6))
    # Window pixel column j has centre (j + 0.5 + 3) / 2 in x1 pixels; inside the image's centres the
    # bilinear ramp returns exactly that coordinate.
    expected = ((torch.arange(6) + 0.5 + 3) / 2) / 10
    assert torch.allclose(sampled[0, 0, 0, 0], expected, atol=1e-6)


def test_highres_terms():
    config = LossConfig(highres_weight=2.0, closure_weight=0.5)
    color = torch.zeros(1, 1, 3, 4, 4)
    truth = torch.full_like(color, 0.5)
    alpha_hr = torch.full((1, 1, 1, 4, 4), 0.6)
    alpha_x1 = torch.full_like(alpha_hr, 0.9)
    terms = highres_loss(config, color, alpha_hr, truth, alpha_x1)
    assert float(terms.highres) == pytest.approx(0.25)
    assert float(terms.closure) == pytest.approx(0.3)
    assert float(terms.total) == pytest.approx(2 * 0.25 + 0.5 * 0.3)
    # Closed already (the close-up keeps more alpha than x1): no closure loss.
    assert float(highres_loss(config, color, alpha_x1, truth, alpha_hr).closure) == 0.0


# ------------------------------------------------------------------------------------------ training
# The tiny preset cut to seconds, as test_train_fit runs it (32x32 rooms, one target, two steps).
from tests.helpers.training import validated_quick_config as _quick  # noqa: E402


def test_close_up_terms_join_the_loss_and_validation_reports_closure(tmp_path: Path):
    config = _quick(
        tmp_path / "run",
        **{
            "data.highres_factor": 4,
            "data.highres_crop": 32,
            "loss.highres_weight": 1.0,
            "loss.closure_weight": 0.5,
            "model.adapter.multiplier_gradient": "inward",
            "model.adapter.tangent_clamp_unit": "footprint",
            "model.adapter.tangent_clamp": 4.0,
        },
    )
    fit(config)
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    train = [r for r in rows if "loss/total" in r]
    assert len(train) == 2
    for r in train:
        assert r["loss/highres"] > 0 and r["loss/closure"] >= 0
        assert r["loss/total"] == pytest.approx(r["loss/mse"] + r["loss/highres"] + 0.5 * r["loss/closure"], rel=1e-5)
    val = [r for r in rows if "val/closure/closure" in r]
    assert val, "validation logs closure"
    v = val[-1]
    assert v["val/closure/closure"] == pytest.approx(v["val/closure/alpha_x2"] / v["val/closure/alpha_x1"])
    assert 0 <= v["val/closure/undersized"] <= 1 and 0 <= v["val/closure/multiplier_at_low"] <= 1


def test_close_up_terms_need_the_truth():
    with pytest.raises(SurfSplatInputError, match="data.highres_factor >= 2"):
        override(train_preset("tiny"), {"loss.highres_weight": 1.0})
    assert override(train_preset("small"), {"data.highres_factor": 2}).data.highres_factor == 2  # chunks: from frames


def test_init_checkpoint_may_change_the_adapters_rules_not_its_layout(tmp_path: Path):
    from surfsplat.train import build_model
    from surfsplat.train.checkpoint import latest_checkpoint

    fit(_quick(tmp_path / "a", **{"val_every": 0}))
    ckpt = str(latest_checkpoint(tmp_path / "a"))
    model = build_model(
        override(train_preset("tiny"), {"model.init_checkpoint": ckpt, "model.adapter.multiplier_gradient": "inward"})
    )
    assert model.cfg.adapter.multiplier_gradient == "inward"
    assert any("multiplier_gradient" in line for line in model.init_report)
    with pytest.raises(SurfSplatInputError, match="sh_degree"):
        build_model(override(train_preset("tiny"), {"model.init_checkpoint": ckpt, "model.adapter.sh_degree": 1}))


def test_training_batch_without_window_is_refused():
    from surfsplat.model.decoder import decoder_mode
    from surfsplat.train import build_model, build_optimizer
    from surfsplat.train.data import build_validation_samples
    from surfsplat.train.loop import training_step
    from surfsplat.train.losses import ImageLoss

    config = _quick(Path("unused"), **{"data.highres_factor": 2, "loss.highres_weight": 1.0})
    batch: TrainBatch = build_validation_samples(config.data, 0, 1, config.seed)[0]  # validation has no window
    model = build_model(config)
    with pytest.raises(SurfSplatInputError, match="need high-resolution truth"):
        training_step(
            model,
            model,
            batch,
            ImageLoss(config.loss),
            build_optimizer(model, config),
            mode=decoder_mode(model.cfg.adapter),
        )


def test_chunk_frames_give_the_window_at_s_times_the_training_size(tmp_path: Path):
    from surfsplat.data import (
        BoundedViewSampler,
        BoundedViewSamplerConfig,
        ChunkDataset,
        ChunkDatasetConfig,
        write_chunks,
    )
    from surfsplat.data.transforms import rescale_and_crop
    from tests.helpers.data import make_example

    example = make_example("wide", 8, seed=0, size=(60, 120))
    write_chunks([example], tmp_path)
    sampler = BoundedViewSampler(
        BoundedViewSamplerConfig(
            min_distance_between_context_views=2, max_distance_between_context_views=4, warm_up_steps=0
        )
    )
    config = ChunkDatasetConfig(
        roots=[tmp_path], image_shape=(12, 12), shuffle=False, highres_factor=4, highres_crop=20
    )
    (sample,) = list(ChunkDataset(config, sampler))
    target = sample["target"]
    assert target["image_hr"].shape == (len(target["index"]), 3, 20, 20)
    # The window is a crop of the target frames rescaled to 48x48 (4 x 12), and K_hr is that image's K
    # shifted by the crop: recover the offset from the principal point and compare the pixels.
    from surfsplat.data.chunks import decode_views, example_cameras

    frames = decode_views(example, target["index"].tolist(), "test")
    K = example_cameras(example, 120, 60, "test").K[target["index"]]
    full, K_full, _ = rescale_and_crop(frames, K, (48, 48))
    for v in range(len(target["index"])):
        x0 = round(float(K_full[v, 0, 2] - target["K_hr"][v, 0, 2]))
        y0 = round(float(K_full[v, 1, 2] - target["K_hr"][v, 1, 2]))
        assert torch.equal(target["image_hr"][v], full[v, :, y0 : y0 + 20, x0 : x0 + 20])
        assert target["K_hr"][v, 0, 0] == pytest.approx(float(K_full[v, 0, 0]))
    # Frames smaller than 4 x the training size are never upsampled into "truth": the sample is skipped.
    small = ChunkDataset(
        ChunkDatasetConfig(roots=[tmp_path], image_shape=(24, 24), shuffle=False, highres_factor=4), sampler
    )
    assert list(small) == [] and "frames too small for x4 truth" in str(small.summary)
