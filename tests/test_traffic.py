"""A world that moves: traffic with exact ground truth and a moving mask, camera effects, evaluation of
static and moving pixels apart, and the objective's levers for them (brightness, outliers)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch

from fisheyedepth.cameras import compute_rays
from fisheyedepth.data import FisheyeDataset, Kitti360Layout, collate
from fisheyedepth.data.augment import flip_sample
from fisheyedepth.evaluation import PROTOCOLS, Evaluator
from fisheyedepth.losses.selfsup import ReprojectionLoss, match_brightness, trimmed
from fisheyedepth.synthetic import DatasetMismatch, WorldSpec, ensure_dataset, generate
from fisheyedepth.synthetic.raycast import Movers, scene_tensors
from fisheyedepth.synthetic.render import MAX_RANGE, CameraRenderer
from fisheyedepth.synthetic.rig import make_rig
from fisheyedepth.synthetic.scene import make_scene_motion, pose_at
from fisheyedepth.synthetic.sensor import BLUR_SAMPLES, SHUTTER, Sensor, blur_times, check_effects
from fisheyedepth.synthetic.traffic import CLEARANCE, MOVING, _legs, make_traffic
from fisheyedepth.synthetic.world import make_drive, make_trajectory, make_world

from conftest import TRAIN_SEQ, kitti02

EFFECTS = ["exposure", "motion_blur", "noise", "vignetting", "white_balance"]
SEED, FRAMES = 3, 60


@pytest.fixture(scope="module")
def street():
    world = make_world(SEED)
    drive = make_drive(world, FRAMES, SEED)
    return world, drive, make_traffic(world, drive, 1.0, SEED)


# ------------------------------------------------------------------------------------------ the traffic
def test_no_traffic_leaves_the_drive_as_it_was_and_places_no_agent():
    world = make_world(SEED)
    poses, traffic = make_scene_motion(world, FRAMES, SEED, "right", 0.0)
    assert np.array_equal(poses, make_trajectory(world, FRAMES, SEED))
    assert traffic.n_agents == 0 and traffic.track.shape == (0, FRAMES, 3)


def test_the_agents_keep_to_their_lanes_and_never_come_near_the_ego(street):
    world, drive, traffic = street
    kinds = set(traffic.kind)
    assert {"lead", "oncoming", "crossing", "pedestrian"} <= kinds, kinds
    ego = drive.poses[:, :3, 3]
    lead = traffic.track[traffic.kind.index("lead")]
    # the lead car moves with the ego: in the body frame it stays ahead, in the lane, at one distance
    ahead = np.einsum(
        "fij,fj->fi", drive.poses[:, :3, :3].transpose(0, 2, 1), np.c_[lead[:, :2], ego[:, 2:]] - ego
    )
    ego_yaw = np.arctan2(drive.poses[:, 1, 0], drive.poses[:, 0, 0])
    straight = np.abs(np.angle(np.exp(1j * (lead[:, 2] - ego_yaw)))) < math.radians(1.0)
    assert straight.sum() > FRAMES // 2  # on a straight stretch: straight ahead, at one distance
    assert np.abs(ahead[straight, 1]).max() < 0.05 and np.ptp(ahead[straight, 0]) < 0.05
    assert ahead[:, 0].min() > 7.0
    on_lane = np.linalg.norm(drive.lane[None] - lead[:, None, :2], axis=-1).min(1)
    assert on_lane.max() < 0.05  # in turns too: it follows the lane
    speeds = np.linalg.norm(np.diff(ego[:, :2], axis=0), axis=1)
    assert np.allclose(np.linalg.norm(np.diff(lead[:, :2], axis=0), axis=1), speeds, rtol=0.05, atol=0.05)
    # crossing cars are never on a street the route drives along, and they wait for it
    driven = _legs(drive.route, world.pitch)
    for a in (i for i, k in enumerate(traffic.kind) if k == "crossing"):
        x, y, yaw = traffic.track[a, 0]
        axis = 0 if abs(math.sin(yaw)) < 0.5 else 1
        line = round((y if axis == 0 else x) / world.pitch)
        assert (axis, line) not in driven
    # an agent the ego would meet is left out of that frame: every box placed is clear of the ego
    for k in range(FRAMES):
        boxes = traffic.boxes_at(k, ego[k])
        placed = np.c_[boxes["x"], boxes["y"]]
        assert (np.linalg.norm(placed - ego[k, :2], axis=1) >= CLEARANCE).all()
    # "moving" follows the speed: the lead car always moves, a waiting agent does not
    for k in (0, 20, FRAMES - 1):
        assert traffic.moving(k)[traffic.kind.index("lead")]
        assert np.array_equal(traffic.moving(k), traffic.speed(k) > MOVING)


def test_traffic_density_must_be_a_number_of_at_least_zero(street):
    world, drive, _ = street
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="traffic density"):
            make_traffic(world, drive, bad, SEED)
    indoor = make_world(SEED)
    indoor.scene = "indoor"
    with pytest.raises(ValueError, match="indoor scene has no streets"):
        make_scene_motion(indoor, FRAMES, SEED, "right", 1.0)


def _oriented_hits(origin, dirs, boxes) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of unit rays ``dirs [N, 3]`` from ``origin [3]`` with the boxes turned about z, in
    float64 (an independent slab test), and the agent it belongs to (-1: none)."""
    best, agent = np.full(len(dirs), np.inf), np.full(len(dirs), -1)
    parts = zip(boxes["lo"], boxes["hi"], boxes["x"], boxes["y"], boxes["yaw"], boxes["owner"], strict=True)
    for lo, hi, x, y, yaw, owner in parts:
        c, s = math.cos(yaw), math.sin(yaw)
        R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world to box
        o = R @ (origin - np.array([x, y, 0.0]))
        d = dirs @ R.T
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - o) / d, (hi - o) / d
        near = np.nanmax(np.minimum(t1, t2), axis=1)
        far = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (far >= near) & (near > 1e-4)
        nearer = hit & (near < best)
        best, agent = np.where(nearer, near, best), np.where(nearer, owner, agent)
    return best, agent


