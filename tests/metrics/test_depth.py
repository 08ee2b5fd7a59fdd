"""Depth errors against hand-computed values, masks and the ScanNet range."""

from __future__ import annotations

import math

import pytest
import torch

from surfsplat.metrics import SCANNET_DEPTH_RANGE, depth_metrics
from surfsplat.utils.checks import SurfSplatInputError


def test_depth_metrics_closed_form_on_four_pixels():
    target = torch.tensor([[[1.0, 2.0], [4.0, 5.0]]])
    prediction = torch.tensor([[[1.1, 1.0], [4.0, 10.0]]])
    m = depth_metrics(prediction, target)
    # Per pixel: |e| = .1, 1, 0, 5; e^2 = .01, 1, 0, 25; ratio = 1.1, 2, 1, 2.
    assert m.abs_rel.item() == pytest.approx((0.1 / 1 + 1 / 2 + 0 + 5 / 5) / 4)
    assert m.sq_rel.item() == pytest.approx((0.01 / 1 + 1 / 2 + 0 + 25 / 5) / 4)
    assert m.rmse.item() == pytest.approx(math.sqrt((0.01 + 1 + 0 + 25) / 4))
    logs = [math.log(1.1), math.log(0.5), 0.0, math.log(2.0)]
    assert m.log_rmse.item() == pytest.approx(math.sqrt(sum(v * v for v in logs) / 4))
    assert m.delta1.item() == pytest.approx(0.5)  # 1.1 and 1 pass 1.25
    assert m.delta2.item() == pytest.approx(0.5)  # 2 > 1.25^2 = 1.5625
    assert m.delta3.item() == pytest.approx(0.5)  # 2 > 1.25^3 = 1.953125
    assert m.num_valid.tolist() == [4]


def test_delta_thresholds_are_powers_of_1_25():
    target = torch.ones(1, 1, 3)
    prediction = torch.tensor([[[1.24, 1.5, 1.9]]])  # just under 1.25, 1.25^2, 1.25^3
    m = depth_metrics(prediction, target)
    assert [m.delta1.item(), m.delta2.item(), m.delta3.item()] == pytest.approx([1 / 3, 2 / 3, 1.0])
    prediction = torch.tensor([[[1 / 1.24, 1 / 1.5, 1 / 1.9]]])  # under-estimates count the same
    m = depth_metrics(prediction, target)
    assert [m.delta1.item(), m.delta2.item(), m.delta3.item()] == pytest.approx([1 / 3, 2 / 3, 1.0])


def test_masks_and_depth_range_select_pixels():
    target = torch.tensor([[[0.0, 0.3, 2.0, 12.0]], [[math.inf, 3.0, 3.0, 3.0]]])
    prediction = torch.tensor([[[5.0, 5.0, 2.2, 1.0]], [[1.0, 3.3, 3.0, 6.0]]])
    m = depth_metrics(prediction, target, min_depth=SCANNET_DEPTH_RANGE[0], max_depth=SCANNET_DEPTH_RANGE[1])
    # Image 0: only 2.0 is inside (0.5, 10); image 1: the three finite 3.0 pixels.
    assert m.num_valid.tolist() == [1, 3]
    assert m.abs_rel.tolist() == pytest.approx([0.1, (0.1 + 0 + 1) / 3])
    mask = torch.tensor([[[True, True, True, True]], [[True, True, True, False]]])
    m = depth_metrics(prediction, target, mask, min_depth=0.5, max_depth=10.0)
    assert m.num_valid.tolist() == [1, 2]
    assert m.abs_rel.tolist() == pytest.approx([0.1, 0.05])
    means = m.mean()
    assert means["abs_rel"] == pytest.approx(0.075) and means["num_images"] == 2


def test_empty_images_are_nan_and_skipped_in_the_mean():
    target = torch.tensor([[[0.0, 0.0]], [[2.0, 2.0]]])
    prediction = torch.tensor([[[1.0, 1.0]], [[2.0, 3.0]]])
    m = depth_metrics(prediction, target)
    assert math.isnan(m.rmse[0].item()) and m.num_valid.tolist() == [0, 2]
    assert m.mean()["rmse"] == pytest.approx(math.sqrt(0.5)) and m.mean()["num_images"] == 1
    with pytest.raises(SurfSplatInputError, match="no image has a valid"):
        depth_metrics(prediction[:1], target[:1]).mean()


def test_holes_in_the_prediction_fail_every_delta_and_make_log_rmse_infinite():
    target = torch.tensor([[[2.0, 2.0]]])
    prediction = torch.tensor([[[2.0, 0.0]]])
    m = depth_metrics(prediction, target)
    assert m.delta1.item() == pytest.approx(0.5) and m.delta3.item() == pytest.approx(0.5)
    assert math.isinf(m.log_rmse.item())
    assert m.abs_rel.item() == pytest.approx(0.5)


def test_channel_axis_and_bad_inputs():
    target = 1 + torch.rand(2, 1, 4, 4)
    prediction = target * 1.1
    assert depth_metrics(prediction, target).abs_rel.tolist() == pytest.approx([0.1, 0.1], rel=1e-5)
    with pytest.raises(SurfSplatInputError, match="target"):
        depth_metrics(prediction[:, 0], target[:1, 0])
    with pytest.raises(SurfSplatInputError, match="mask"):
        depth_metrics(prediction, target, torch.ones(2, 4, 4))
    with pytest.raises(SurfSplatInputError, match="min_depth"):
        depth_metrics(prediction, target, min_depth=2.0, max_depth=1.0)
