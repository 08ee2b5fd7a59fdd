"""PSNR and SSIM: closed forms, scikit-image's published call, and the LPIPS fixture's values."""

from __future__ import annotations

import math

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from safetensors.torch import load_file
from skimage.metrics import structural_similarity

from surfsplat.metrics import psnr, ssim
from surfsplat.metrics.image import gaussian_taps
from surfsplat.utils.checks import SurfSplatInputError


def skimage_ssim(target: torch.Tensor, prediction: torch.Tensor) -> list[float]:
    """The call every published table of this family used, image by image ([B, C, H, W])."""
    return [
        float(
            structural_similarity(
                gt.numpy(), pred.numpy(), win_size=11, gaussian_weights=True, channel_axis=0, data_range=1.0
            )
        )
        for gt, pred in zip(target, prediction)
    ]


def degrade(images: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """A plausible render error: blur, shift, noise; kept in [0, 1]."""
    blurred = torch.nn.functional.avg_pool2d(images, 3, stride=1, padding=1, count_include_pad=False)
    noisy = blurred.roll(1, dims=-1) + 0.05 * torch.randn(images.shape, generator=generator, dtype=images.dtype)
    return noisy.clamp(0, 1)


# ------------------------------------------------------------------------------------ PSNR
def test_psnr_closed_form_constant_error():
    target = torch.full((2, 3, 8, 8), 0.5)
    prediction = target + torch.tensor([0.1, 0.01]).view(2, 1, 1, 1)
    # mse = e^2 -> PSNR = -20 log10(e): 20 dB and 40 dB.
    torch.testing.assert_close(psnr(prediction, target), torch.tensor([20.0, 40.0]), rtol=0, atol=1e-4)


def test_psnr_clips_both_images_to_unit_range():
    target = torch.zeros(1, 3, 4, 4)
    prediction = torch.full((1, 3, 4, 4), 2.0)  # clipped to 1: mse 1, PSNR 0 dB (not -6 dB)
    assert psnr(prediction, target).item() == pytest.approx(0.0, abs=1e-6)
    prediction = torch.full((1, 3, 4, 4), -3.0)  # clipped to 0: identical to the target
    assert math.isinf(psnr(prediction, target).item())


def test_psnr_is_per_image_mean_over_channels_and_pixels():
    torch.manual_seed(0)
    a, b = torch.rand(3, 3, 10, 12), torch.rand(3, 3, 10, 12)
    expected = [-10 * math.log10(float(((x - y) ** 2).double().mean())) for x, y in zip(a, b)]
    torch.testing.assert_close(psnr(a, b).double(), torch.tensor(expected, dtype=torch.float64), rtol=0, atol=1e-4)


def test_psnr_and_ssim_reject_mismatched_shapes():
    with pytest.raises(SurfSplatInputError, match="target"):
        psnr(torch.rand(1, 3, 16, 16), torch.rand(1, 3, 16, 15))
    with pytest.raises(SurfSplatInputError, match="prediction"):
        ssim(torch.rand(3, 16, 16), torch.rand(3, 16, 16))
    with pytest.raises(SurfSplatInputError, match="at least 11x11"):
        ssim(torch.rand(1, 3, 10, 40), torch.rand(1, 3, 10, 40))
    with pytest.raises(SurfSplatInputError, match="NaN"):
        ssim(torch.full((1, 3, 16, 16), math.nan), torch.rand(1, 3, 16, 16))


# ------------------------------------------------------------------------------------ SSIM
def test_ssim_gaussian_window_is_scipys():
    taps = gaussian_taps()
    assert taps.numel() == 11  # radius int(3.5 * 1.5 + 0.5) = 5
    x = torch.arange(-5, 6, dtype=torch.float64)
    expected = torch.exp(-(x**2) / (2 * 1.5**2))
    torch.testing.assert_close(taps, expected / expected.sum(), rtol=0, atol=1e-15)


def test_ssim_matches_skimage_on_random_images_float64():
    g = torch.Generator().manual_seed(1)
    target = torch.rand(3, 3, 40, 57, generator=g, dtype=torch.float64)
    prediction = degrade(target, g)
    ours = ssim(prediction, target)
    torch.testing.assert_close(
        ours, torch.tensor(skimage_ssim(target, prediction), dtype=torch.float64), rtol=0, atol=1e-12
    )


def test_ssim_matches_skimage_on_a_long_side_float64():
    # a side beyond the banded-matrix limit takes the shifted-sum filter
    g = torch.Generator().manual_seed(4)
    target = torch.rand(1, 3, 13, 700, generator=g, dtype=torch.float64)
    prediction = degrade(target, g)
    ours = ssim(prediction, target)
    torch.testing.assert_close(
        ours, torch.tensor(skimage_ssim(target, prediction), dtype=torch.float64), rtol=0, atol=1e-12
    )


def test_ssim_float32_matches_skimage_within_1e5():
    g = torch.Generator().manual_seed(2)
    target = torch.rand(2, 3, 64, 48, generator=g)
    prediction = degrade(target, g)
    ours = ssim(prediction, target)
    assert ours.dtype == torch.float32
    reference = torch.tensor(skimage_ssim(target.double(), prediction.double()))
    assert (ours.double() - reference).abs().max().item() <= 1e-5


def test_ssim_identity_is_one_and_constant_shift_is_closed_form():
    g = torch.Generator().manual_seed(3)
    image = torch.rand(1, 3, 32, 32, generator=g, dtype=torch.float64)
    assert ssim(image, image).item() == pytest.approx(1.0, abs=1e-12)
    # Two constant images a, b: variances vanish and SSIM = (2ab + C1) / (a^2 + b^2 + C1).
    a, b, c1 = 0.3, 0.7, 0.01**2
    flat_a = torch.full((1, 1, 20, 20), a, dtype=torch.float64)
    flat_b = torch.full((1, 1, 20, 20), b, dtype=torch.float64)
    assert ssim(flat_a, flat_b).item() == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), abs=1e-12)


