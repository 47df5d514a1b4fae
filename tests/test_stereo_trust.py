"""Distance from geometry that can be trusted: each way a pair's images can mislead the rectified pipeline,
reproduced on small synthetic rigs in the textured room (exact distance), and what the pipeline does
about it: the round trip, a motion checked against its images, static pixels, fusion by evidence, a
refinement that cannot make a rig worse, a search range from geometry, and pairs whose images contradict
their calibration or motion named with the evidence and keeping no pixel."""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import pytest
import torch

from fisheyedepth.cameras import PinholeCamera
from fisheyedepth.cameras.base import CameraModel
from fisheyedepth.geometry.se3 import axis_angle_to_matrix, invert_pose, make_pose
from fisheyedepth.stereo import RigStereo, SgbmSettings, match_pair, rectify_pair
from fisheyedepth.stereo.features import features, match_features
from fisheyedepth.stereo.fuse import fuse
from fisheyedepth.stereo.motion import check_motion
from fisheyedepth.stereo.pipeline import MAX_TRIANGULATION_DEG, pair_range
from fisheyedepth.stereo.rectify import RectificationCache
from fisheyedepth.stereo.refine import guarded_refinement
from fisheyedepth.stereo.static import StaticFinder
from stereo_world import pose, render, texture_volume

from conftest import kitti02

SETTINGS = SgbmSettings(min_distance=0.5, max_distance=20.0)


