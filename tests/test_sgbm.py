"""The rectified SGBM pipeline (fisheyedepth.stereo: rectify, match, fill, map back, fuse; RigStereo):
the spherical rectification's geometry to exact numbers for cameras of several models beyond 90 degrees
of incidence, each step's rules on hand-made arrays, and metric distance from a fisheye pair, a pinhole
pair (beside OpenCV's StereoSGBM alone) and a live rig in a textured room with exact ground truth; then
real photographs."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from fisheyedepth.cameras import PinholeCamera
from fisheyedepth.cameras.rays import compute_rays
from fisheyedepth.geometry.se3 import invert_pose
from fisheyedepth.stereo import RigStereo, SgbmParameters, SgbmSettings, fuse, match_pair
from fisheyedepth.stereo.fill import fill, fill_rows, matchable
from fisheyedepth.stereo.mapback import PixelMaps, sample
from fisheyedepth.stereo.match import INVALID, despeckle, match, match_both, normalise
from fisheyedepth.stereo.pipeline import grey as grey_image
from fisheyedepth.stereo.rectify import build_rectification, nearest_parallax, remap
from stereo_world import pair, pose, render, texture_volume

from conftest import aria_fisheye624, kitti02, realdata_dir

# ------------------------------------------------------------------ the rectification's geometry
NARROW = PinholeCamera(width=160, height=120, fx=150.0, fy=150.0, cx=79.5, cy=59.5)  # 34 degrees to a corner
PAIRS = {
    # two fisheyes side by side, turned 20 degrees apart: a rig pair
    "rig_pair": lambda: (kitti02().resize(160, 160), kitti02().resize(160, 160), pose(-10, (-0.15, 0, 0)),
                         pose(10, (0.15, 0, 0))),
    # one fisheye moving 1 m along its axis: the epipole in the image, every row through it
    "forward_motion": lambda: (kitti02().resize(160, 160), kitti02().resize(160, 160), pose(),
                               pose(0, (0, 0, 1.0))),
    # two models, the second turned 80 degrees away and 0.1 m up: overlap only at high incidence
    "two_models": lambda: (kitti02().resize(160, 160), aria_fisheye624().resize(180, 180), pose(),
                           pose(80, (0.3, -0.1, 0))),
    # a narrow pinhole moving 1 m along its axis: a whole circle of rows, coarser than its columns
    "narrow_forward": lambda: (NARROW, NARROW, pose(), pose(0, (0, 0, 1.0))),
}  # fmt: skip


def seen_points(camera_a, camera_b, T_a_to_b, n=4000, seed=0):
    """Points 1-10 m from camera a, in every direction a sees, that b sees too."""
    g = torch.Generator().manual_seed(seed)
    rays, has_ray = compute_rays(camera_a, dtype=torch.float64)
    rays = rays[has_ray]
    pick = rays[torch.randint(len(rays), (n,), generator=g)]
    points = pick * (1 + 9 * torch.rand(n, 1, generator=g, dtype=torch.float64))
    in_b = points @ T_a_to_b[:3, :3].T + T_a_to_b[:3, 3]
    uv, ok = camera_b.project(in_b)
    ok &= (uv[:, 0] > 0) & (uv[:, 0] < camera_b.width - 1) & (uv[:, 1] > 0) & (uv[:, 1] < camera_b.height - 1)
    return points[ok], in_b[ok]


@pytest.mark.parametrize("case", list(PAIRS))
def test_rows_are_epipolar_lines_and_the_law_of_sines_gives_distance(case):
    camera_a, camera_b, P_a, P_b = PAIRS[case]()
    T = invert_pose(P_b) @ P_a
    rect = build_rectification(camera_a, camera_b, T.numpy(), min_distance=0.5)
    points_a, points_b = seen_points(camera_a, camera_b, T)
    assert len(points_a) > 300
    ray_a = points_a / points_a.norm(dim=-1, keepdim=True)
    ray_b_in_a = (points_b / points_b.norm(dim=-1, keepdim=True)) @ T[:3, :3]  # b's ray, a's orientation
    grid_a, theta_a = rect.grid.pixels(ray_a)
    grid_b, theta_b = rect.grid.pixels(ray_b_in_a)
    assert (grid_a[:, 0] - grid_b[:, 0]).abs().max() < 1e-8  # one row: the same plane through the baseline
    disparity = grid_a[:, 1] - grid_b[:, 1]
    assert disparity.min() > 0  # b sees every point further from the baseline: a is the left image
    alpha = (disparity * rect.grid.step).numpy()
    from_a = rect.distance("a", theta_a.numpy(), alpha)
    from_b = rect.distance("b", theta_b.numpy(), alpha)
    assert np.allclose(from_a, points_a.norm(dim=-1).numpy(), rtol=1e-9)
    assert np.allclose(from_b, points_b.norm(dim=-1).numpy(), rtol=1e-9)
    if case not in ("two_models", "narrow_forward"):
        incidence = torch.rad2deg(torch.acos(ray_a[:, 2]))
        assert (incidence > 90).sum() > 20  # rays beyond 90 degrees are rectified like the rest


@pytest.mark.parametrize("case", list(PAIRS))
def test_the_grid_answers_every_point_both_cameras_see(case):
    """Every point 0.5-10 m from a that b sees lies inside the grid, at least the disparity range from
    its left edge (SGBM answers no column before it), its partner inside the range."""
    camera_a, camera_b, P_a, P_b = PAIRS[case]()
    T = invert_pose(P_b) @ P_a
    rect = build_rectification(camera_a, camera_b, T.numpy(), min_distance=0.5)
    points_a, points_b = seen_points(camera_a, camera_b, T, seed=1)
    grid_a, _ = rect.grid.pixels(points_a / points_a.norm(dim=-1, keepdim=True))
    grid_b, _ = rect.grid.pixels((points_b / points_b.norm(dim=-1, keepdim=True)) @ T[:3, :3])
    rows, cols, last = rect.grid.rows, rect.grid.cols, rect.first_disparity + rect.disparities - 1
    assert grid_a[:, 0].min() >= -0.5 and grid_a[:, 0].max() <= rows - 0.5
    assert grid_a[:, 1].min() >= last and grid_b[:, 1].max() <= cols - 1 - last
    assert (grid_a[:, 1] - grid_b[:, 1]).max() < last  # every parallax inside the range
    assert rect.a.inside.mean() > 0.3  # a's pixels that have a grid row
    # the remap tables are the cameras' projections of the grid's directions
    directions = rect.grid.directions()
    uv, _ = camera_a.project(directions)
    valid = torch.from_numpy(rect.a.valid)
    assert np.allclose(rect.a.map_x[rect.a.valid], uv[..., 0][valid].float().numpy(), atol=1e-3)


def test_the_disparity_range_runs_from_the_farthest_parallax_to_the_nearest():
    step = math.radians(0.25)
    assert nearest_parallax(0.14, 0.2, step) == math.ceil(math.degrees(math.asin(0.7)) / 0.25)
    assert nearest_parallax(2.6, 0.5, step) == 360  # a baseline longer than the nearest distance: 90 degrees
    # a narrow pinhole pair looking across its baseline: no epipole in view, the range starts above 0
    pinhole = PinholeCamera(width=200, height=150, fx=400.0, fy=400.0, cx=99.5, cy=74.5)
    T = (invert_pose(pose(0, (0.2, 0, 0))) @ pose()).numpy()
    rect = build_rectification(pinhole, pinhole, T, 1.5, directions=(True, False), max_distance=10.0)
    far = 0.2 * math.cos(math.radians(14.1)) / 10 * 400  # the image's edge, 14 degrees off the axis, 10 m on
    assert rect.first_disparity == pytest.approx(far - 2, abs=1.5)
    near = nearest_parallax(0.2, 1.5, rect.grid.step)
    assert rect.first_disparity + rect.disparities > near and rect.disparities % 16 == 0
    assert rect.first_disparity + rect.disparities <= near + 17
    # a fisheye moving along its axis sees its epipole: every parallax down to 0 is possible
    camera = kitti02().resize(96, 96)
    ahead = build_rectification(camera, camera, (invert_pose(pose(0, (0, 0, 1.0))) @ pose()).numpy(), 0.5,
                                max_distance=80.0)  # fmt: skip
    assert ahead.first_disparity == 0


def test_a_forward_pair_searches_what_its_view_can_show_on_rows_as_fine_as_its_columns():
    """A narrow camera moving 1.3 m along its axis, from 2.6 m on (a car's front camera): no ray runs
    across the baseline, so a point 2.6 m away shows at most the parallax at the image's corner (11
    degrees, not the 30 of asin(L / D)), and the rows around the epipole need be no finer on the sphere
    than the columns at that corner."""
    T = (invert_pose(pose(0, (0, 0, -1.3))) @ pose()).numpy()  # now -> then: then lies 1.3 m behind
    step = math.radians(0.5)
    rect = build_rectification(NARROW, NARROW, T, 2.6, step, directions=(True, True), max_distance=50.0,
                               asked=(True, False))  # fmt: skip
    corner = math.atan(math.hypot(80, 60) / 150)  # radians off the axis
    D, L = 2.6, 1.3
    from_b = math.atan2(D * math.sin(corner), D * math.cos(corner) + L)  # the corner's point, seen from b
    largest = (corner - from_b) / step
    assert math.degrees(corner - from_b) == pytest.approx(11.1, abs=0.1)
    assert largest <= rect.first_disparity + rect.disparities - 1 - 2  # inside the range, end margin off
    assert rect.disparities <= 16 * math.ceil((largest + 4) / 16)  # and no more than that
    assert rect.disparities < nearest_parallax(L, D, step)
    assert rect.grid.phi_step == pytest.approx(step / math.sin(corner), rel=0.05)
    assert rect.grid.rows < 2 * math.pi / step * 0.6
    scale = rect.grid.row_scale()  # a row step on the sphere, in column steps: at most one
    psi = rect.grid.psi0 + step * np.arange(rect.grid.cols)
    assert scale[psi <= corner].max() == pytest.approx(1.0, abs=0.05)
    # b asked too: its pixels see points 2.6 m from b, 1.3 m nearer a: the range reaches further
    both = build_rectification(NARROW, NARROW, T, 2.6, step, max_distance=50.0)
    assert both.disparities > rect.disparities


def test_each_direction_is_matched_over_its_own_span_of_columns():
    """A grid answering both cameras is padded on each side for one of them, where the other sees
    nothing: each direction matched over its own span (up to the last column a sees, from the first b
    sees) gives what the whole grid gives."""
    camera = PinholeCamera(width=160, height=120, fx=110.0, fy=110.0, cx=79.5, cy=59.5)
    T_a, T_b = pose(-15, (-0.15, 0, 0)), pose(15, (0.15, 0, 0))
    rect = build_rectification(camera, camera, (invert_pose(T_b) @ T_a).numpy(), 0.5, max_distance=20.0)
    (a0, a1), (b0, b1) = rect.spans
    pad = rect.first_disparity + rect.disparities
    assert a0 == 0 and b1 == rect.grid.cols and a1 < rect.grid.cols - pad // 2 and b0 > pad // 2
    assert not rect.a.valid[:, a1:].any() and not rect.b.valid[:, :b0].any()
    volume = texture_volume(3)
    a, b = (remap(grey_image(render(camera, P, volume)[0]), side)
            for P, side in ((T_a, rect.a), (T_b, rect.b)))  # fmt: skip
    both = [match_both(a, b, rect.a.valid, rect.b.valid, rect.disparities, rect.grid.step, SgbmParameters(),
                       first=rect.first_disparity, spans=spans) for spans in (rect.spans, None)]  # fmt: skip
    for spanned, whole in ((both[0].a, both[1].a), (both[0].b, both[1].b)):
        spanned, whole = spanned.checked, whole.checked
        kept = whole != INVALID
        assert kept.mean() > 0.15
        assert (np.abs(spanned - whole) < 0.25)[kept].mean() > 0.99
        assert ((spanned != INVALID) & ~kept).sum() < 0.01 * kept.sum()


def test_a_pair_without_baseline_or_overlap_is_refused():
    camera = kitti02().resize(96, 96)
    with pytest.raises(ValueError, match="T_a_to_b: the two camera centres coincide"):
        build_rectification(camera, camera, pose(30).numpy(), 0.5)
    pinhole = PinholeCamera(width=64, height=64, fx=60.0, fy=60.0, cx=31.5, cy=31.5)
    back_to_back = (invert_pose(pose(180, (0, 0, -0.2))) @ pose()).numpy()
    with pytest.raises(ValueError, match="no ray of one is seen by the other"):
        build_rectification(pinhole, pinhole, back_to_back, 0.5)


# ------------------------------------------------------------------ each step's rules
def test_normalisation_removes_gain_and_offset():
    rng = np.random.default_rng(0)
    image = rng.uniform(20, 120, (40, 50)).astype(np.float32)
    seen = np.ones_like(image, bool)
    seen[:, :5] = False
    a, b = normalise(image, seen, 7), normalise(2.5 * image + 40, seen, 7)
    assert np.abs(a.astype(int) - b.astype(int)).max() <= 1
    assert (a[:, :5] == 0).all() and (a[:, 5:] > 0).all()  # 0: not seen


def test_matching_recovers_a_shift_and_rejects_what_it_cannot_see():
    rng = np.random.default_rng(1)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (80, 300)).astype(np.float32), (3, 3), 0)
    left, right = texture[:, 40:240], texture[:, 52:252]  # a point at column x in left is at x - 12 in right
    seen = np.ones(left.shape, bool)
    step = math.radians(0.25)
    found = match(left, right, seen, seen, 64, step, SgbmParameters())
    inner = found.checked[:, 70:-10]  # left of column 64 + a block SGBM answers nothing
    assert (inner != INVALID).mean() > 0.9
    assert np.abs(inner[inner != INVALID] - 12).max() < 0.25
    # the right camera blind in a band: the left pixels whose match lies there are rejected
    blind = seen.copy()
    blind[:, 100:140] = False
    found = match(left, right, seen, blind, 64, step, SgbmParameters())
    rows, cols = np.nonzero(found.matched != INVALID)
    partner = np.round(cols - found.matched[rows, cols]).astype(int)
    assert len(rows) > 1000 and not ((partner >= 100) & (partner < 140)).any()
    # a parallax beyond the range: winners at its end are rejected, not kept
    found = match(left, texture[:, 80:280], seen, seen, 32, step, SgbmParameters())  # disparity 40
    assert (found.matched[found.matched != INVALID] < 31).all()


def test_a_speckle_is_a_solid_angle():
    disparity = np.full((60, 60), 10.0, np.float32)
    disparity[20:25, 20:25] = 30.0  # a 25-pixel island
    settings = SgbmParameters(speckle_deg2=0.01 * 100)  # 100 pixels of 0.1 degrees
    assert settings.speckle_pixels(math.radians(0.1)) == 100
    assert settings.speckle_pixels(math.radians(0.05)) == 400
    kept = despeckle(disparity, settings.speckle_pixels(math.radians(0.1)), 2.0)
    assert (kept[20:25, 20:25] == INVALID).all() and (kept[30:] == 10.0).all()
    assert (despeckle(disparity, 20, 2.0) == disparity).all()  # larger than a speckle of 20 pixels


def test_filling_takes_the_background_across_an_edge_and_interpolates_between_equals():
    I = INVALID  # noqa: N806
    rows = np.array(
        [
            [5, I, I, I, 9, 9],  # an edge: the occluded pixels take the background (5)
            [5, I, I, I, 5.4, 6],  # equal ends: a surface between them
            [I, I, 7, 7, I, I],  # one side only: that side
            [I, I, I, I, I, I],  # nothing to fill from
        ],
        np.float32,
    )
    everywhere = np.ones(rows.shape, bool)
    filled = fill_rows(rows, everywhere, min_jump=1.0)
    assert filled[0].tolist() == [5, 5, 5, 5, 9, 9]
    assert np.allclose(filled[1], [5, 5.1, 5.2, 5.3, 5.4, 6])
    assert filled[2].tolist() == [7, 7, 7, 7, 7, 7] and (filled[3] == I).all()
    nowhere = fill_rows(rows, np.zeros(rows.shape, bool))
    assert (nowhere == rows).all()  # only where a partner could match
    rim = np.full((1, 40), I, np.float32)
    rim[0, 30:] = 8.0  # a kept stretch at the rim of the partner's view, nothing to its left
    reached = fill_rows(rim, np.ones(rim.shape, bool), reach=10)
    assert (reached[0, 20:] == 8.0).all() and (reached[0, :20] == I).all()  # ten pixels out, no farther
    smoothed = fill(rows, everywhere, smooth=3)
    assert (smoothed[rows != I] == rows[rows != I]).all()  # measured pixels keep their measurement


def test_matchable_pixels_have_a_partner_within_the_range():
    seen = np.ones((2, 30), bool)
    partner = np.zeros((2, 30), bool)
    partner[:, 10:12] = True
    left = matchable(seen, partner, 5, partner_left=True)  # a's partner lies at column - d, d in [0, 4]
    assert np.nonzero(left[0])[0].tolist() == list(range(10, 16))
    right = matchable(seen, partner, 5, partner_left=False)
    assert np.nonzero(right[0])[0].tolist() == list(range(6, 12))
    later = matchable(seen, partner, 5, partner_left=True, first=3)  # d in [3, 7]
    assert np.nonzero(later[0])[0].tolist() == list(range(13, 19))


def test_map_back_interpolates_a_surface_and_not_an_edge():
    camera = kitti02().resize(96, 96)
    rect = build_rectification(camera, camera, (invert_pose(pose(0, (0.2, 0, 0))) @ pose()).numpy(), 0.5)
    rows, cols = rect.grid.rows, rect.grid.cols
    plane = (5 + 0.01 * np.arange(cols)[None] + 0.02 * np.arange(rows)[:, None]).astype(np.float32)
    at = sample(plane, rect.a)
    r, c = rect.a.grid_row, rect.a.grid_col
    inside = at != INVALID
    assert inside.mean() > 0.5
    assert np.allclose(at[inside], (5 + 0.01 * c + 0.02 * r)[inside], atol=1e-4)  # bilinear on a plane
    step = np.where(np.arange(cols)[None] < cols // 2, 5.0, 20.0).astype(np.float32).repeat(rows, 0)
    values = sample(step, rect.a)
    assert set(np.unique(values[values != INVALID])) <= {5.0, 20.0}  # the nearest across the edge


def fused_maps(distance, parallax, step=0.01, roundtrip=0.0, residual=0.0, shape=(1, 3)):
    d = np.full(shape, distance, np.float32)
    angle = np.full(shape, parallax, np.float32)
    return PixelMaps(d, d, angle, angle, step, np.full(shape, roundtrip, np.float32), residual)


def test_fusion_by_evidence():
    """Partners that agree within their expected error are averaged by precision; a disagreement is
    settled by a majority or by an estimate three times more precise, never by the larger parallax alone
    (a longer baseline with a worse pose counts for less); otherwise the pixel is dropped; an estimate no
    partner corroborates needs to resolve its distance to an eighth."""
    maps = fused_maps
    agreeing = fuse([maps(10.0, 0.1), maps(10.4, 0.1)])  # sigma 0.1 each: log ratio 0.039 within 0.28
    assert np.allclose(agreeing.distance, 10.2) and (agreeing.agreeing == 2).all()
    alone = fuse([maps(10.0, 0.1)])  # sigma 0.1 <= 1/8: kept, half as sure as two that agree
    assert (agreeing.confidence > alone.confidence).all()
    assert np.allclose(alone.confidence, 0.5 / (1 + 0.1 / 0.05))
    assert not fuse([maps(10.0, 0.07)]).distance.any()  # sigma 0.14: a lone estimate it cannot resolve
    assert not fuse([maps(10.0, 0.1, roundtrip=0.5)]).distance.any()  # the round trip's miss counts too
    torn = fuse([maps(10.0, 0.1), maps(20.0, 0.2)])  # one against one, sigma 0.1 and 0.05: dropped
    assert not torn.distance.any() and not torn.dense.any()
    clear = fuse([maps(10.0, 0.1), maps(20.0, 0.4)])  # sigma 0.025 is four times 0.1's precision: it wins
    assert np.allclose(clear.distance, 20.0) and (clear.agreeing == 1).all()
    # the larger parallax with a pose its images leave 3 px unexplained: sigma 4 x 0.025 = 0.1, a tie
    posed = fuse([maps(10.0, 0.1), maps(20.0, 0.4, residual=3.0)])
    assert not posed.distance.any()
    majority = fuse([maps(10.0, 0.1), maps(20.0, 0.2), maps(20.4, 0.2)])
    assert np.allclose(majority.distance, 20.2) and (majority.agreeing == 2).all()
    assert np.allclose(majority.confidence, 0.75 * (2 / 3) / (1 + 0.05 / np.sqrt(2) / 0.05), atol=1e-6)
    with pytest.raises(ValueError, match="maps: nothing to fuse"):
        fuse([])


def test_partners_that_disagree_as_wholes_are_named_and_left_out():
    """Odometry ten times too long against a correct rig pair: neither can be told right from the pair
    alone, so both are left out and named; a third partner that agrees with the rig settles it."""
    shape = (40, 40)
    rig, moved = fused_maps(10.0, 0.2, shape=shape), fused_maps(100.0, 0.2, shape=shape)
    other_rig = fused_maps(10.2, 0.2, shape=shape)
    two = fuse([rig, moved])
    assert set(two.left_out) == {0, 1} and "x10" in two.left_out[1] and not two.distance.any()
    three = fuse([rig, moved, other_rig])
    assert set(three.left_out) == {1} and "partner 0: x10" in three.left_out[1]
    assert np.allclose(three.distance, 10.1, rtol=1e-3) and (three.agreeing == 2).all()


# ------------------------------------------------------------------ metric distance, end to end
def grey(view) -> np.ndarray:
    return (view.image[0].mean(0).numpy() * 255).astype(np.float32)


def test_a_fisheye_pair_comes_back_within_one_percent():
    """Two 512 px KITTI-360 fisheyes 0.4 m apart in the textured room (every wall textured): the median
    error of the checked distance under 1 %, on nearly every pixel both see."""
    camera = kitti02().resize(512, 512)
    reference, source, truth = pair(camera, camera, pose(0, (-0.2, 0, 0)), pose(0, (0.2, 0, 0)))
    rect = build_rectification(camera, camera, source.T_ref_to_view.double().numpy(), 0.5)
    settings = SgbmSettings(min_distance=0.5, max_distance=20.0)
    maps, other = match_pair(grey(reference), grey(source), rect, settings)
    truth = truth[0].numpy()
    kept = (maps.distance > 0) & (truth > 0)
    error = np.abs(maps.distance[kept] / truth[kept] - 1)
    assert np.median(error) < 0.01 and kept.sum() > 0.9 * (maps.dense > 0).sum(), np.median(error)
    assert error.mean() < 0.025 and (maps.dense > 0).mean() > 0.7
    dense = (maps.dense > 0) & (truth > 0)
    assert np.abs(maps.dense[dense] / truth[dense] - 1).mean() < 0.05
    _, truth_b = render(camera, pose(0, (0.2, 0, 0)), texture_volume(0))  # b's image answered too
    kept_b = (other.distance > 0) & (truth_b[0].numpy() > 0)
    assert np.median(np.abs(other.distance[kept_b] / truth_b[0].numpy()[kept_b] - 1)) < 0.01


def test_a_pinhole_pair_gives_stereo_sgbms_own_answer():
    """A rectified pinhole pair: the pipeline (spherical grid, remap, SGBM, law of sines) against OpenCV's
    StereoSGBM alone on the same normalised images (z = f b / d). They agree to SGBM's own sub-pixel error
    (its pixel locking: 2 % at the 10 px of disparity of this room's far wall), and the pipeline's median
    error against the truth is no larger than SGBM's alone."""
    camera = PinholeCamera(width=320, height=240, fx=260.0, fy=260.0, cx=159.5, cy=119.5)
    reference, source, truth = pair(camera, camera, pose(0, (-0.1, 0, 0)), pose(0, (0.1, 0, 0)))
    settings = SgbmSettings(min_distance=0.8, max_distance=20.0)
    rect = build_rectification(camera, camera, source.T_ref_to_view.double().numpy(), 0.8)
    ours, _ = match_pair(grey(reference), grey(source), rect, settings, (True, False))
    m = settings.sgbm
    seen = np.ones((240, 320), bool)
    a, b = (normalise(grey(v), seen, m.normalise_window) for v in (reference, source))
    sgbm = m.create(rect.disparities)  # the pipeline's own settings
    d = sgbm.compute(a, b).astype(np.float32) / 16
    rays, _ = compute_rays(camera)
    theirs = np.where(d > 1, 260.0 * 0.2 / np.maximum(d, 1e-6), 0) / rays[..., 2].numpy()
    both = (theirs > 0) & (ours.distance > 0)
    assert both.mean() > 0.6
    difference = np.abs(ours.distance[both] / theirs[both] - 1)
    assert np.median(difference) < 0.025 and np.percentile(difference, 90) < 0.05
    truth = truth[0].numpy()
    errors = []
    for distance in (ours.distance, theirs):
        kept = (distance > 0) & (truth > 0)
        errors.append(np.median(np.abs(distance[kept] / truth[kept] - 1)))
    assert errors[0] <= errors[1] < 0.025, errors


def test_a_live_rig_gets_distance_for_every_camera():
    """RigStereo, one call per instant: two fisheyes that overlap and a pinhole looking back (no rig
    partner), then the next instant 0.3 m on with the odometry: each camera with its rig partner and its
    own previous image, fused; each partner's evidence (its motion checked against its images, the round
    trip, the row check) in the result."""
    fisheye = kitti02().resize(192, 192)
    back = PinholeCamera(width=160, height=120, fx=140.0, fy=140.0, cx=79.5, cy=59.5)
    cameras = {"left": fisheye, "right": fisheye, "back": back}
    cam_to_body = {
        "left": pose(-10, (-0.15, 0, 0)),
        "right": pose(10, (0.15, 0, 0)),
        "back": pose(180, (0, 0, -0.2)),
    }
    rig = RigStereo(cameras, {n: E.numpy() for n, E in cam_to_body.items()},
                    SgbmSettings(min_distance=0.5, max_distance=20.0), threads=2)  # fmt: skip
    assert set(rig.pairs) == {("left", "right")} and len(rig.unpaired) == 2
    body = [pose(0, (0.3 * i, 0, 0.3 * i)) for i in range(2)]  # forward and aside: the back camera's
    # own motion is not along its axis alone (there it would resolve little of the room)

    def shoot(P):
        return {n: render(cameras[n], P @ E, texture_volume(0)) for n, E in cam_to_body.items()}

    first, second = shoot(body[0]), shoot(body[1])
    images = [
        {n: (img[0, 0].numpy() * 255).astype(np.uint8) for n, (img, _) in s.items()} for s in (first, second)
    ]
    out = rig(images[0])
    assert set(out) == {"left", "right", "back"} and out["left"].partners == ("right",)
    assert out["back"].partners == () and not out["back"].fused.distance.any()  # no partner: nothing
    motion = (invert_pose(body[0]) @ body[1]).numpy()  # the body now, in the body then
    out = rig(images[1], previous=images[0], motion=motion)
    assert out["left"].partners == ("right", "left@previous") and out["back"].partners == ("back@previous",)
    for name, result in out.items():
        truth = second[name][1][0].numpy()
        kept = (result.fused.distance > 0) & (truth > 0)
        assert (
            kept.mean() > 0.3 and np.median(np.abs(result.fused.distance[kept] / truth[kept] - 1)) < 0.03
        ), name
    assert (out["left"].fused.agreeing.max()) == 2  # both partners agree somewhere
    checks = out["left"].checks
    assert checks["left@previous"]["epipolar_px_after"] < 0.2 and checks["left@previous"]["left_out"] is None
    assert checks["right"]["round_trip_closed"] > 0.7 and checks["right"]["row_offset_px"] < 0.3
    assert out["left"].left_out == {} and rig.timer.seconds["motion"] > 0
    assert rig.timer.seconds["match"] > 0
    with pytest.raises(ValueError, match="images: no image of camera back"):
        rig({"left": images[0]["left"], "right": images[0]["right"]})
    with pytest.raises(ValueError, match="previous, motion: give both"):
        rig(images[1], previous=images[0])
    with pytest.raises(
        ValueError, match=r"previous\['back'\]: shape \(60, 80\), but camera 'back' is 160x120"
    ):
        rig(images[1], previous={**images[0], "back": images[0]["back"][::2, ::2]}, motion=motion)
    with pytest.raises(ValueError, match="masks: 'top' is not a camera of the rig"):
        RigStereo(cameras, {n: E.numpy() for n, E in cam_to_body.items()}, masks={"top": np.ones((4, 4))})
    with pytest.raises(ValueError, match=r"threads: 0; a whole number from 1 to \d+ \(this machine"):
        RigStereo(cameras, {n: E.numpy() for n, E in cam_to_body.items()}, threads=0)


# ------------------------------------------------------------------ real photographs
def test_sift_matches_on_a_rectified_middlebury_pair_lie_on_one_row():
    pytest.importorskip("skimage")
    from fisheyedepth.realworld.pairs import motorcycle

    p = motorcycle()
    rect = build_rectification(p.camera, p.partner_camera, p.T.numpy(), 1.5)
    dy, dx = sift_rows(rect, p.image, p.partner_image)
    assert len(dy) > 500 and np.median(np.abs(dy)) < 0.2 and (dx > 0).mean() > 0.99


def sift_rows(rect, image_a, image_b, ratio: float = 0.75) -> tuple[np.ndarray, np.ndarray]:
    """Row and column differences of mutual SIFT matches between the two rectified images."""
    a, b = ((x[0].mean(0).numpy() * 255).astype(np.uint8) for x in (image_a, image_b))
    ra, rb = remap(a, rect.a), remap(b, rect.b)
    sift = cv2.SIFT_create()
    (ka, da), (kb, db) = (
        sift.detectAndCompute(x, s.valid.astype(np.uint8)) for x, s in ((ra, rect.a), (rb, rect.b))
    )
    matcher = cv2.BFMatcher()
    back = {m.queryIdx: m.trainIdx for (m,) in matcher.knnMatch(db, da, k=1)}
    good = [
        m
        for m, n in matcher.knnMatch(da, db, k=2)
        if m.distance < ratio * n.distance and back.get(m.trainIdx) == m.queryIdx
    ]
    pts = np.array([(ka[m.queryIdx].pt, kb[m.trainIdx].pt) for m in good]).reshape(-1, 2, 2)
    return pts[:, 0, 1] - pts[:, 1, 1], pts[:, 0, 0] - pts[:, 1, 0]


@pytest.fixture(scope="module")
def adt_refined():
    from fisheyedepth.realworld.stereo import refine_adt

    folder = realdata_dir() / "adt_slam"
    if not folder.is_dir():
        pytest.skip(f"real data not found at {folder} (set FISHEYEDEPTH_REALDATA)")
    return folder, refine_adt(folder)


@pytest.mark.realdata
def test_sift_matches_on_the_rectified_adt_pair_lie_on_one_row_once_refined(adt_refined):
    """The ADT SLAM pair rectified with its refined rotation: the mutual SIFT matches of its three
    instants that lie within 3 px of a row (the others are wrong matches, anywhere) lie within 0.25 px of
    it on the median; with the stored extrinsics, 1.8 px."""
    from fisheyedepth.realworld.pairs import adt_instants, adt_left_to_right, adt_pairs

    folder, (T, refinement) = adt_refined
    assert 0.5 < refinement["rotation_deg"] < 1.2
    first = adt_pairs(folder, T)[0]
    for pose_, bound in ((T, 0.25), (adt_left_to_right(folder), None)):
        rect = build_rectification(first.camera, first.partner_camera, pose_.numpy(), 0.2)
        dy = np.concatenate([sift_rows(rect, a, b)[0] for a, b in adt_instants(folder)])
        near = np.abs(dy[np.abs(dy) < 3])
        assert len(near) > 50
        if bound is None:
            assert np.median(near) > 1.2
        else:
            assert np.median(near) < bound


def test_the_readme_live_rig_example_runs():
    """README's live-rig snippet, run as written on two fisheyes in the textured room (named as it names
    them) and their previous instant."""
    import re
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = re.search(r"```python\n(.*?)```", readme, re.S).group(1)
    camera = kitti02().resize(160, 160)
    cam_to_body = {"front": pose(-10, (-0.15, 0, 0)).numpy(), "right": pose(10, (0.15, 0, 0)).numpy()}
    pose_then, pose_now = pose().numpy(), pose(0, (0, 0, 0.3)).numpy()

    def shoot(P):
        return {n: (render(camera, torch.from_numpy(P @ E), texture_volume(0))[0][0, 0].numpy() * 255)
                .astype(np.uint8) for n, E in cam_to_body.items()}  # fmt: skip

    scope = {"np": np, "cameras": {n: camera for n in cam_to_body}, "cam_to_body": cam_to_body,
             "images": shoot(pose_now), "last_images": shoot(pose_then), "pose_then": pose_then,
             "pose_now": pose_now}  # fmt: skip
    exec(block, scope)
    out = scope["out"]
    assert out["front"].partners == ("right", "front@previous")
    assert (out["front"].fused.distance > 0).mean() > 0.3
