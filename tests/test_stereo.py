"""Sweep stereo on the sphere (fisheyedepth.stereo): its costs, aggregation and refinement to exact numbers,
and metric distance from a fisheye rig, a moving fisheye camera and a rectified pinhole pair (beside
OpenCV's StereoSGBM) in a textured room with exact ground truth; a rig's rotation refined from its
images' feature matches; the command on a rig recording."""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F
import yaml

from fisheyedepth.cameras import PinholeCamera
from fisheyedepth.cameras.rays import compute_rays
from fisheyedepth.geometry.se3 import axis_angle_to_matrix, invert_pose, make_pose
from fisheyedepth.stereo import SweepStereo, View, aggregate, census, hamming, winner, zncc_cost
from fisheyedepth.stereo.refine import Matches, match_features, refine_relative_pose
from fisheyedepth.stereo.sweep import box_mean

from conftest import kitti02

ROOM = torch.tensor([[-4.0, -1.5, -3.0], [4.0, 1.5, 5.0]], dtype=torch.float64)  # metres, x right, y down


@functools.cache
def texture_volume(seed: int = 0, cell: float = 0.04) -> torch.Tensor:
    """A random texture over the room's volume (fine noise over coarse blotches), sampled where rays hit."""
    g = torch.Generator().manual_seed(seed)
    size = [int(n) for n in ((ROOM[1] - ROOM[0]) / cell).long().flip(0) + 2]
    fine = torch.rand(1, 1, *size, generator=g)
    coarse = torch.rand(1, 1, *[n // 4 + 2 for n in size], generator=g)
    return 0.6 * fine + 0.4 * F.interpolate(coarse, size=size, mode="trilinear", align_corners=True)


def render(camera, T_cam_to_world: torch.Tensor, volume: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``[1, 1, H, W]`` image and ``[1, H, W]`` exact distance (0 without a ray) of ``camera`` inside the
    room: each ray's first hit of the box's walls."""
    rays, valid = compute_rays(camera, dtype=torch.float64)
    R, t = T_cam_to_world[:3, :3], T_cam_to_world[:3, 3]
    d = rays @ R.T
    hits = []
    for axis in range(3):
        component = torch.where(
            d[..., axis].abs() > 1e-12, d[..., axis], torch.full_like(d[..., axis], 1e-12)
        )
        for bound in ROOM[:, axis]:
            s = (bound - t[axis]) / component
            hits.append(torch.where(s > 0, s, torch.full_like(s, math.inf)))
    distance = torch.stack(hits).amin(0)
    where = ((t + d * distance[..., None]) - ROOM[0]) / (ROOM[1] - ROOM[0]) * 2 - 1
    value = F.grid_sample(volume, where[None, None].float(), mode="bilinear", align_corners=True)[0, 0, 0]
    image = torch.where(valid, value, torch.zeros_like(value))
    return image[None, None].float(), torch.where(valid, distance, torch.zeros_like(distance))[None].float()


def pose(yaw_deg: float = 0.0, t=(0.0, 0.0, 0.0)) -> torch.Tensor:
    R = axis_angle_to_matrix(torch.tensor([0.0, math.radians(yaw_deg), 0.0], dtype=torch.float64))
    return make_pose(R, torch.tensor(t, dtype=torch.float64))


def scores(
    distance: torch.Tensor, truth: torch.Tensor, among: torch.Tensor | None = None
) -> dict[str, float]:
    among = (truth > 0) if among is None else among & (truth > 0)
    kept = among & (distance > 0)
    ratio = distance[kept] / truth[kept]
    return {
        "abs_rel": float((ratio - 1).abs().mean()),
        "a1": float((torch.maximum(ratio, 1 / ratio) < 1.25).float().mean()),
        "coverage": float(kept.sum() / among.sum()),
    }


def pair(camera_a, camera_b, T_a, T_b, seed: int = 0):
    volume = texture_volume(seed)
    image_a, truth_a = render(camera_a, T_a, volume)
    image_b, _ = render(camera_b, T_b, volume)
    T_ab = (invert_pose(T_b) @ T_a).float()
    return View(image_a, camera_a, torch.eye(4)), View(image_b, camera_b, T_ab), truth_a


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
    one, seen_one = SweepStereo(hypotheses=10, chunk=1).cost_volume(reference, [source])
    many, seen_many = SweepStereo(hypotheses=10, chunk=4).cost_volume(reference, [source])
    assert torch.equal(one, many) and torch.equal(seen_one, seen_many)


def test_census_counts_the_neighbours_that_change_order():
    a = torch.arange(25.0).reshape(1, 1, 5, 5)  # strictly increasing in reading order
    bits = census(a, 3)
    assert bits.shape == (1, 8, 5, 5)
    # the centre pixel: the 4 neighbours after it in reading order are brighter, the 4 before are not
    assert bits[0, :, 2, 2].tolist() == [False] * 4 + [True] * 4
    assert float(hamming(bits, census(-a, 3))[0, 2, 2]) == 1.0
    assert float(hamming(bits, census(3 * a + 7, 3)).max()) == 0.0


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
        SweepStereo(**{option: value})


def test_a_reference_without_sources_is_refused():
    camera = PinholeCamera(width=32, height=32, fx=30.0, fy=30.0, cx=15.5, cy=15.5)
    with pytest.raises(ValueError, match="sources: sweep stereo needs at least one source view"):
        SweepStereo()(View(torch.rand(1, 1, 32, 32), camera, torch.eye(4)), [])


# ------------------------------------------------------------------ metric distance, exact ground truth
SIZE = 160
SWEEP = SweepStereo(hypotheses=64, min_distance=0.5, max_distance=20.0)


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
    sweep = {cost: SweepStereo(hypotheses=64, min_distance=1.0, max_distance=20.0, cost=cost, window=9)
             for cost in ("zncc", "census")}  # fmt: skip
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
    on_cpu = SweepStereo(hypotheses=24)(reference, [source])
    cuda = [View(v.image.cuda(), v.camera, v.T_ref_to_view.cuda()) for v in (reference, source)]
    on_gpu = SweepStereo(hypotheses=24)(cuda[0], cuda[1:])
    agree = (on_gpu.dense.cpu() - on_cpu.dense).abs() <= 1e-3 * on_cpu.dense
    assert agree.float().mean() > 0.99


# ------------------------------------------------------------------ the rig refined from its images
def rotation_between_deg(T_a: torch.Tensor, T_b: torch.Tensor) -> float:
    cos = ((torch.trace(T_a[:3, :3] @ T_b[:3, :3].T) - 1) / 2).clamp(-1, 1)
    return math.degrees(float(torch.acos(cos)))


@functools.cache
def refine_rig() -> tuple:
    """Two KITTI-360 fisheyes at 384 px, 0.2 m apart and turned 15 degrees, their SIFT matches, and the
    true pose between them."""
    camera = kitti02().resize(384, 384)
    T_b = pose(15.0, (0.2, 0.0, 0.0))
    image_a, _ = render(camera, pose(), texture_volume(0))
    image_b, _ = render(camera, T_b, texture_volume(0))
    matches = match_features(image_a, camera, image_b, camera)
    return camera, matches, invert_pose(T_b) @ pose()


@pytest.mark.parametrize("degrees", [1.0, 2.0])
@pytest.mark.parametrize("direction", [True, False])
def test_a_rig_turned_by_one_or_two_degrees_is_recovered(degrees, direction):
    camera, matches, T_true = refine_rig()
    axis = torch.tensor([0.3, -0.8, 0.5], dtype=torch.float64)
    turn = axis_angle_to_matrix(axis / axis.norm() * math.radians(degrees))
    start = make_pose(turn @ T_true[:3, :3], T_true[:3, 3])  # the rotation off, the lever arm as measured
    refined = refine_relative_pose(matches, start, float(camera.paraxial_focal()[0]), direction=direction)
    assert rotation_between_deg(refined.T_a_to_b, T_true) < 0.05
    assert refined.rotation_deg == pytest.approx(degrees, abs=0.05)
    assert refined.error_before_px > 0.8 * degrees and refined.error_after_px < 0.2  # pixels of camera b
    assert float(refined.T_a_to_b[:3, 3].norm()) == pytest.approx(0.2, rel=1e-9)  # the baseline's length kept
    assert refined.inliers > 0.9 * refined.matches > 1000


def test_a_correct_rig_is_left_as_it_is():
    camera, matches, T_true = refine_rig()
    refined = refine_relative_pose(matches, T_true, float(camera.paraxial_focal()[0]))
    assert refined.rotation_deg < 0.02 and rotation_between_deg(refined.T_a_to_b, T_true) < 0.02


def test_too_few_matches_or_no_baseline_are_refused():
    camera, matches, T_true = refine_rig()
    few = Matches(matches.rays_a[:5], matches.rays_b[:5], matches.uv_a[:5], matches.uv_b[:5])
    with pytest.raises(ValueError, match="matches: 5 feature matches; at least 8 are needed"):
        refine_relative_pose(few, T_true, 100.0)
    with pytest.raises(ValueError, match="T_a_to_b: the baseline has no length"):
        refine_relative_pose(matches, make_pose(T_true[:3, :3], torch.zeros(3)), 100.0)


# ------------------------------------------------------------------ the command on a recording
def write_room_rig(root: Path, size: int = 96, stamps=(1_000_000_000, 1_100_000_000, 1_200_000_000)) -> dict:
    """A rig layout in the textured room: cameras ``left`` and ``right`` 0.2 m apart, turned 20 degrees
    apart, moving 0.15 m forward per frame, with exact distance maps; and ``lonely``, whose one image is
    taken between the others' instants."""
    camera = kitti02().resize(size, size)
    extrinsics = {"left": pose(-10.0, (-0.1, 0.0, 0.0)), "right": pose(10.0, (0.1, 0.0, 0.0))}
    entries = [
        {"name": n, "model": camera.to_dict(), "cam_to_body": E.tolist()} for n, E in extrinsics.items()
    ]
    entries.append({"name": "lonely", "model": camera.to_dict(), "cam_to_body": np.eye(4).tolist()})
    (root / "seq").mkdir(parents=True)
    (root / "rig.yaml").write_text(yaml.safe_dump({"cameras": entries}))
    poses = {t: pose(0.0, (0.0, 0.0, 0.15 * i)) for i, t in enumerate(stamps)}
    (root / "seq" / "poses.txt").write_text(
        "".join(f"{t} 0 0 {0.15 * i} 0 0 0 1\n" for i, t in enumerate(stamps))
    )
    for name, E in extrinsics.items():
        for t, P in poses.items():
            image, distance = render(camera, P @ E, texture_volume(0))
            (root / "seq" / "images" / name).mkdir(parents=True, exist_ok=True)
            (root / "seq" / "distance" / name).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(
                str(root / "seq" / "images" / name / f"{t}.png"),
                (image[0, 0].numpy() * 255).round().astype(np.uint8),
            )
            np.save(root / "seq" / "distance" / name / f"{t}.npy", distance[0].numpy())
    lonely = root / "seq" / "images" / "lonely"
    lonely.mkdir(parents=True)
    cv2.imwrite(str(lonely / f"{stamps[0] + 50_000_000}.png"), np.zeros((size, size), np.uint8))
    return {"stamps": stamps, "camera": camera}


def test_the_multiview_command_on_a_rig_recording(tmp_path, capsys):
    from fisheyedepth.stereo.recording import main

    rig = write_room_rig(tmp_path / "rec", size=80)
    out = tmp_path / "out"
    args = [str(tmp_path / "rec"), "--out", str(out), "--hypotheses", "32", "--min-distance", "0.5",
            "--max-distance", "20", "--quiet"]  # fmt: skip
    assert main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    t0, t1, _ = rig["stamps"]
    assert summary["unpaired"] == [f"seq/lonely/{t0 + 50_000_000}"]  # no partner at its instant or later
    first = {r["image"]: r for r in summary["images"]}[f"seq/left/{t0}"]
    assert first["partners"] == [f"right/{t0}", f"left/{t1}"]  # the rig's other camera, then its own motion
    for record in summary["images"]:
        assert record["checked"]["abs_rel"] < 0.12 and record["checked"]["coverage"] > 0.6, record  # 80 px
        assert record["checked"]["abs_rel"] < 0.5 * record["checked"]["constant_abs_rel"], record
    distance = np.load(out / "seq" / "distance" / "left" / f"{t0}.npy")
    dense = np.load(out / "seq" / "dense" / "left" / f"{t0}.npy")
    assert distance.dtype == np.float32 and distance.shape == (80, 80)
    assert ((distance == 0) | (distance == dense)).all() and (dense > 0).sum() >= (distance > 0).sum() > 0
    assert cv2.imread(str(out / "seq" / "panels" / "left" / f"{t0}.png")).shape == (80, 4 * 80, 3)

    assert main(args) == 2  # the outputs exist: replaced only with --overwrite
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"error: {out / 'summary.json'} exists; pass --overwrite to replace the outputs"
    )
    assert main([*args[:3], "--sources", "rig,gps", "--quiet"]) == 2
    assert "--sources: 'rig,gps'; choose from rig,time" in capsys.readouterr().err


# ------------------------------------------------------------------ a real rectified pair
def crop(view: View, x0: int, y0: int, width: int, height: int) -> View:
    c = view.camera
    camera = PinholeCamera(width=width, height=height, fx=c.fx, fy=c.fy, cx=c.cx - x0, cy=c.cy - y0)
    return View(view.image[..., y0 : y0 + height, x0 : x0 + width], camera, view.T_ref_to_view)


def test_middlebury_motorcycle_a_real_pair():
    """Middlebury 2014 Motorcycle (real photographs, scikit-image): census sweep stereo on a 320x240 window
    of the left image's centre against the right image's full rows, scored against the exact disparity.
    The whole image (128 hypotheses) scores 0.0117 on 85.9 % of its pixels (BENCHMARKS.md); the window
    loses some of its border to the round trip."""
    pytest.importorskip("skimage")
    from fisheyedepth.stereo.pairs import motorcycle

    pair = motorcycle()
    x0, y0, width, height = 250, 130, 320, 240
    reference = crop(pair.reference, x0, y0, width, height)
    source = crop(pair.source, 0, y0, pair.source.camera.width, height)
    truth = pair.distance[y0 : y0 + height, x0 : x0 + width][None]
    result = SweepStereo(hypotheses=96, min_distance=1.5, max_distance=10.0, cost="census")(
        reference, [source]
    )
    checked = scores(result.distance, truth)
    assert checked["abs_rel"] < 0.02 and checked["a1"] > 0.96 and checked["coverage"] > 0.8, checked
    assert scores(result.dense, truth)["abs_rel"] < 0.1
