"""The synthetic world: layout, exact geometry (temporal and cross-camera warps), LiDAR, determinism."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from fisheyedepth.cameras import RayCache, load_camera
from fisheyedepth.cli.synthetic import main as cli_main
from fisheyedepth.data.kitti360 import (
    KITTI360_CAM_TO_POSE,
    kitti360_camera,
    read_cam_to_pose,
    read_cam_to_velo,
    read_poses,
    read_velodyne,
)
from fisheyedepth.geometry import relative_pose, sample, warp_to_source
from fisheyedepth.synthetic import WorldSpec, generate, is_complete, make_trajectory, make_world
from fisheyedepth.synthetic.frames import FrameRenderer
from fisheyedepth.synthetic.raycast import first_per_ray
from fisheyedepth.synthetic.scene import split_frames

SIZE = 256
TRAIN = "2013_05_28_drive_0000_sync"
TINY = WorldSpec(frames=9, size=16, supersample=1)


@pytest.fixture(scope="session")
def surround_data(tmp_path_factory):
    spec = WorldSpec(
        "surround4",
        frames=9,
        size=SIZE,
        seed=5,
        supersample=1,  # one ray per pixel: warped / unwarped L1 0.02-0.04 (0.02-0.03 with 2x2 rays)
    )
    return generate(tmp_path_factory.mktemp("syn") / "surround", spec, lidar=False, progress=False)


def load_frame(root, seq, cam, frame):
    img = cv2.imread(str(root / "data_2d_raw" / seq / cam / "data_rgb" / f"{frame:010d}.png"))[..., ::-1]
    dist = np.load(root / "data_2d_distance" / seq / cam / f"{frame:010d}.npy")
    return torch.from_numpy(img.astype(np.float32) / 255).permute(2, 0, 1), torch.from_numpy(dist)


def body_mask(root, cam):
    return torch.from_numpy(
        cv2.imread(str(root / "calibration" / f"body_mask_{cam}.png"), cv2.IMREAD_UNCHANGED) > 0
    )


def depth_edges(dist: torch.Tensor, tol: float = 0.02) -> torch.Tensor:
    """Pixels next to a depth discontinuity: the distance is not locally linear along a row or a column
    (a plane seen at a grazing angle is smooth, an occluding contour is not), or a neighbour is sky."""
    d = torch.nn.functional.pad(dist[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    c = d[1:-1, 1:-1]
    kink = ((2 * c - d[1:-1, :-2] - d[1:-1, 2:]).abs() > tol * c) | (
        (2 * c - d[:-2, 1:-1] - d[2:, 1:-1]).abs() > tol * c
    )
    kink |= c <= 0
    return torch.nn.functional.max_pool2d(kink.float()[None, None], 3, 1, 1)[0, 0] > 0


def warp_check(root, seq, target, t_frame, source, s_frame):
    """Warp the source image into the target with the target's GT distance; (warped L1, unwarped L1, n)."""
    cam_t, cam_s = (
        load_camera(root / "calibration" / f"{target}.yaml"),
        load_camera(root / "calibration" / f"{source}.yaml"),
    )
    E = read_cam_to_pose(root / "calibration" / "calib_cam_to_pose.txt")
    P = read_poses(root / "data_poses" / seq / "poses.txt")
    T = relative_pose(*(torch.from_numpy(m) for m in (P[t_frame], P[s_frame], E[target], E[source])))
    img_t, dist_t = load_frame(root, seq, target, t_frame)
    img_s, dist_s = load_frame(root, seq, source, s_frame)
    rays, valid = RayCache().get(cam_t, dtype=torch.float64)
    warp = warp_to_source(
        rays[None],
        valid[None] & (dist_t > 0)[None] & body_mask(root, target)[None],
        dist_t.double()[None],
        T[None].double(),
        cam_s,
        body_mask(root, source)[None].double(),
    )
    warped = sample(img_s[None].double(), warp.grid)[0]
    # not occluded: the source sees the same surface at the warped pixel (its GT distance agrees)
    X_s = (rays * dist_t.double()[..., None]) @ T[:3, :3].T + T[:3, 3]
    seen = sample(dist_s[None, None].double(), warp.grid, padding_mode="zeros")[0, 0]
    visible = warp.valid[0] & ((seen - X_s.norm(dim=-1)).abs() < 0.03 * X_s.norm(dim=-1))
    # pixels on a depth edge mix two surfaces in their (supersampled) colour: neither side's depth fits
    smooth_t = ~depth_edges(dist_t)
    smooth_s = (
        sample((~depth_edges(dist_s)).double()[None, None], warp.grid, padding_mode="zeros")[0, 0] > 0.999
    )
    visible &= smooth_t & smooth_s
    photo = (warped - img_t).abs().mean(0)[visible].mean().item()
    unwarped = (img_s - img_t).abs().mean(0)[visible].mean().item()
    return photo, unwarped, int(visible.sum())


