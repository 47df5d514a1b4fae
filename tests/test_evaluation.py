"""Evaluation: one scaling ratio per image over all scored pixels, shared by the angle breakdown."""

from __future__ import annotations

import pytest
import torch

from fisheyedepth.cameras import RayCache
from fisheyedepth.evaluation import ANGLE_BINS, PROTOCOLS, Evaluator

from conftest import kitti02


@pytest.fixture(scope="module")
def scene():
    """A 96 x 96 KITTI-360 camera, a ground truth of 2-40 m, and its rays and angles of incidence."""
    camera = kitti02().resize(96, 96)
    rays, valid = RayCache().get(camera, dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    gt = (2.0 + 38.0 * torch.rand(96, 96, generator=gen, dtype=torch.float64)) * valid
    angle = torch.rad2deg(torch.acos(rays[..., 2].clamp(-1, 1)))
    return camera, gt, valid, angle


def test_median_scaling_is_one_ratio_per_image_shared_by_the_angle_bands(scene):
    camera, gt, valid, angle = scene
    # the periphery beyond 60 degrees is predicted 2x too far, the centre right, and all 3x too near
    pred = torch.where(angle >= 60, 2.0 * gt, gt) / 3.0
    ev = Evaluator(PROTOCOLS["full"], ("none", "median"))
    ev.update(pred, gt, valid, camera)
    out = ev.compute()
    scored = valid & (gt > 0)
    ratio = float(gt[scored].median() / pred[scored].median())
    assert out["median"]["scale_ratio"] == pytest.approx(ratio)
    bands = out["median_by_angle"]
    for lo, hi in ANGLE_BINS:  # each band scored with the image's ratio, not its own
        band = scored & (angle >= lo) & (angle < hi)
        if band.any():
            expected = ((pred[band] * ratio - gt[band]).abs() / gt[band]).mean()
            assert bands[f"{lo}-{hi}"]["abs_rel"] == pytest.approx(float(expected), rel=1e-6)
    # per-band median scaling would have made both the centre and the periphery exact; one ratio does not
    assert bands["0-30"]["abs_rel"] > 0.1 and bands["60-90"]["abs_rel"] > 0.1
    # and the bands add up to the headline number, weighted by their pixels
    weights = {f"{lo}-{hi}": int((scored & (angle >= lo) & (angle < hi)).sum()) for lo, hi in ANGLE_BINS}
    total = sum(weights[k] * bands[k]["abs_rel"] for k in weights if weights[k]) / sum(weights.values())
    assert out["median"]["abs_rel"] == pytest.approx(total, rel=1e-6)
    assert out["none"]["abs_rel"] == pytest.approx(
        float(((pred[scored] - gt[scored]).abs() / gt[scored]).mean()), rel=1e-6
    )


def test_a_right_shape_at_the_wrong_scale_is_exact_after_median_scaling(scene):
    camera, gt, valid, _ = scene
    ev = Evaluator(PROTOCOLS["full"], ("none", "median"))
    ev.update(gt * 0.25, gt, valid, camera)
    out = ev.compute()
    assert out["none"]["abs_rel"] == pytest.approx(0.75)
    assert out["median"]["abs_rel"] == pytest.approx(0.0, abs=1e-9) and out["median"]["a1"] == 1.0
    assert out["median"]["scale_ratio"] == pytest.approx(4.0)


def test_per_camera_breakdown_scores_each_named_camera_alone(scene):
    camera, gt, valid, _ = scene
    ev = Evaluator(PROTOCOLS["full"], ("none",))
    ev.update(gt * 0.5, gt, valid, camera, "image_02")  # abs_rel 0.5
    ev.update(gt * 1.1, gt, valid, camera, "image_03")  # abs_rel 0.1
    ev.update(gt * 1.1, gt, valid, camera, "image_03")
    out = ev.compute()
    cams = out["none_by_camera"]
    assert set(cams) == {"image_02", "image_03"}
    assert cams["image_02"]["abs_rel"] == pytest.approx(0.5) and cams["image_02"]["images"] == 1
    assert cams["image_03"]["abs_rel"] == pytest.approx(0.1) and cams["image_03"]["images"] == 2
    assert out["none"]["abs_rel"] == pytest.approx((0.5 + 0.1 + 0.1) / 3)  # same pixels per image


def test_unnamed_images_give_no_per_camera_breakdown(scene):
    camera, gt, valid, _ = scene
    ev = Evaluator(PROTOCOLS["full"], ("none",))
    ev.update(gt, gt, valid, camera)
    assert "none_by_camera" not in ev.compute()


def test_the_occlusion_filter_is_the_protocols_and_only_for_lidar(scene):
    """A far LiDAR point two pixels from a near one (the scanner saw behind an edge): the project's
    ``full`` protocol drops it, the reference's ``kitti360`` scores it, and a dense map is never filtered."""
    camera, _, valid, _ = scene
    gt = torch.zeros(96, 96, dtype=torch.float64)
    gt[48, 40], gt[48, 42], gt[30, 30] = 3.0, 6.0, 5.0  # all within 8 m, near the optical axis (z > 0.3)
    pred = gt.clone()
    pred[48, 42] = 3.0  # the camera sees the near surface there: a network predicts it
    results = {}
    for name in ("full", "kitti360"):
        for source in ("lidar", "rendered"):
            ev = Evaluator(PROTOCOLS[name], ("none",))
            ev.update(pred, gt, valid, camera, source=source)
            results[name, source] = ev.compute()["none"]["abs_rel"]
    assert results["full", "lidar"] == 0.0  # the hidden point is not scored
    assert results["kitti360", "lidar"] == pytest.approx(0.5 / 3)  # scored: |3 - 6| / 6 over 3 points
    assert results["full", "rendered"] == results["kitti360", "rendered"] == pytest.approx(0.5 / 3)
    assert PROTOCOLS["kitti360"].occlusion is None and PROTOCOLS["full"].occlusion == 0.1


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_scores_on_cuda_equal_those_on_the_cpu(scene):
    """eval.py device=cuda feeds CUDA tensors: the metrics' states follow them, the numbers do not move."""
    camera, gt, valid, _ = scene
    pred = gt * torch.linspace(0.7, 1.4, gt.shape[1], dtype=gt.dtype)
    out = {}
    for device in ("cpu", "cuda"):
        ev = Evaluator(PROTOCOLS["full"], ("none", "median"))
        for name in ("image_02", "image_03"):
            ev.update(pred.to(device), gt.to(device), valid.to(device), camera, name)
        out[device] = ev.compute()
    for scaling in ("none", "median"):
        for key in ("abs_rel", "a1", "rmse"):
            # float32 reductions (a1's mean) differ by ~1e-7 between the devices (seen on an H100)
            assert out["cuda"][scaling][key] == pytest.approx(out["cpu"][scaling][key], rel=1e-6)
        for name, cpu in out["cpu"][f"{scaling}_by_camera"].items():
            assert out["cuda"][f"{scaling}_by_camera"][name] == pytest.approx(cpu, rel=1e-6)
    assert out["cpu"]["none"]["abs_rel"] > 0.05  # the case is not trivial