@pytest.mark.parametrize("rig_name, camera", [("surround4", "image_04"), ("kitti360", "image_02")])
def test_the_ground_truth_of_moving_agents_is_exact_at_the_frames_instant(street, rig_name, camera):
    world, drive, traffic = street
    rig = make_rig(rig_name, 96)
    renderer = CameraRenderer(rig.cameras[camera], rig.cam_to_pose[camera], supersample=1)
    scene = scene_tensors(world)
    seen = 0
    for k in (10, 40):
        pose = drive.poses[k]
        boxes = traffic.boxes_at(k, pose[:2, 3])
        distance, moving = renderer.truth(scene, pose, Movers.from_boxes(boxes), traffic.moving(k))
        rays, valid = compute_rays(rig.cameras[camera], dtype=torch.float64)
        T = pose @ rig.cam_to_pose[camera]
        dirs = rays.numpy().reshape(-1, 3) @ T[:3, :3].T
        reference, owner = (a.reshape(distance.shape) for a in _oriented_hits(T[:3, 3], dirs, boxes))
        assert moving.dtype == bool and not moving[~valid.numpy()].any()
        ys, xs = np.nonzero(moving)
        seen += len(ys)
        # every pixel marked moving sees an agent, at the distance of the exact ray-box intersection
        assert np.isfinite(reference[ys, xs]).all()
        np.testing.assert_allclose(distance[ys, xs], reference[ys, xs], rtol=2e-4, atol=2e-4)
        # and a moving agent nearer than the static world (and the ego's body) is never left unmarked
        still = renderer.truth(scene, pose)[0]
        in_range = np.isfinite(reference) & (reference <= MAX_RANGE)  # the renderer's range
        nearer = in_range & (reference < np.where(still > 0, still, np.inf) - 1e-3)
        expected = nearer & valid.numpy() & traffic.moving(k)[np.maximum(owner, 0)]
        assert np.array_equal(expected, moving)
    assert seen > 20, f"the {camera} of {rig_name} saw only {seen} moving pixels"


# ------------------------------------------------------------------------------------------ the camera
def test_effects_are_checked_by_name():
    assert check_effects(["noise", "exposure", "noise"]) == ("exposure", "noise")
    with pytest.raises(ValueError, match=r"unknown \['fog'\]"):
        check_effects(["fog"])