def shot(camera, P, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """8-bit image and exact distance of ``camera`` at pose ``P`` in the room."""
    image, distance = render(camera, P, texture_volume(seed))
    return (image[0, 0].numpy() * 255).round().astype(np.uint8), distance[0].numpy()


@functools.cache
def fisheye() -> CameraModel:
    return kitti02().resize(192, 192)


def errors(distance: np.ndarray, truth: np.ndarray) -> np.ndarray:
    kept = (distance > 0) & (truth > 0)
    return np.abs(distance[kept] / truth[kept] - 1)


def pair_maps(camera_a, camera_b, P_a, P_b, T_claimed=None, images=None, settings=SETTINGS, claimed_b=None):
    """Camera a's maps against b (the pair's geometry as claimed), and a's exact distance."""
    image_a, truth = shot(camera_a, P_a)
    image_b, _ = shot(camera_b, P_b)
    if images is not None:
        image_a, image_b = images(image_a, image_b)
    T = (invert_pose(P_b) @ P_a).numpy() if T_claimed is None else T_claimed
    rect = rectify_pair(camera_a, claimed_b or camera_b, T, settings, (True, False), RectificationCache())
    maps, _ = match_pair(image_a, image_b, rect, settings, (True, False))
    return maps, truth


# ------------------------------------------------------------------ the round trip
def test_the_round_trip_drops_answers_outside_the_partners_view():
    """A camera 1 m forward of the reference: a band of the reference lies outside its view, where SGBM
    still answers with a smaller, wrong disparity. Without the round trip (a miss of any size allowed)
    those answers are kept (7 % of the kept pixels off by over 25 %); with it (1 grid pixel) they are not,
    and the kept pixels are right."""
    camera = fisheye()
    now, then = pose(0, (0.0, 0.0, 0.0)), pose(0, (0.0, 0.0, 1.0))
    loose = dataclasses.replace(SETTINGS, sgbm=dataclasses.replace(SETTINGS.sgbm, round_trip=1e6))
    without, truth = pair_maps(camera, camera, now, then, settings=loose)
    kept, _ = pair_maps(camera, camera, now, then)
    wrong_without, wrong_with = (float((errors(m.distance, truth) > 0.25).mean()) for m in (without, kept))
    assert wrong_without > 0.05 and wrong_with < 0.5 * wrong_without, (wrong_without, wrong_with)
    assert np.median(errors(kept.distance, truth)) < 0.03
    assert 0.5 < kept.evidence.returned / kept.evidence.answered < 0.95
    assert kept.roundtrip[kept.distance > 0].max() <= 1.0


# ------------------------------------------------------------------ odometry is not a calibration
def test_a_motion_off_by_5_cm_and_one_and_a_half_degrees_is_refined_from_its_images():
    """The odometry says the camera moved 0.35 m, but it also turned by 1.5 degrees and slid 5 cm: the
    motion check finds its images over a pixel off the odometry's epipolar curves, refines the rotation
    and the direction of travel (the length kept), and leaves a fraction of a pixel; matched with the
    refined pose the distance is right, with the odometry's it is not."""
    camera = fisheye()
    then, now = pose(0, (0.0, 0.0, 0.0)), pose(6, (0.25, 0.0, 0.25))
    truth_T = (invert_pose(then) @ now).numpy()  # now -> then
    slip = pose(1.5, (0.05, 0.0, 0.0)).numpy()
    odometry = slip @ truth_T
    odometry[:3, 3] *= np.linalg.norm(truth_T[:3, 3]) / np.linalg.norm(odometry[:3, 3])  # length right
    image_now, truth = shot(camera, now)
    image_then, _ = shot(camera, then)
    verdict = check_motion(features(image_now, 1000), camera, features(image_then, 1000), camera, odometry)
    assert verdict.left_out is None and verdict.applied
    assert verdict.before_px > 1.0 and verdict.after_px < 0.3, verdict.record()
    assert np.linalg.norm(verdict.T_a_to_b[:3, 3]) == pytest.approx(np.linalg.norm(odometry[:3, 3]))
    R_error = verdict.T_a_to_b[:3, :3] @ truth_T[:3, :3].T
    assert math.degrees(math.acos(min(1.0, (np.trace(R_error) - 1) / 2))) < 0.3  # of the 1.5 off
    refined, _ = pair_maps(camera, camera, now, then, T_claimed=verdict.T_a_to_b)
    raw, _ = pair_maps(camera, camera, now, then, T_claimed=odometry)
    assert np.median(errors(refined.distance, truth)) < 0.03 < np.median(errors(raw.distance, truth))


def test_the_live_rig_checks_and_leaves_out_a_motion_its_images_do_not_explain():
    """RigStereo with a motion pitched 20 degrees off: too far for the refinement, which starts from the
    matches within 3 degrees of the odometry's epipolar curves (10 degrees off are found and corrected), so
    the pair is left out and named, and the rig pair alone answers."""
    camera = fisheye()
    cam_to_body = {"left": pose(-10, (-0.15, 0, 0)).numpy(), "right": pose(10, (0.15, 0, 0)).numpy()}
    rig = RigStereo({n: camera for n in cam_to_body}, cam_to_body, SETTINGS)
    body = [pose(0, (0.0, 0.0, 0.0)), pose(0, (0.2, 0.0, 0.3))]
    images = [{n: shot(camera, P @ torch.from_numpy(E))[0] for n, E in cam_to_body.items()} for P in body]
    rig(images[0])
    pitch = axis_angle_to_matrix(torch.tensor([math.radians(20.0), 0.0, 0.0], dtype=torch.float64))
    wrong = (
        make_pose(pitch, torch.zeros(3, dtype=torch.float64)).numpy()
        @ (invert_pose(body[0]) @ body[1]).numpy()
    )
    out = rig(images[1], previous=images[0], motion=wrong)
    assert out["left"].partners == ("right",) and "left@previous" in out["left"].left_out
    assert "agree with the starting pose within 3.0 degrees" in out["left"].left_out["left@previous"]
    assert out["left"].checks["left@previous"]["left_out"] == out["left"].left_out["left@previous"]


# ------------------------------------------------------------------ pixels that do not move
def test_a_constant_border_is_found_and_never_matched():
    """Every image of a turning camera has a white border 14 px wide (a burnt-in frame): it sits still
    while the scene moves, and matched at no parallax it reads as "too far". The static finder finds it
    from the images themselves (and nothing of the scene), and the live rig then keeps nothing there."""
    camera = fisheye()
    cam_to_body = {"cam": np.eye(4)}
    body = [pose(12 * i, (0.25 * i, 0.0, 0.1 * i)) for i in range(4)]

    def framed(P):
        image, truth = shot(camera, P)
        image[:, :14] = 255
        return image, truth

    shots = [framed(P) for P in body]
    finder = StaticFinder(camera, SETTINGS.max_distance)
    for i in range(3):
        finder.add(shots[i][0], shots[i + 1][0], (invert_pose(body[i + 1]) @ body[i]).numpy())
    border = np.zeros((192, 192), bool)
    border[:, :14] = True
    seen = shots[0][1] > 0
    found = finder.mask
    widened = np.zeros_like(border)
    widened[:, : 14 + 4] = True
    assert not (found & ~widened & seen).any()  # nothing of the scene, beyond the widening
    edge = np.zeros_like(border)
    edge[:, 10:18] = True  # the border's inner edge, where a matching window has contrast
    assert (found & edge & seen).sum() > 0.5 * (edge & seen).sum()

    rig = RigStereo({"cam": camera}, cam_to_body, SETTINGS)
    rig({"cam": shots[0][0]})
    for i in range(1, 4):
        out = rig({"cam": shots[i][0]}, previous={"cam": shots[i - 1][0]},
                  motion=(invert_pose(body[i - 1]) @ body[i]).numpy())  # fmt: skip
    distance, truth = out["cam"].fused.distance, shots[3][1]
    assert rig.static["cam"].mask[:, 12:16].mean() > 0.3
    assert not (distance[:, :14] > 0).any() and (distance > 0).mean() > 0.05
    beside = np.zeros_like(border)
    beside[:, 14:24] = True  # where the border's edge would read as "too far"
    assert (errors(np.where(beside, distance, 0), truth) < 0.25).all()
    assert np.median(errors(distance, truth)) < 0.03


# ------------------------------------------------------------------ a refinement that cannot make a rig worse
def test_a_thin_overlap_strip_does_not_turn_a_correct_rig():
    """Two 320x240 pinholes turned 56 degrees apart overlap in a strip 16 degrees wide: their stored
    extrinsics are right, a fit to the strip's matches finds a small turn, and the guard does not apply
    it (it is not bounded by the matches, or the held-out matches are not explained better)."""
    camera = PinholeCamera(width=320, height=240, fx=220.0, fy=220.0, cx=159.5, cy=119.5)
    E_a, E_b = pose(-28, (-0.15, 0, 0)), pose(28, (0.15, 0, 0))
    per_instant = []
    for i in range(3):
        P = pose(0, (0.0, 0.0, 0.3 * i))
        per_instant.append(match_features(shot(camera, P @ E_a)[0], camera, shot(camera, P @ E_b)[0], camera))
    T = (invert_pose(E_b) @ E_a).numpy()
    verdict = guarded_refinement(per_instant, torch.from_numpy(T), 220.0, direction=False)
    assert verdict["matches"] > 30 and not verdict["applied"] and verdict["why"], verdict
    assert np.allclose(verdict["T_a_to_b"].numpy(), T)
    tilt = axis_angle_to_matrix(torch.tensor([math.radians(1.5), 0.0, 0.0], dtype=torch.float64))
    turned = make_pose(tilt, torch.zeros(3, dtype=torch.float64)).numpy() @ T  # 1.5 degrees off: corrected
    verdict = guarded_refinement(per_instant, torch.from_numpy(turned), 220.0, direction=False)
    R_error = verdict["T_a_to_b"].numpy()[:3, :3] @ T[:3, :3].T
    assert verdict["applied"] and math.degrees(math.acos(min(1.0, (np.trace(R_error) - 1) / 2))) < 0.5


# ------------------------------------------------------------------ a search range from geometry
def test_a_long_motion_pair_searches_the_triangulation_angle_a_matcher_can_match():
    """A car's 1.3 m motion pair from 0.3 m on would search 77 degrees of parallax at its cameras' step
    (grids of 6862x4042 were refused): the range stops at the triangulation angle a window matcher can
    still match across, the step is coarsened so the search fits, and the pair is matched."""
    settings = SgbmSettings(min_distance=0.3, max_distance=80.0)
    car = PinholeCamera(width=968, height=608, fx=1060.0, fy=1060.0, cx=483.5, cy=303.5)
    nearest, step = pair_range(car, car, 1.3, settings)
    assert nearest == pytest.approx(1.3 / math.sin(math.radians(MAX_TRIANGULATION_DEG)))
    assert step == pytest.approx(math.radians(MAX_TRIANGULATION_DEG) / settings.max_disparities)
    assert step > 1 / 1060.0  # coarser than the camera's own: 30 degrees at its own step are 555 pixels
    camera = PinholeCamera(width=320, height=200, fx=260.0, fy=260.0, cx=159.5, cy=99.5)
    assert pair_range(camera, camera, 0.1, settings) == (settings.min_distance, 1 / 260.0)  # short: as is
    assert pair_range(camera, camera, 1.3, settings)[1] == 1 / 260.0  # 30 degrees are 136 of its pixels
    now, then = pose(0, (0.0, 0.0, 1.3)), pose(0, (0.0, 0.0, 0.0))  # forward: the epipole in view
    maps, truth = pair_maps(camera, camera, now, then, settings=settings)
    rect = rectify_pair(camera, camera, (invert_pose(then) @ now).numpy(), settings)
    assert rect.disparities <= settings.max_disparities + 16 and rect.grid.rows * rect.grid.cols < 2e6
    assert (maps.distance > 0).mean() > 0.1 and np.median(errors(maps.distance, truth)) < 0.05


# ------------------------------------------------------------------ pairs the images contradict
def noise(a, b):
    rng = np.random.default_rng(3)
    return rng.integers(0, 256, a.shape, np.uint8), rng.integers(0, 256, b.shape, np.uint8)


def another_scene(a, b):
    return a, shot(fisheye(), pose(40, (0.5, 0.2, 1.0)), seed=7)[0]


def same_stream(a, b):
    return a, a.copy()


LEFT, RIGHT = pose(-10, (-0.1, 0, 0)), pose(10, (0.1, 0, 0))


def focal_off(camera: CameraModel, factor: float) -> CameraModel:
    model = camera.to_dict()
    for key in ("gamma1", "gamma2"):
        model[key] *= factor
    return CameraModel.from_dict(model)


CONTRADICTIONS = {  # name: (images, the pose claimed a -> b, the partner's claimed camera)
    "independent noise": (noise, None, None),
    "the partner shows another scene": (another_scene, None, None),
    "the same stream in both cameras": (same_stream, None, None),
    "left and right swapped": (None, (invert_pose(LEFT) @ RIGHT).numpy(), None),
    "extrinsics given body -> camera": (None, (RIGHT @ invert_pose(LEFT)).numpy(), None),
    "the partner's focal 10 % off": (None, None, 1.1),
    "the motion inverted": ("motion", None, None),
}


@pytest.mark.parametrize("case", list(CONTRADICTIONS))
def test_a_pair_whose_images_contradict_its_geometry_keeps_no_pixel(case):
    """Each contradiction a new user makes (images, calibration or motion that do not belong together):
    the pair keeps no pixel, and its evidence says why (its matches off their epipolar rows, or its
    round trip failing), where a right pair keeps half its pixels within a few percent."""
    images, T_claimed, focal = CONTRADICTIONS[case]
    camera = fisheye()
    claimed = focal_off(camera, focal) if focal else None
    if images == "motion":  # now -> then given as then -> now
        now, then = pose(5, (0.3, 0.0, 0.1)), pose(0, (0.0, 0.0, 0.0))
        maps, _ = pair_maps(camera, camera, now, then, T_claimed=(invert_pose(now) @ then).numpy())
    else:
        maps, _ = pair_maps(
            camera, camera, LEFT, RIGHT, T_claimed=T_claimed, images=images, claimed_b=claimed
        )
    assert not maps.distance.any() and not maps.dense.any()
    record = maps.evidence.record()
    assert record["contradicted"] and ("epipolar rows" in record["contradicted"] or
                                       "round trip" in record["contradicted"]), record  # fmt: skip
    right, truth = pair_maps(camera, camera, LEFT, RIGHT)
    assert right.evidence.contradicted is None and right.evidence.rows_median_px < 0.3
    assert (right.distance > 0).mean() > 0.4 and np.median(errors(right.distance, truth)) < 0.03


def test_odometry_ten_times_too_long_is_named_not_fused_over_a_correct_rig():
    """The live rig with odometry ten times too long: its epipolar geometry is right (the direction is),
    so only the rig's other pairs can tell; the camera's motion partner and its rig partner disagree by
    a factor of ten on every pixel both keep, and neither is fused: named, with the factor."""
    camera = fisheye()
    cam_to_body = {"left": pose(-10, (-0.15, 0, 0)).numpy(), "right": pose(10, (0.15, 0, 0)).numpy()}
    rig = RigStereo({n: camera for n in cam_to_body}, cam_to_body, SETTINGS)
    body = [pose(0, (0.0, 0.0, 0.0)), pose(0, (0.03, 0.0, 0.045))]
    images = [{n: shot(camera, P @ torch.from_numpy(E))[0] for n, E in cam_to_body.items()} for P in body]
    rig(images[0])
    motion = (invert_pose(body[0]) @ body[1]).numpy()
    motion[:3, 3] *= 10
    out = rig(images[1], previous=images[0], motion=motion)
    left = out["left"]
    assert set(left.left_out) == {"right", "left@previous"} and left.partners == ()
    assert "x0.1" in left.left_out["right"] or "x10" in left.left_out["right"], left.left_out
    assert not left.fused.distance.any()


# ------------------------------------------------------------------ a confidence that means something
def test_confidence_orders_the_error():
    """A camera in the room with a rig partner and two motion partners: the kept pixels' abs_rel by
    confidence tercile falls as confidence rises."""
    camera = fisheye()
    centre = pose(0, (0.0, 0.0, 0.3))
    truth = shot(camera, centre)[1]
    maps = [pair_maps(camera, camera, centre, P)[0] for P in (pose(0, (0.3, 0, 0.3)), pose(8, (0.0, 0, 0.0)),
                                                                  pose(-8, (0.1, 0.1, 0.7)))]  # fmt: skip
    fused = fuse(maps)
    kept = (fused.distance > 0) & (truth > 0)
    error = np.abs(fused.distance[kept] / truth[kept] - 1)
    confidence = fused.confidence[kept]
    edges = np.quantile(confidence, [0, 1 / 3, 2 / 3, 1])
    by_tercile = [
        error[(confidence >= lo) & (confidence <= hi)].mean()
        for lo, hi in zip(edges, edges[1:], strict=False)
    ]
    assert by_tercile[0] > by_tercile[1] > by_tercile[2], by_tercile