def test_layout(kitti_data):
    root = kitti_data
    assert is_complete(root)
    meta = json.loads((root / "synthetic.json").read_text())
    assert meta["rig"] == "kitti360" and meta["size"] == SIZE and meta["seed"] == 3
    for seq in (TRAIN, "2013_05_28_drive_0001_sync", "2013_05_28_drive_0002_sync"):
        poses = read_poses(root / "data_poses" / seq / "poses.txt")
        for cam in ("image_02", "image_03"):
            frames = sorted(p.stem for p in (root / "data_2d_raw" / seq / cam / "data_rgb").glob("*.png"))
            assert frames == [f"{i:010d}" for i in sorted(poses)]
            dist = np.load(root / "data_2d_distance" / seq / cam / f"{frames[0]}.npy")
            assert dist.dtype == np.float32 and dist.shape == (SIZE, SIZE)
            scene = (dist > 0) & body_mask(root, cam).numpy()  # the ego roof is ~0.37 m below the camera
            assert 0.35 < dist[dist > 0].min() and 1.0 < dist[scene].min() and dist.max() <= 120
            assert (dist > 0).mean() > 0.4
        scans = sorted((root / "data_3d_raw" / seq / "velodyne_points" / "data").glob("*.bin"))
        assert len(scans) == len(poses)
    splits = {s: (root / "splits" / f"{s}.txt").read_text().split("\n") for s in ("train", "val", "test")}
    assert {line.split()[0] for line in splits["train"] if line} == {TRAIN}
    assert sum(len([x for x in v if x]) for v in splits.values()) == 12