def test_ssim_of_one_window_is_the_weighted_formula():
    # An 11x11 image holds exactly one full window: SSIM is the Gaussian-weighted statistic of
    # that window, with sample-covariance factor 121/120, written out independently here.
    g = torch.Generator().manual_seed(5)
    x = torch.rand(1, 1, 11, 11, generator=g, dtype=torch.float64)
    y = (0.6 * x + 0.3 * torch.rand(1, 1, 11, 11, generator=g, dtype=torch.float64)).clamp(0, 1)
    t = np.exp(-(np.arange(-5, 6) ** 2) / (2 * 1.5**2))
    w = np.outer(t, t) / np.outer(t, t).sum()
    a, b = x[0, 0].numpy(), y[0, 0].numpy()
    mu_a, mu_b = (w * a).sum(), (w * b).sum()
    k = 121 / 120
    var_a = k * ((w * a * a).sum() - mu_a**2)
    var_b = k * ((w * b * b).sum() - mu_b**2)
    cov = k * ((w * a * b).sum() - mu_a * mu_b)
    c1, c2 = 0.01**2, 0.03**2
    expected = (2 * mu_a * mu_b + c1) * (2 * cov + c2) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    assert ssim(y, x).item() == pytest.approx(expected, abs=1e-12)
    assert ssim(y, x).item() == pytest.approx(skimage_ssim(x, y)[0], abs=1e-12)


def test_ssim_is_differentiable_gradcheck():
    g = torch.Generator().manual_seed(4)
    target = torch.rand(1, 1, 12, 13, generator=g, dtype=torch.float64)
    prediction = degrade(target, g).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: ssim(p, target), (prediction,), fast_mode=True)


def test_ssim_matches_skimage_on_real_captures(samples):
    fern = sorted((samples.root / "llff_fern" / samples.fern_images).glob("*.png"))[:2]
    dtu = sorted((samples.root / "dtu_scan24" / samples.dtu_images).glob("*.png"))[:2]
    assert len(fern) == 2 and len(dtu) == 2, "sample captures are incomplete"

    def load(path):
        return torch.from_numpy(iio.imread(path)[..., :3].astype(np.float32) / 255.0).permute(2, 0, 1)

    # Neighbouring views of the same scene: a realistic, imperfect "prediction".
    for paths in (fern, dtu):
        images = torch.stack([load(p) for p in paths])
        target, prediction = images[:-1], images[1:]
        reference = torch.tensor(skimage_ssim(target, prediction), dtype=torch.float64)
        assert (ssim(prediction, target).double() - reference).abs().max().item() <= 1e-5
        assert (ssim(prediction.double(), target.double()) - reference).abs().max().item() <= 1e-5