def test_vignetting_exposure_white_balance_and_noise_do_what_they_say():
    H = W = 64
    valid = np.ones((H, W), bool)
    flat = torch.full((H, W, 3), 0.5)
    vignette = Sensor(["vignetting"], SEED, 0, valid)(flat, 0)
    assert float(vignette[H // 2, W // 2, 0]) > 0.49 and float(vignette[0, 0, 0]) < 0.5 * 0.8
    # auto-exposure pulls a dark frame up and a bright one down; its drift changes it from frame to frame
    exposure = Sensor(["exposure"], SEED, 0, valid)
    dark, bright = exposure(torch.full((H, W, 3), 0.1), 5), exposure(torch.full((H, W, 3), 0.9), 5)
    assert float(dark.mean()) > 0.2 and float(bright.mean()) < 0.75
    gains = [float(exposure.gains(flat, k)[0]) for k in range(0, 60, 5)]
    assert max(gains) / min(gains) > 1.1
    balance = Sensor(["white_balance"], SEED, 0, valid)
    g = torch.stack([balance.gains(flat, k) for k in range(0, 120, 4)])
    assert (g[:, 1] == 1).all() and g[:, 0].std() > 0.01 and g[:, 2].std() > 0.01
    assert (g[:, [0, 2]] - 1).abs().max() < 0.25
    # noise: zero mean, the model's spread, new in every frame, the same for the same seed and frame
    noise = Sensor(["noise"], SEED, 0, valid)
    a, b = noise(flat, 1) - flat, noise(flat, 2) - flat
    assert abs(float(a.mean())) < 2e-3 and float(a.std()) == pytest.approx(
        math.sqrt(0.004**2 + 0.0008 * 0.5), rel=0.05
    )
    assert not torch.equal(a, b) and torch.equal(noise(flat, 1), Sensor(["noise"], SEED, 0, valid)(flat, 1))
    # another camera of the rig drifts on its own
    assert float(Sensor(["exposure"], SEED, 1, valid).gains(flat, 5)[0]) != float(exposure.gains(flat, 5)[0])


def test_motion_blur_averages_the_open_shutter_around_the_frame():
    times = blur_times(7)
    assert len(times) == BLUR_SAMPLES and times.mean() == pytest.approx(7.0)
    assert times.max() - times.min() == pytest.approx(SHUTTER)
    world = make_world(SEED)
    poses = make_trajectory(world, 20, SEED)
    assert np.allclose(pose_at(poses, 7.0), poses[7]) and np.allclose(pose_at(poses, 8.0), poses[8])
    half = pose_at(poses, 7.5)
    assert np.allclose(half[:3, 3], 0.5 * (poses[7][:3, 3] + poses[8][:3, 3]))
    assert np.allclose(half[:3, :3] @ half[:3, :3].T, np.eye(3), atol=1e-12)
    angle = lambda R: math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1))  # noqa: E731
    step = poses[7][:3, :3].T @ poses[8][:3, :3]
    assert angle(poses[7][:3, :3].T @ half[:3, :3]) == pytest.approx(angle(step) / 2, abs=1e-9)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """The same 16-pixel world with traffic rendered three times: plain, with every effect, and again
    with every effect (same seed; no LiDAR this time)."""
    root = tmp_path_factory.mktemp("traffic")
    kwargs = dict(frames=9, size=16, seed=SEED, supersample=1, traffic=1.0)
    plain = generate(root / "plain", WorldSpec(**kwargs), lidar=True, progress=False)
    effects = generate(root / "effects", WorldSpec(**kwargs, effects=EFFECTS), lidar=True, progress=False)
    spec = WorldSpec(**kwargs, effects=list(reversed(EFFECTS)))
    again = generate(root / "again", spec, lidar=False, progress=False)
    return plain, effects, again


def _files(root, pattern):
    return sorted(p.relative_to(root) for p in root.glob(pattern))


