"""Training loss: MSE + lambda LPIPS, its start-up error, and the depth-cascade weights."""

from __future__ import annotations

import pytest
import torch

from surfsplat.metrics import Lpips, LpipsUnavailable, load_lpips
from surfsplat.train.losses import ImageLoss, LossConfig, cascade_loss, cascade_weights
from surfsplat.utils.checks import SurfSplatInputError


def constant_error_pair(error: float, shape=(2, 2, 3, 16, 16)) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(1)
    target = 0.2 + 0.5 * torch.rand(shape, generator=g)
    return target + error, target


def test_default_is_the_papers_lambda():
    assert LossConfig().lpips_weight == 0.05 and LossConfig().intermediate_weight == 0.9


def test_mse_only_needs_no_weights(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "empty"))
    loss = ImageLoss(LossConfig(lpips_weight=0.0))
    prediction, target = constant_error_pair(0.1)
    terms = loss(prediction, target)
    assert terms.lpips is None
    assert terms.mse.item() == pytest.approx(0.01, rel=1e-5)
    assert terms.total.item() == pytest.approx(0.01, rel=1e-5)
    assert ImageLoss(LossConfig(lpips_weight=0.0, mse_weight=2.0))(prediction, target).total.item() == pytest.approx(
        0.02, rel=1e-5
    )


def test_missing_lpips_weights_fail_at_construction_with_advice(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "empty"))
    with pytest.raises(LpipsUnavailable) as info:
        ImageLoss(LossConfig())
    message = str(info.value)
    assert message.startswith("LPIPS unavailable: VGG16 weights vgg16-397923af.pth not found")
    assert str(tmp_path / "empty" / "hub" / "checkpoints") in message  # where to put the file
    assert "lpips_vgg_path" in message and "set lpips_weight to 0" in message
    with pytest.raises(LpipsUnavailable, match="does not exist"):
        ImageLoss(LossConfig(lpips_vgg_path=str(tmp_path / "missing.pth"), lpips_lin_path=str(tmp_path / "x.pth")))


def test_loss_is_mse_plus_lambda_lpips(lpips_files):
    vgg_path, lin_path = lpips_files
    loss = ImageLoss(LossConfig(lpips_vgg_path=str(vgg_path), lpips_lin_path=str(lin_path)))
    assert isinstance(loss.lpips, Lpips)
    assert list(loss.parameters()) == [] and loss.state_dict() == {}  # nothing leaks into checkpoints
    prediction, target = constant_error_pair(0.05, shape=(1, 2, 3, 16, 16))
    prediction.requires_grad_(True)
    terms = loss(prediction, target)
    reference = load_lpips(vgg_path, lin_path)
    with torch.no_grad():
        expected_lpips = reference(prediction.reshape(2, 3, 16, 16), target.reshape(2, 3, 16, 16)).mean()
    assert terms.lpips.item() == pytest.approx(expected_lpips.item(), rel=1e-6)
    assert terms.total.item() == pytest.approx(0.05**2 + 0.05 * expected_lpips.item(), rel=1e-5)
    terms.total.backward()
    assert prediction.grad is not None and bool(torch.isfinite(prediction.grad).all())
    # The gradient holds more than MSE's 2 e / N: LPIPS contributes.
    mse_grad = torch.full_like(prediction, 2 * 0.05 / prediction.numel())
    assert (prediction.grad - mse_grad).abs().max() > 1e-6


def test_a_loaded_lpips_model_can_be_shared(lpips_files):
    model = load_lpips(*lpips_files)
    loss = ImageLoss(LossConfig(lpips_weight=0.5), lpips=model)
    assert loss.lpips is model


def test_cascade_weights_follow_the_release():
    # Intermediate render i of n (coarse first) weighs 0.9^(n - i); the final render weighs 1.
    assert cascade_weights(1) == [1.0]
    assert cascade_weights(2) == pytest.approx([0.9, 1.0])
    assert cascade_weights(3) == pytest.approx([0.81, 0.9, 1.0])
    assert cascade_weights(3, base=0.5) == pytest.approx([0.25, 0.5, 1.0])
    with pytest.raises(SurfSplatInputError, match="num_renders"):
        cascade_weights(0)


def test_cascade_loss_is_the_weighted_sum_of_per_render_losses():
    loss = ImageLoss(LossConfig(lpips_weight=0.0))
    _, target = constant_error_pair(0.0)
    errors = (0.3, 0.2, 0.1)  # coarse, middle, final
    renders = [target + e for e in errors]
    total, terms = cascade_loss(loss, renders, target)
    assert [t.mse.item() for t in terms] == pytest.approx([e * e for e in errors], rel=1e-5)
    assert total.item() == pytest.approx(0.81 * 0.09 + 0.9 * 0.04 + 1.0 * 0.01, rel=1e-5)
    single, _ = cascade_loss(loss, renders[-1:], target)
    assert single.item() == pytest.approx(0.01, rel=1e-5)


