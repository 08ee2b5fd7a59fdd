"""HRRC: ground-truth upsampling against independent references, K scaling, aggregation, table."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.ndimage as ndi
import torch
import torch.nn.functional as F

from surfsplat import Cameras
from surfsplat.metrics import (
    HrrcConfig,
    HrrcEvaluator,
    HrrcReport,
    Lpips,
    LpipsUnavailable,
    evaluate_hrrc,
    format_hrrc_table,
    psnr,
    render_at_scales,
    ssim,
    upsample_ground_truth,
)
from surfsplat.metrics.lpips import lin_shapes, vgg_shapes
from surfsplat.utils.checks import SurfSplatInputError


def keys_bicubic_1d(signal: np.ndarray, factor: int, a: float = -0.75) -> np.ndarray:
    """Cubic convolution (Keys 1981) at output centres, source x = (j + 0.5) / s - 0.5, edges clamped."""

    def kernel(d: float) -> float:
        d = abs(d)
        if d <= 1:
            return (a + 2) * d**3 - (a + 3) * d**2 + 1
        if d < 2:
            return a * d**3 - 5 * a * d**2 + 8 * a * d - 4 * a
        return 0.0

    n = signal.shape[-1]
    out = np.zeros(signal.shape[:-1] + (n * factor,))
    for j in range(n * factor):
        x = (j + 0.5) / factor - 0.5
        i = math.floor(x)
        for k in range(i - 1, i + 3):
            out[..., j] += kernel(x - k) * signal[..., min(max(k, 0), n - 1)]
    return out


def test_bilinear_upsampling_is_scipy_zoom_with_pixel_centres():
    g = torch.Generator().manual_seed(0)
    image = torch.rand(2, 3, 7, 9, generator=g, dtype=torch.float64)
    for s in (2, 4):
        ours = upsample_ground_truth(image, s, "bilinear")
        reference = np.stack(
            [[ndi.zoom(ch.numpy(), s, order=1, grid_mode=True, mode="nearest") for ch in im] for im in image]
        )
        np.testing.assert_allclose(ours.numpy(), reference, rtol=0, atol=1e-12)


def test_bilinear_reproduces_the_release_call():
    # The release: F.interpolate(gt, size=(int(h * s), int(w * s)), mode="bilinear", align_corners=False).
    g = torch.Generator().manual_seed(1)
    image = torch.rand(3, 3, 16, 12, generator=g)
    release = F.interpolate(image, size=(int(16 * 2.0), int(12 * 2.0)), mode="bilinear", align_corners=False)
    assert torch.equal(upsample_ground_truth(image, 2, "bilinear"), release)


def test_bicubic_upsampling_is_keys_cubic_convolution_then_clamped():
    g = torch.Generator().manual_seed(2)
    image = torch.rand(1, 3, 6, 8, generator=g, dtype=torch.float64)
    for s in (2, 4):
        rows = keys_bicubic_1d(image.numpy().swapaxes(-1, -2), s).swapaxes(-1, -2)  # along H
        reference = np.clip(keys_bicubic_1d(rows, s), 0.0, 1.0)  # then along W
        np.testing.assert_allclose(upsample_ground_truth(image, s).numpy(), reference, rtol=0, atol=1e-12)


def test_clamp_removes_bicubic_overshoot_at_edges():
    step = torch.zeros(1, 1, 8, 8)
    step[..., 4:] = 1.0
    raw = F.interpolate(step, scale_factor=4, mode="bicubic", align_corners=False)
    assert raw.max() > 1.05 and raw.min() < -0.05  # Keys' kernel rings at a step
    up = upsample_ground_truth(step, 4)
    assert up.min() == 0.0 and up.max() == 1.0
    torch.testing.assert_close(up, raw.clamp(0, 1))


def test_bilinear_reproduces_linear_ramps_and_bicubic_constants_away_from_the_border():
    # Bilinear is exact on linear functions: the value at output centre j is ramp((j + 0.5) / s).
    # torch's bicubic (Keys, a = -0.75) is exact on constants only (a = -0.5 would be cubic).
    w, s = 12, 4
    ramp = (torch.arange(w, dtype=torch.float64) + 0.5) / (2 * w)  # in [0, 0.5]
    expected = (torch.arange(w * s, dtype=torch.float64) + 0.5) / s / (2 * w)
    interior = slice(2 * s, (w - 2) * s)
    up = upsample_ground_truth(ramp.expand(1, 1, 5, w), s, "bilinear")[0, 0, 0]
    torch.testing.assert_close(up[interior], expected[interior], rtol=0, atol=1e-12)
    flat = torch.full((1, 3, 6, 7), 0.37, dtype=torch.float64)
    torch.testing.assert_close(upsample_ground_truth(flat, s), torch.full((1, 3, 24, 28), 0.37, dtype=torch.float64))


def test_upsampling_factor_one_and_errors():
    image = torch.rand(2, 3, 4, 4) * 1.5
    assert torch.equal(upsample_ground_truth(image, 1), image.clamp(0, 1))
    with pytest.raises(SurfSplatInputError, match="factor"):
        upsample_ground_truth(image, 0)
    with pytest.raises(SurfSplatInputError, match="factor"):
        upsample_ground_truth(image, 2.0)  # type: ignore[arg-type]
    with pytest.raises(SurfSplatInputError, match="mode"):
        upsample_ground_truth(image, 2, "nearest")  # type: ignore[arg-type]


# ------------------------------------------------------------------------ rendering with K scaled
def linear_texture_renderer(cameras: Cameras, width: int, height: int) -> torch.Tensor:
    """An analytic 'renderer': colour is linear in the ray direction K^-1 (u, v, 1) at pixel centres."""
    v, u = torch.meshgrid(
        torch.arange(height, dtype=torch.float64) + 0.5, torch.arange(width, dtype=torch.float64) + 0.5, indexing="ij"
    )
    pix = torch.stack([u, v, torch.ones_like(u)], dim=-1)  # [H, W, 3]
    rays = torch.einsum("cij,hwj->chwi", torch.linalg.inv(cameras.K.double()), pix)  # [C, H, W, 3]
    colour = torch.stack(
        [0.5 + 0.3 * rays[..., 0], 0.5 + 0.2 * rays[..., 1], 0.4 + 0.1 * (rays[..., 0] - rays[..., 1])], 1
    )
    return colour  # [C, 3, H, W]


def test_render_at_scales_scales_K_so_renders_agree_with_upsampled_ground_truth():
    K = torch.tensor([[[40.0, 0.0, 16.5], [0.0, 44.0, 11.0], [0.0, 0.0, 1.0]]])
    cameras = Cameras(torch.eye(4)[None], K)
    renders = render_at_scales(linear_texture_renderer, cameras, width=32, height=24)
    assert {s: tuple(r.shape) for s, r in renders.items()} == {1: (1, 3, 24, 32), 2: (1, 3, 48, 64), 4: (1, 3, 96, 128)}
    for s in (2, 4):
        # The s-times render is the same scene sampled at finer pixel centres: its s x s box
        # average is the standard render, and bilinear upsampling of the standard render (exact
        # on linear textures) equals it away from the clamped border.
        torch.testing.assert_close(F.avg_pool2d(renders[s], s), renders[1], rtol=0, atol=1e-12)
        up = upsample_ground_truth(renders[1], s, "bilinear")
        inner = (..., slice(s, -s), slice(s, -s))
        torch.testing.assert_close(up[inner], renders[s][inner], rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------ aggregation
@pytest.fixture(scope="module")
def random_lpips() -> Lpips:
    g = torch.Generator().manual_seed(3)  # random weights: a structural check, never reported
    vgg = {k: 0.1 * torch.randn(s, generator=g) for k, s in vgg_shapes().items()}
    lin = {k: torch.rand(s, generator=g) for k, s in lin_shapes().items()}
    return Lpips(vgg, lin)


def noisy_renders(target: torch.Tensor, offsets: dict[int, float]) -> dict[int, torch.Tensor]:
    """Renders = upsampled truth + a constant offset per factor: PSNR = -20 log10(offset)."""
    return {s: (upsample_ground_truth(target, s) + d).clamp(0, 1) for s, d in offsets.items()}


def test_evaluator_means_over_images_and_factors(random_lpips):
    g = torch.Generator().manual_seed(4)
    # Mid-grey textures keep the +offset renders inside [0, 1], so the PSNR is exact.
    scene_a = 0.3 + 0.4 * torch.rand(1, 3, 16, 16, generator=g)
    scene_b = 0.3 + 0.4 * torch.rand(2, 3, 16, 16, generator=g)
    offsets = {1: 0.01, 2: 0.02}  # two factors keep the LPIPS calls few; the table test has three
    # A pixel budget of two 32x32 images: the x2 renders of scene b are scored in one call.
    config = HrrcConfig(factors=(1, 2), upsample="bicubic", max_batch_pixels=2 * 32 * 32)
    evaluator = HrrcEvaluator(random_lpips, config)
    renders_a, renders_b = noisy_renders(scene_a, offsets), noisy_renders(scene_b, offsets)
    per_scene = evaluator.add_scene("a", scene_a, renders_a)
    evaluator.add_scene("b", scene_b, renders_b)
    report = evaluator.report()
    assert report.num_images == 3 and report.base_size == (16, 16) and report.lpips_unavailable is None
    for s, d in offsets.items():
        assert report.mean[s]["psnr"] == pytest.approx(-20 * math.log10(d), abs=1e-3)
        gt = torch.cat([upsample_ground_truth(scene_a, s), upsample_ground_truth(scene_b, s)])
        pred = torch.cat([renders_a[s], renders_b[s]])
        # The mean is over images (3), not scenes (2).
        assert report.mean[s]["ssim"] == pytest.approx(ssim(pred.double(), gt.double()).mean().item(), abs=1e-12)
        with torch.no_grad():
            expected_lpips = random_lpips(pred, gt)  # [3]: image 0 is scene a
        assert report.mean[s]["lpips"] == pytest.approx(expected_lpips.mean().item(), rel=1e-5)
        assert per_scene[s]["lpips"] == pytest.approx(expected_lpips[0].item(), rel=1e-5)
        assert report.per_scene["b"][s]["lpips"] == pytest.approx(expected_lpips[1:].mean().item(), rel=1e-5)
    average = report.average()
    for metric in ("psnr", "ssim", "lpips"):
        assert average[metric] == pytest.approx(sum(report.mean[s][metric] for s in (1, 2)) / 2)


def test_evaluator_without_lpips_reports_the_reason_and_no_number():
    g = torch.Generator().manual_seed(5)
    target = torch.rand(2, 3, 12, 12, generator=g)
    unavailable = LpipsUnavailable("VGG16 weights vgg16-397923af.pth not found")
    report = evaluate_hrrc([("only", target, noisy_renders(target, {1: 0.1, 2: 0.1, 4: 0.1}))], unavailable)
    assert report.mean[2]["lpips"] is None and report.average()["lpips"] is None
    data = report.to_json()
    assert data["lpips_unavailable"] == "LPIPS unavailable: VGG16 weights vgg16-397923af.pth not found"
    assert data["per_scene"]["only"]["x4"]["lpips"] is None
    assert data["mean"]["x1"]["psnr"] == pytest.approx(psnr(target, noisy_renders(target, {1: 0.1})[1]).mean().item())
    table = format_hrrc_table({"Ours": report})
    assert "LPIPS unavailable: VGG16 weights" in table
    row = next(line for line in table.splitlines() if line.startswith("Ours "))
    assert row.count("n/a") == 4  # three factors and the average, no LPIPS number anywhere


def test_table_reproduces_the_papers_layout_and_average():
    # Table 1's pixelSplat row: the "Average" group is the plain mean of the three resolutions.
    means = {1: (26.049, 0.862, 0.137), 2: (25.782, 0.868, 0.207), 4: (24.920, 0.877, 0.269)}
    report = HrrcReport(
        factors=(1, 2, 4),
        upsample="bicubic",
        base_size=(256, 256),
        mean={s: dict(zip(("psnr", "ssim", "lpips"), v)) for s, v in means.items()},
        per_scene={},
        num_images=3,
        lpips_unavailable=None,
    )
    table = format_hrrc_table({"pixelSplat": report})
    header = table.splitlines()[0]
    for group in ("256x256 (Standard)", "512x512 (HRRC)", "1024x1024 (HRRC)", "Average"):
        assert group in header
    row = next(line for line in table.splitlines() if line.startswith("pixelSplat"))
    numbers = row.split("|", 1)[1].replace("|", " ").split()
    assert numbers == "26.049 0.862 0.137 25.782 0.868 0.207 24.920 0.877 0.269 25.584 0.869 0.204".split()


def test_evaluator_rejects_bad_input():
    target = torch.rand(2, 3, 12, 12)
    evaluator = HrrcEvaluator(LpipsUnavailable("not needed here"))
    renders = noisy_renders(target, {1: 0.1, 2: 0.1, 4: 0.1})
    with pytest.raises(SurfSplatInputError, match=r"no render for factors \[4\]"):
        evaluator.add_scene("s", target, {1: renders[1], 2: renders[2]})
    with pytest.raises(SurfSplatInputError, match=r"renders\[2\]"):
        evaluator.add_scene("s", target, {**renders, 2: renders[4]})
    evaluator.add_scene("s", target, renders)
    with pytest.raises(SurfSplatInputError, match="already added"):
        evaluator.add_scene("s", target, renders)
    with pytest.raises(SurfSplatInputError, match="no scene"):
        HrrcEvaluator(LpipsUnavailable("x")).report()
    with pytest.raises(SurfSplatInputError, match="lpips"):
        HrrcEvaluator(None)  # type: ignore[arg-type]