def test_traffic_and_effects_render_the_same_bytes_for_a_seed_and_leave_the_ground_truth_alone(rendered):
    plain, effects, again = rendered
    meta = json.loads((effects / "synthetic.json").read_text())
    assert meta["traffic"] == 1.0 and meta["effects"] == EFFECTS and meta["world"]["agents"]["lead"] == 1
    masks = _files(plain, "data_2d_moving/*/*/*.png")
    assert len(masks) == 9 * 2
    for pattern in (
        "data_2d_raw/*/*/data_rgb/*.png",
        "data_2d_distance/*/*/*.npy",
        "data_2d_moving/*/*/*.png",
    ):
        assert _files(effects, pattern) == _files(again, pattern) and _files(effects, pattern)
        for f in _files(effects, pattern):
            assert (effects / f).read_bytes() == (again / f).read_bytes(), f
    # the effects change the images, never the ground truth (distance, moving mask, LiDAR)
    for pattern in ("data_2d_distance/*/*/*.npy", "data_2d_moving/*/*/*.png", "data_3d_raw/**/*.bin"):
        for f in _files(plain, pattern):
            assert (plain / f).read_bytes() == (effects / f).read_bytes(), f
    changed = [
        (plain / f).read_bytes() != (effects / f).read_bytes()
        for f in _files(plain, "data_2d_raw/*/*/data_rgb/*.png")
    ]
    assert all(changed)


def test_a_dataset_asked_for_with_other_traffic_or_effects_is_refused(rendered):
    plain, effects, _ = rendered
    common = dict(frames=9, size=16, seed=SEED, supersample=1)
    assert ensure_dataset(plain, WorldSpec(**common, traffic=1.0), progress=False) == plain
    spec = WorldSpec(**common, traffic=1.0, effects=list(reversed(EFFECTS)))
    assert ensure_dataset(effects, spec, progress=False) == effects
    with pytest.raises(DatasetMismatch, match=r"traffic 1\.0 \(asked 0\.5\)"):
        ensure_dataset(plain, WorldSpec(**common, traffic=0.5), progress=False)
    with pytest.raises(DatasetMismatch, match="effects"):
        ensure_dataset(plain, WorldSpec(**common, traffic=1.0, effects=["noise"]), progress=False)


# ------------------------------------------------------------------------------------------ evaluation
def test_the_moving_mask_reaches_the_batch_and_flips_with_the_image(rendered):
    plain = rendered[0]
    layout = Kitti360Layout(plain)
    dataset = FisheyeDataset(layout, [{"sequence": TRAIN_SEQ}], offsets=(), ground_truth="distance")
    samples = [dataset[i] for i in range(len(dataset))]
    batch = collate(samples)
    assert batch.moving is not None and batch.moving.shape == batch.distance.shape
    for sample, item in zip(samples, dataset.items, strict=True):
        frame = layout.frames(item.sequence)[item.row]
        mask = cv2.imread(str(layout.moving(item.sequence, item.camera, frame)), cv2.IMREAD_GRAYSCALE) > 127
        assert torch.equal(sample["moving"][0].bool(), torch.from_numpy(mask))
    flipped = flip_sample(samples[0])
    assert torch.equal(flipped["moving"], samples[0]["moving"].flip(-1))


def test_a_broken_moving_mask_is_refused_naming_its_file(rendered, tmp_path):
    import shutil

    root = tmp_path / "copy"
    shutil.copytree(rendered[0], root)
    layout = Kitti360Layout(root)
    masks = sorted((root / "data_2d_moving" / TRAIN_SEQ / "image_02").glob("*.png"))
    cv2.imwrite(str(masks[1]), np.zeros((8, 8), np.uint8))
    masks[2].unlink()
    dataset = FisheyeDataset(layout, [{"sequence": TRAIN_SEQ}], cameras=["image_02"], offsets=())
    with pytest.raises(ValueError, match=rf"{masks[1].name}: moving-object mask of 8x8 pixels"):
        dataset[1]
    with pytest.raises(FileNotFoundError, match=rf"no moving-object mask for {TRAIN_SEQ}/image_02/2"):
        dataset[2]