def test_bad_config_and_inputs_are_named():
    with pytest.raises(SurfSplatInputError, match="config.lpips_weight"):
        ImageLoss(LossConfig(lpips_weight=-0.1))
    with pytest.raises(SurfSplatInputError, match="config.mse_weight"):
        ImageLoss(LossConfig(mse_weight=float("nan"), lpips_weight=0.0))
    loss = ImageLoss(LossConfig(lpips_weight=0.0))
    with pytest.raises(SurfSplatInputError, match="target"):
        loss(torch.rand(2, 3, 8, 8), torch.rand(2, 3, 8, 9))
    with pytest.raises(SurfSplatInputError, match="prediction"):
        loss(torch.rand(3, 8, 8), torch.rand(3, 8, 8))
    with pytest.raises(SurfSplatInputError, match="renders"):
        cascade_loss(loss, [], torch.rand(1, 3, 8, 8))


# ------------------------------------------------------------------------------ geometry supervision
def _pinhole(batch=(1, 1), size=16, focal=20.0) -> torch.Tensor:
    K = torch.tensor([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1.0]])
    return K.expand(*batch, 3, 3).clone()


def _plane_depth(normal, offset: float, K: torch.Tensor, size=16) -> torch.Tensor:
    """[H, W] camera-z depth of the plane n . X = offset seen through K (pixel centres)."""
    from surfsplat.model.adapter import unproject_depth

    rays = unproject_depth(torch.ones(size, size), K)  # z = 1 rays
    n = torch.nn.functional.normalize(torch.tensor(normal, dtype=torch.float32), dim=0)
    return offset / (rays @ n)


def test_geometry_loss_is_relative_depth_error_and_normal_angle():
    from surfsplat.train.losses import geometry_loss

    K = _pinhole()
    truth = torch.full((1, 1, 1, 16, 16), 2.0)  # fronto-parallel wall 2 m away
    unknown = torch.zeros(16, 16, dtype=torch.bool)
    unknown[:4, :4] = True
    truth[0, 0, 0][unknown] = 0  # no truth there: left out of both terms
    config = LossConfig(lpips_weight=0, depth_weight=0.5, normal_weight=0.25)

    # 10% too far everywhere: relative error 0.1 exactly, and the same (flat) normals.
    scaled = torch.where(unknown, torch.tensor(7.0), torch.tensor(2.2))[None, None]
    terms = geometry_loss(config, scaled, truth, K)
    assert terms.depth.item() == pytest.approx(0.1, rel=1e-5)
    assert terms.normal.item() == pytest.approx(0.0, abs=1e-6)  # the 7 m block never enters a stencil
    assert terms.total.item() == pytest.approx(0.5 * 0.1, rel=1e-5)

    # A plane tilted by 30 degrees about the camera's y axis, through (0, 0, 2): 1 - cos 30 at every
    # pixel whose 3x3 stencil has truth, whatever the depth error is.
    angle = torch.deg2rad(torch.tensor(30.0))
    tilted = _plane_depth((float(torch.sin(angle)), 0.0, float(torch.cos(angle))), 2 * float(torch.cos(angle)), K[0, 0])
    terms = geometry_loss(config, tilted[None, None], truth, K)
    assert terms.normal.item() == pytest.approx(1 - float(torch.cos(angle)), rel=1e-4)
    inside = torch.ones(16, 16, dtype=torch.bool)
    inside[:4, :4] = False
    expected_depth = ((tilted - 2).abs() / 2)[inside].mean()
    assert terms.depth.item() == pytest.approx(float(expected_depth), rel=1e-5)

    # Exact depth gives zero for both; a weight of 0 leaves its term out.
    exact = geometry_loss(LossConfig(lpips_weight=0, depth_weight=1.0), truth[:, :, 0].clamp_min(2.0), truth, K)
    assert exact.depth.item() == 0 and exact.normal is None and exact.total.item() == 0


def test_geometry_loss_needs_some_truth_and_matching_shapes():
    from surfsplat.train.losses import geometry_loss

    config = LossConfig(lpips_weight=0, depth_weight=1.0)
    with pytest.raises(SurfSplatInputError, match="no pixel with a true depth"):
        geometry_loss(config, torch.ones(1, 1, 8, 8), torch.zeros(1, 1, 1, 8, 8), _pinhole(size=8))
    with pytest.raises(SurfSplatInputError, match="true_depths"):
        geometry_loss(config, torch.ones(1, 1, 8, 8), torch.ones(1, 2, 1, 8, 8), _pinhole(size=8))
    with pytest.raises(SurfSplatInputError, match="normal_weight"):
        ImageLoss(LossConfig(lpips_weight=0, normal_weight=-1.0))