def test_calibration_is_kitti360_scaled(kitti_data):
    root = kitti_data / "calibration"
    for i in (2, 3):
        assert load_camera(root / f"image_0{i}.yaml") == kitti360_camera(i).resize(SIZE, SIZE)
        kept = load_camera(root / f"image_0{i}.yaml", keep_tangential=True)
        assert kept == kitti360_camera(i, tangential=True).resize(SIZE, SIZE)
    E = read_cam_to_pose(root / "calib_cam_to_pose.txt")
    assert sorted(E) == ["image_00", "image_01", "image_02", "image_03"]
    for name, values in KITTI360_CAM_TO_POSE.items():
        assert np.allclose(E[name][:3].reshape(-1), values, atol=1e-9)
    mask = body_mask(kitti_data, "image_02")
    assert mask[: SIZE // 3].all() and not mask[-3:, SIZE // 2].any()  # the car body fills the bottom
    assert 0.1 < (~mask).float().mean() < 0.45


def test_trajectory_speed_and_turns():
    world = make_world(11)
    poses = make_trajectory(world, 400, 11)
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert step.min() >= 0.3 - 1e-9 and step.max() <= 1.5 + 1e-9
    heading = np.unwrap(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    assert np.abs(np.diff(heading)).sum() > math.radians(80)  # it turns at intersections
    assert np.allclose(poses[:, 2, 3], 0.73) and np.allclose(np.linalg.det(poses[:, :3, :3]), 1)
    other = make_world(12)
    assert other.pitch != world.pitch and len(other.boxes) != len(world.boxes)


def test_left_lane_mirrors_the_cars_offset_from_the_centreline():
    """``lane="left"``: the same route, the car 1.75 m to the left of the centreline instead of the right;
    a bad lane name is refused before anything is written."""
    world = make_world(11)
    right, left = make_trajectory(world, 60, 11, 1.75), make_trajectory(world, 60, 11, -1.75)
    # the body's y axis points to its right: the left-lane car sits 3.5 m to the left of the right-lane one
    # (compared at the start, on the same straight, before the two lanes' arc lengths drift apart)
    lateral = np.einsum("i,i->", left[0, :3, 3] - right[0, :3, 3], right[0, :3, 1])
    assert lateral == pytest.approx(-3.5, abs=0.05)
    with pytest.raises(ValueError, match="lane must be one of"):
        generate(Path("/nonexistent/never-written"), WorldSpec(lane="centre"))


@pytest.mark.parametrize("cam", ["image_02", "image_03"])
def test_consecutive_frames_are_consistent(kitti_data, cam):
    """Frame t+1 warped into t with GT distance and poses reproduces t: L1 <= a third of the unwarped L1."""
    for t in range(0, 6, 2):
        photo, unwarped, n = warp_check(kitti_data, TRAIN, cam, t, cam, t + 1)
        assert n > 0.1 * SIZE * SIZE
        assert photo <= unwarped / 3, (t, photo, unwarped)
        assert photo < 0.03


def test_cameras_of_the_surround_rig_agree(surround_data):
    """The front (Kannala-Brandt) camera warped into the left (Mei) camera at the same instant."""
    for target, source in (("image_02", "image_04"), ("image_03", "image_05"), ("image_04", "image_03")):
        photo, unwarped, n = warp_check(surround_data, TRAIN, target, 2, source, 2)
        assert n > 500
        assert photo <= unwarped / 3, (target, source, photo, unwarped)


def test_lidar_agrees_with_the_distance_maps(kitti_data):
    root = kitti_data
    E = read_cam_to_pose(root / "calibration" / "calib_cam_to_pose.txt")
    velo_to_pose = E["image_00"] @ np.linalg.inv(
        read_cam_to_velo(root / "calibration" / "calib_cam_to_velo.txt")
    )
    points = read_velodyne(root / "data_3d_raw" / TRAIN / "velodyne_points" / "data" / f"{4:010d}.bin")
    assert len(points) > 10_000 and np.isfinite(points).all()
    for cam_name in ("image_02", "image_03"):
        cam = load_camera(root / "calibration" / f"{cam_name}.yaml")
        X = points[:, :3].astype(np.float64) @ (np.linalg.inv(E[cam_name]) @ velo_to_pose)[:3, :3].T
        X += (np.linalg.inv(E[cam_name]) @ velo_to_pose)[:3, 3]
        uv, ok = cam.project(torch.from_numpy(X))
        px = torch.round(uv).long()
        inside = ok & (px[:, 0] >= 0) & (px[:, 0] < SIZE) & (px[:, 1] >= 0) & (px[:, 1] < SIZE)
        _, dist = load_frame(root, TRAIN, cam_name, 4)
        gt = dist[px[inside, 1], px[inside, 0]].double()
        rng = torch.from_numpy(np.linalg.norm(X, axis=1))[inside]
        has = gt > 0
        assert has.sum() > 1000
        rel = ((gt[has] - rng[has]).abs() / rng[has]).median().item()
        assert rel < 0.01, (cam_name, rel)


def test_same_seed_same_files_other_seed_other_world(tmp_path):
    tiny = {"frames": 9, "size": 32, "supersample": 1}
    a = generate(tmp_path / "a", WorldSpec("kitti360", seed=1, **tiny), progress=False)
    b = generate(tmp_path / "b", WorldSpec("kitti360", seed=1, **tiny), progress=False)
    c = generate(tmp_path / "c", WorldSpec("kitti360", seed=2, **tiny), progress=False, lidar=False)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for rel in files:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    first = f"data_2d_raw/{TRAIN}/image_02/data_rgb/{0:010d}.png"
    assert (a / first).read_bytes() != (c / first).read_bytes()


def test_refuses_to_overwrite_and_never_leaves_a_partial_dataset(tmp_path, monkeypatch):
    out = tmp_path / "data"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="overwrite"):
        generate(out, TINY, lidar=False, progress=False)
    assert (out / "keep.txt").read_text() == "mine"
    calls = {"n": 0}
    original = FrameRenderer.__call__

    def crash(self, job):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return original(self, job)

    monkeypatch.setattr(FrameRenderer, "__call__", crash)
    fresh = tmp_path / "fresh"
    with pytest.raises(KeyboardInterrupt):
        generate(fresh, TINY, lidar=False, progress=False)
    assert not fresh.exists() and not list(tmp_path.glob(".fresh*"))
    monkeypatch.setattr(FrameRenderer, "__call__", original)
    generate(out, TINY, lidar=False, progress=False, overwrite=True)
    assert is_complete(out) and not (out / "keep.txt").exists()


def test_cli(tmp_path, capsys):
    args = [
        "--out",
        str(tmp_path / "d"),
        "--frames",
        "9",
        "--size",
        "16",
        "--supersample",
        "1",
        "--no-lidar",
        "--quiet",
    ]
    assert cli_main(args) == 0
    assert is_complete(tmp_path / "d")
    assert cli_main(args) == 2
    assert "overwrite" in capsys.readouterr().err
    assert cli_main([*args, "--size", "20"]) == 2  # not a multiple of 8


def test_worker_processes_write_the_same_dataset(tmp_path):
    spec = WorldSpec("kitti360", frames=9, size=32, seed=4, supersample=1)
    serial = generate(tmp_path / "s", spec, progress=False)
    parallel = generate(tmp_path / "p", spec, workers=2, progress=False)
    for path in serial.rglob("*.npy"):
        assert np.array_equal(np.load(path), np.load(parallel / path.relative_to(serial)))


def _turn_deg(poses: np.ndarray) -> float:
    """Total absolute heading change along a stretch of body poses (degrees)."""
    yaw = np.unwrap(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    return float(np.degrees(np.abs(np.diff(yaw)).sum()))


def test_the_table2_world_turns_in_training_and_validation():
    """``scripts/research/reproduce.py`` trains on world 34 because its training segment turns: in the
    default world 0 it drives straight while validation turns, so a PoseNet never learns a rotation there."""
    ranges = split_frames(200)
    turns = {}
    for seed in (0, 34):
        poses = make_trajectory(make_world(seed), ranges["test"][1], seed)
        turns[seed] = {split: _turn_deg(poses[a:b]) for split, (a, b) in ranges.items()}
    assert turns[0]["train"] < 5 and turns[0]["val"] > 30, turns[0]
    assert turns[34]["train"] > 150 and turns[34]["val"] > 30, turns[34]


def test_a_ray_meeting_two_objects_at_one_distance_keeps_the_lower_id():
    """Two boxes sharing a face give one ray two hits at the same distance: the lower object id wins,
    whatever order the candidates come in (an indexed write with a repeated index picks any)."""
    rays, objs = torch.tensor([7, 3, 7, 5, 3]), torch.tensor([4, 9, 2, 1, 0])
    ray, obj = first_per_ray(rays, objs)
    assert ray.tolist() == [3, 5, 7] and obj.tolist() == [0, 1, 2]
    ray, obj = first_per_ray(rays.flip(0), objs.flip(0))
    assert ray.tolist() == [3, 5, 7] and obj.tolist() == [0, 1, 2]
