"""Sweep stereo on the sphere (fisheyedepth.stereo.sweep, .costs): its costs, aggregation and refinement
to exact numbers, and metric distance from a fisheye rig, a moving fisheye camera and a rectified pinhole
pair (beside OpenCV's StereoSGBM) in a textured room with exact ground truth."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from fisheyedepth.cameras import PinholeCamera
from fisheyedepth.cameras.rays import compute_rays
from fisheyedepth.geometry.se3 import invert_pose
from fisheyedepth.stereo import SweepMatcher, SweepSettings, View
from fisheyedepth.stereo.costs import aggregate, box_mean, census, census_cost, hamming, winner, zncc_cost
from stereo_world import pair, pose, render, scores, texture_volume

from conftest import kitti02


# ------------------------------------------------------------------ costs, aggregation, refinement
def test_zncc_cost_is_zero_for_gain_and_offset_and_one_for_inversion():
    a = torch.rand(1, 1, 24, 24, generator=torch.Generator().manual_seed(0))
    assert zncc_cost(a, 2 * a + 1, 5)[0, 2:-2, 2:-2].max() < 1e-3
    assert zncc_cost(a, -a, 5)[0, 2:-2, 2:-2].min() > 1 - 1e-3
    flat = torch.full_like(a, 0.3)
    assert torch.allclose(zncc_cost(a, flat, 5), torch.full((1, 24, 24), 0.5), atol=1e-3)  # no evidence


@pytest.mark.parametrize("window", [3, 7, 11])
def test_the_separable_box_mean_is_the_window_mean(window):
    x = torch.rand(2, 1, 37, 53, dtype=torch.float64, generator=torch.Generator().manual_seed(window))
    expected = F.avg_pool2d(x, window, stride=1, padding=window // 2, count_include_pad=False)
    assert torch.allclose(box_mean(x, window), expected, atol=1e-12)


def test_hypotheses_warped_in_chunks_give_the_same_volume():
    camera = kitti02().resize(48, 48)
    reference, source, _ = pair(camera, camera, pose(), pose(30.0, (0.2, 0.0, 0.0)))
    one, seen_one = SweepMatcher(SweepSettings(hypotheses=10, chunk=1)).cost_volume(reference, [source])
    many, seen_many = SweepMatcher(SweepSettings(hypotheses=10, chunk=4)).cost_volume(reference, [source])
    assert torch.equal(one, many) and torch.equal(seen_one, seen_many)


def test_census_counts_the_neighbours_that_change_order():
    a = torch.arange(25.0).reshape(1, 1, 5, 5)  # strictly increasing in reading order
    bits = census(a, 3)
    assert bits.shape == (1, 8, 5, 5)
    # the centre pixel: the 4 neighbours after it in reading order are brighter, the 4 before are not
    assert bits[0, :, 2, 2].tolist() == [False] * 4 + [True] * 4
    assert float(hamming(bits, census(-a, 3))[0, 2, 2]) == 1.0
    assert float(hamming(bits, census(3 * a + 7, 3)).max()) == 0.0


@pytest.mark.parametrize("window", [3, 7, 9])
def test_the_census_cost_counts_what_hamming_counts(window):
    g = torch.Generator().manual_seed(window)
    reference = torch.rand(2, 1, 13, 17, generator=g)
    warps = torch.rand(2, 5, 13, 17, generator=g)
    expected = torch.stack([hamming(census(reference, window), census(warps[:, k : k + 1], window))
                            for k in range(5)], 1)  # fmt: skip
    assert torch.equal(census_cost(census(reference, window), warps, window), expected)


def test_aggregation_without_penalties_adds_the_cost_once_per_path():
    volume = torch.rand(2, 6, 7, 9, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(aggregate(volume, 0.0, 0.0, 4), 4 * volume, atol=1e-6)
    assert torch.allclose(aggregate(volume, 0.0, 0.0, 8), 8 * volume, atol=1e-6)
    assert torch.equal(aggregate(volume, 0.1, 0.5, 0), volume)


def test_aggregation_outvotes_one_wrong_pixel():
    """A 9x9 patch at hypothesis 3 with one pixel whose own cost prefers 7 by 0.8: a jump penalty P2 above
    that carries 3 into it along every path, one below it does not."""
    volume = torch.ones(1, 10, 9, 9)
    volume[:, 3] = 0.0
    volume[:, :, 4, 4] = 1.0
    volume[:, 7, 4, 4] = 0.2
    assert int(volume.argmin(1)[0, 4, 4]) == 7
    index, _ = winner(aggregate(volume, 0.05, 1.0, 4))
    assert torch.equal(index.round(), torch.full((1, 9, 9), 3.0))
    index, _ = winner(aggregate(volume, 0.05, 0.7, 4))
    assert int(index[0, 4, 4].round()) == 7 and int((index.round() == 3).sum()) == 80


def test_winner_refines_to_the_parabola_vertex_and_says_how_unique_it_is():
    hypotheses = torch.arange(20.0).reshape(1, 20, 1, 1)
    index, confidence = winner((hypotheses - 10.3) ** 2 + 1.0)
    assert float(index) == pytest.approx(10.3, abs=1e-5)
    # best 1.09, second best outside the winner's neighbours (index 8 or 12): 1 + 1.7**2 = 3.89
    assert float(confidence) == pytest.approx(1 - 1.09 / 3.89, abs=1e-5)
    flat, flat_confidence = winner(torch.ones(1, 20, 1, 1))
    assert float(flat_confidence) == 0.0


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [
        ("cost", "sad", "cost: 'sad' is not one of zncc, census"),
        ("min_distance", 0.0, "min_distance, max_distance: 0.0, 80.0"),
        ("window", 4, "window: 4 is not an odd number >= 3"),
        ("paths", 3, "paths: 3 is not 0, 4 or 8"),
        ("hypotheses", 2, "hypotheses: 2; at least 3"),
    ],
)
def test_bad_settings_are_refused_by_name(option, value, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        SweepMatcher(SweepSettings(**{option: value}))


def test_a_reference_without_sources_is_refused():
    camera = PinholeCamera(width=32, height=32, fx=30.0, fy=30.0, cx=15.5, cy=15.5)
    with pytest.raises(ValueError, match="sources: sweep stereo needs at least one source view"):
        SweepMatcher(SweepSettings())(View(torch.rand(1, 1, 32, 32), camera, torch.eye(4)), [])


# ------------------------------------------------------------------ metric distance, exact ground truth
SIZE = 160
SWEEP = SweepMatcher(SweepSettings(hypotheses=64, min_distance=0.5, max_distance=20.0))


def test_a_fisheye_rig_gives_metric_distance_beyond_90_degrees():
    """Two KITTI-360 fisheyes 0.2 m apart, turned 30 degrees: checked abs_rel on the pixels it keeps,
    and pixels seen beyond 90 degrees of incidence keep estimates."""
    camera = kitti02().resize(SIZE, SIZE)
    reference, source, truth = pair(camera, camera, pose(), pose(30.0, (0.2, 0.0, 0.0)))
    result = SWEEP(reference, [source])
    checked, dense = scores(result.distance, truth), scores(result.dense, truth)
    assert checked["abs_rel"] < 0.05 and checked["a1"] > 0.97 and checked["coverage"] > 0.75, checked
    assert dense["abs_rel"] < 0.08 and dense["coverage"] > 0.85, dense
    assert checked["abs_rel"] < dense["abs_rel"]  # the round trip removes errors
    rays, _ = compute_rays(camera)
    wide = (rays[..., 2] < 0)[None]  # beyond 90 degrees of incidence
    beyond = scores(result.distance, truth, wide & result.seen)
    assert wide.sum() > 100 and beyond["coverage"] > 0.5 and beyond["abs_rel"] < 0.08, beyond
    assert ((result.confidence >= 0) & (result.confidence <= 1)).all()
    assert float(result.confidence[result.valid].mean()) > float(
        result.confidence[result.seen & ~result.valid].mean()
    )


def test_a_moving_fisheye_camera_gives_metric_distance_from_its_odometry():
    """One camera at two instants, 0.25 m apart sideways and 0.1 m forward (odometry): motion stereo. Rays
    within 25 degrees of the motion (its epipoles, where nothing moves) are resolvable by no method and
    are scored apart."""
    camera = kitti02().resize(SIZE, SIZE)
    T_b = pose(5.0, (0.25, 0.0, 0.1))
    reference, source, truth = pair(camera, camera, pose(), T_b, seed=1)
    result = SWEEP(reference, [source])
    rays, _ = compute_rays(camera)
    motion = T_b[:3, 3].float() / T_b[:3, 3].norm()
    parallax = ((rays @ motion).abs() < math.cos(math.radians(25)))[None]
    checked = scores(result.distance, truth, parallax)
    assert checked["abs_rel"] < 0.05 and checked["coverage"] > 0.7, checked
    assert scores(result.dense, truth, ~parallax)["abs_rel"] > checked["abs_rel"]


def test_two_sources_see_more_than_one():
    """A reference between two partners turned 40 degrees either way: more of it is seen, as well."""
    camera = kitti02().resize(96, 96)
    volume = texture_volume(2)
    poses = pose(), pose(40.0, (0.2, 0.0, 0.0)), pose(-40.0, (-0.2, 0.0, 0.0))
    (image, truth), *others = [render(camera, T, volume) for T in poses]
    views = [
        View(img, camera, (invert_pose(T) @ poses[0]).float())
        for (img, _), T in zip(others, poses[1:], strict=True)
    ]
    reference = View(image, camera, torch.eye(4))
    one, _, seen_one = SWEEP.estimate(reference, views[:1])
    both, _, seen_both = SWEEP.estimate(reference, views)
    assert seen_both.sum() > 1.1 * seen_one.sum() and (seen_both | ~seen_one).all()
    assert scores(both, truth)["abs_rel"] < 0.08 and scores(both, truth)["coverage"] > 0.95


def test_a_rectified_pinhole_pair_beside_opencv_stereo_sgbm():
    """A rectified pinhole pair (0.2 m baseline): the sweep (census and ZNCC) against OpenCV's StereoSGBM
    on the same images, both scored against the exact distance."""
    width, height, f = 128, 96, 80.0
    camera = PinholeCamera(width=width, height=height, fx=f, fy=f, cx=63.5, cy=47.5)
    reference, source, truth = pair(camera, camera, pose(), pose(0.0, (0.2, 0.0, 0.0)), seed=3)
    sweep = {cost: SweepMatcher(SweepSettings(hypotheses=64, min_distance=1.0, max_distance=20.0, cost=cost,
                                              window=9)) for cost in ("zncc", "census")}  # fmt: skip
    ours = {cost: scores(s(reference, [source]).distance, truth) for cost, s in sweep.items()}

    left = (reference.image[0, 0].numpy() * 255).astype(np.uint8)
    right = (source.image[0, 0].numpy() * 255).astype(np.uint8)
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=32, blockSize=5, P1=8 * 25, P2=32 * 25,
                                 uniquenessRatio=5, disp12MaxDiff=1)  # fmt: skip
    disparity = sgbm.compute(left, right).astype(np.float32) / 16
    rays, _ = compute_rays(camera)
    z = torch.where(torch.from_numpy(disparity) > 0, f * 0.2 / torch.from_numpy(disparity).clamp(min=1e-3), 0)
    theirs = scores((z / rays[..., 2])[None], truth)
    assert theirs["abs_rel"] < 0.1 and theirs["coverage"] > 0.5, theirs  # OpenCV works on this pair
    for cost, score in ours.items():
        assert score["abs_rel"] < max(0.05, 1.5 * theirs["abs_rel"]), (cost, score, theirs)
        assert score["coverage"] > 0.8 * theirs["coverage"], (cost, score, theirs)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_the_sweep_runs_on_cuda_as_on_the_cpu():
    camera = kitti02().resize(64, 64)
    reference, source, _ = pair(camera, camera, pose(), pose(30.0, (0.2, 0.0, 0.0)))
    on_cpu = SweepMatcher(SweepSettings(hypotheses=24))(reference, [source])
    cuda = [View(v.image.cuda(), v.camera, v.T_ref_to_view.cuda()) for v in (reference, source)]
    on_gpu = SweepMatcher(SweepSettings(hypotheses=24))(cuda[0], cuda[1:])
    agree = (on_gpu.dense.cpu() - on_cpu.dense).abs() <= 1e-3 * on_cpu.dense
    assert agree.float().mean() > 0.99