def test_the_evaluator_scores_static_and_moving_pixels_apart():
    camera = kitti02().resize(32, 32)
    gt = torch.full((32, 32), 10.0, dtype=torch.float64)
    moving = torch.zeros(32, 32, dtype=torch.bool)
    moving[10:20, 10:20] = True
    pred = torch.where(moving, 2 * gt, gt)  # right on the road, wrong by 2x on the car
    ev = Evaluator(PROTOCOLS["full"], ("none",))
    ev.update(pred, gt, torch.ones(32, 32, dtype=torch.bool), camera, moving=moving)
    ev.update(gt, gt, torch.ones(32, 32, dtype=torch.bool), camera)  # without a mask: all static
    out = ev.compute()["none_by_motion"]
    assert out["static"]["abs_rel"] == pytest.approx(0.0, abs=1e-12) and out["static"]["images"] == 2
    assert out["moving"]["abs_rel"] == pytest.approx(1.0) and out["moving"]["images"] == 1
    headline = ev.compute()["none"]["abs_rel"]
    assert 0 < headline < 1  # the headline mixes both: only the split shows where the error is


# ------------------------------------------------------------------------------------------ the levers
def test_brightness_matching_undoes_an_exposure_and_white_balance_change():
    torch.manual_seed(0)
    target = torch.rand(2, 3, 24, 24)
    gain = torch.tensor([1.4, 1.1, 0.8])[None, None, :, None, None]
    source = (target[:, None] * gain + 0.05).expand(2, 3, 3, 24, 24)  # three sources, one change
    np.testing.assert_allclose(match_brightness(source, target), target[:, None].expand_as(source), atol=1e-5)
    plain, matched = ReprojectionLoss(), ReprojectionLoss(brightness="affine")
    before, after = (float(loss.photometric(source, target).mean()) for loss in (plain, matched))
    assert before > 0.03 and after < before / 30, (before, after)
    # the gain is bounded: a warp that shows something else is not rescaled into agreement
    flat = torch.full_like(source, 0.5) + 1e-3 * torch.rand_like(source)
    assert float(matched.photometric(flat, target).mean()) > 0.05
    with pytest.raises(ValueError, match="brightness"):
        ReprojectionLoss(brightness="gamma")


def test_outliers_leave_the_worst_pixels_of_each_image_out_of_the_loss():
    error = torch.arange(200, dtype=torch.float32).reshape(2, 10, 10)
    mask = torch.ones(2, 10, 10, dtype=torch.bool)
    keep = trimmed(error, mask, 0.2)
    assert keep.sum(dim=(1, 2)).tolist() == [80, 80]
    for b in range(2):
        assert error[b][keep[b]].max() < error[b][~keep[b]].min()
    torch.manual_seed(0)
    target = torch.rand(1, 3, 16, 16)
    warped = target[:, None].clone()
    warped[..., :4, :] = 1 - warped[..., :4, :]  # a quarter of the image is a car no warp explains
    valid = torch.ones(1, 1, 16, 16, dtype=torch.bool)
    usable = torch.ones(1, 16, 16, dtype=torch.bool)
    loss_all, _, _ = ReprojectionLoss(automask=False)(target, warped, valid, None, usable)
    loss_trim, used, _ = ReprojectionLoss(automask=False, trim=0.4)(target, warped, valid, None, usable)
    assert float(loss_all) > 0.05 and float(loss_trim) < 0.2 * float(loss_all)
    assert 0.6 <= float(used) <= 0.75  # the worst 40 % out (ties at the threshold stay in)
    with pytest.raises(ValueError, match="outliers"):
        ReprojectionLoss(trim=1.0)


def test_the_command_line_takes_traffic_and_effects_and_refuses_bad_ones(tmp_path, capsys):
    from fisheyedepth.cli.synthetic import main

    out = tmp_path / "d"
    assert main(["--out", str(out), "--traffic", "-1", "--quiet"]) == 2
    assert "error: --traffic: -1.0 is not a number in [0, 8]" in capsys.readouterr().err and not out.exists()
    with pytest.raises(SystemExit):
        main(["--out", str(out), "--effects", "fog"])
    assert "invalid choice: 'fog'" in capsys.readouterr().err
    assert main(["--out", str(out), "--frames", "9", "--size", "16", "--supersample", "1", "--no-lidar",
                 "--traffic", "0.5", "--effects", "noise", "vignetting", "--quiet"]) == 0  # fmt: skip
    meta = json.loads((out / "synthetic.json").read_text())
    assert meta["traffic"] == 0.5 and meta["effects"] == ["noise", "vignetting"]
