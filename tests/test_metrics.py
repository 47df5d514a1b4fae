"""Depth metrics: known values, per-image averaging over an epoch, masks, caps, median scaling."""

from __future__ import annotations

import math

import pytest
import torch

from fisheyedepth.metrics import DepthMetrics, image_metrics


def test_known_values():
    gt = torch.tensor([2.0, 4.0, 8.0])
    m = image_metrics(gt.clone(), gt)
    assert m.tolist() == pytest.approx([0, 0, 0, 0, 1, 1, 1])
    m = image_metrics(2 * gt, gt)
    assert m[0].item() == pytest.approx(1.0)  # abs_rel
    assert m[1].item() == pytest.approx((4 / 2 + 16 / 4 + 64 / 8) / 3)  # sq_rel
    assert m[2].item() == pytest.approx(math.sqrt((4 + 16 + 64) / 3))
    assert m[3].item() == pytest.approx(math.log(2))
    assert m[4:].tolist() == pytest.approx([0.0, 0.0, 0.0])  # a ratio of 2 exceeds 1.25, 1.5625 and 1.953
    m = image_metrics(1.2 * gt, gt)
    assert m[4:].tolist() == pytest.approx([1.0, 1.0, 1.0])


def test_epoch_average_is_per_image_with_masks_caps_and_scaling():
    metric = DepthMetrics(cap=(1e-3, 80.0))
    scaled = DepthMetrics(cap=(1e-3, 80.0), median_scaling=True)
    gt = torch.full((2, 1, 4, 4), 10.0)
    gt[0, 0, 0, 0] = 0.0  # no ground truth: ignored
    gt[1, 0, 0, 0] = 500.0  # beyond the cap: ignored
    pred = gt.clone()
    pred[1] = 20.0  # the second image twice too far
    mask = torch.ones_like(gt, dtype=torch.bool)
    mask[0, 0, 3, 3] = False
    pred[0, 0, 3, 3] = 1000.0  # masked out
    for m in (metric, scaled):
        m.update(pred[:1], gt[:1], mask[:1])  # two updates: one epoch of two batches
        m.update(pred[1:], gt[1:], mask[1:])
        m.update(pred[1:], torch.zeros_like(gt[1:]))  # an image without any valid pixel: skipped
    out = metric.compute()
    assert out["abs_rel"].item() == pytest.approx((0.0 + 1.0) / 2)
    assert out["a1"].item() == pytest.approx(0.5)
    assert int(metric.skipped) == 1 and int(metric.images) == 2
    out = scaled.compute()
    assert out["abs_rel"].item() == pytest.approx(0.0, abs=1e-12)
    assert out["scale_ratio"].item() == pytest.approx((1.0 + 0.5) / 2)
    metric.reset()
    assert int(metric.images) == 0


def test_predictions_are_clamped_to_the_caps():
    metric = DepthMetrics(cap=(1.0, 10.0))
    metric.update(torch.full((1, 1, 2, 2), 1e6), torch.full((1, 1, 2, 2), 5.0))
    assert metric.compute()["abs_rel"].item() == pytest.approx(1.0)  # clamped to 10, not 1e6