def test_ssim_and_psnr_match_the_lpips_fixture(golden_subset_dir):
    # The 64x64 cases of the LPIPS golden fixture, copied unchanged (see tests/data/README.md).
    cases = load_file(str(golden_subset_dir / "lpips" / "cases64.safetensors"))
    # The fixture computed structural_similarity(gt=a64, pred=b64); SSIM is symmetric anyway.
    ours_ssim = ssim(cases["b64"], cases["a64"])
    assert (ours_ssim - cases["ssim64"]).abs().max().item() <= 1e-5
    assert (psnr(cases["b64"], cases["a64"]) - cases["psnr64"]).abs().max().item() <= 1e-4


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_ssim_compiled_filter_matches_the_banded_products_with_gradients(dtype):
    pytest.importorskip("numba")
    from surfsplat.metrics import image

    g = torch.Generator().manual_seed(6)
    maps = torch.rand(4, 1, 23, 31, generator=g, dtype=dtype, requires_grad=True)
    weights = torch.rand(4, 1, 13, 21, generator=g, dtype=dtype)
    taps = gaussian_taps(dtype=dtype)
    compiled = image._compiled_filter().apply(maps, taps)
    (g_compiled,) = torch.autograd.grad((compiled * weights).sum(), maps)
    banded = image._filter_axis(image._filter_axis(maps, taps, -2), taps, -1)
    (g_banded,) = torch.autograd.grad((banded * weights).sum(), maps)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(compiled, banded, rtol=0, atol=tol)
    torch.testing.assert_close(g_compiled, g_banded, rtol=0, atol=tol)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("target_grad", [False, True])
def test_ssim_fused_cpu_kernels_match_the_tensor_ops_with_gradients(dtype, target_grad):
    pytest.importorskip("numba")
    from surfsplat.metrics import image

    g = torch.Generator().manual_seed(7)
    target = torch.rand(2, 3, 19, 27, generator=g, dtype=dtype)
    prediction = degrade(target, g).to(dtype).requires_grad_(True)
    target.requires_grad_(target_grad)
    upstream = torch.tensor([0.7, -1.3], dtype=dtype)
    n = image.SSIM_WIN_SIZE**2
    constants = ((image.SSIM_K1 * 2.0) ** 2, (image.SSIM_K2 * 2.0) ** 2, n / (n - 1))  # data_range 2
    fused = image._compiled_ssim().apply(prediction, target, image.gaussian_taps(dtype=dtype), *constants)
    reference = image._ssim_tensor_ops(prediction, target, *constants)
    inputs = (prediction, target) if target_grad else (prediction,)
    g_fused = torch.autograd.grad((fused * upstream).sum(), inputs)
    g_reference = torch.autograd.grad((reference * upstream).sum(), inputs)
    tol = 1e-12 if dtype == torch.float64 else 2e-6
    torch.testing.assert_close(fused, reference, rtol=0, atol=tol)
    for a, b in zip(g_fused, g_reference, strict=True):
        assert a.abs().max() > 0
        torch.testing.assert_close(a, b, rtol=0, atol=tol * 1e-2 if dtype == torch.float64 else 1e-7)
    # what `ssim` itself runs on the CPU is the fused pass
    assert torch.equal(ssim(prediction.detach(), target.detach(), data_range=2.0), fused.detach())


def test_ssim_tensor_ops_match_skimage_float64():
    from surfsplat.metrics import image

    g = torch.Generator().manual_seed(8)
    target = torch.rand(2, 3, 24, 30, generator=g, dtype=torch.float64)
    prediction = degrade(target, g)
    n = image.SSIM_WIN_SIZE**2
    constants = (image.SSIM_K1**2, image.SSIM_K2**2, n / (n - 1))
    ours = image._ssim_tensor_ops(prediction, target, *constants)
    assert ours.tolist() == pytest.approx(skimage_ssim(target, prediction), abs=1e-12)


def test_ssim_checks_finite_values_unless_told_not_to():
    target = torch.rand(1, 3, 16, 16, dtype=torch.float64)
    prediction = target.clone()
    prediction[0, 1, 3, 4] = float("nan")
    with pytest.raises(SurfSplatInputError, match="NaN or inf"):
        ssim(prediction, target)
    assert torch.isnan(ssim(prediction, target, check_finite=False)).all()  # a NaN render still shows in a loss
