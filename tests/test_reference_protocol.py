"""The reference implementation's KITTI-360 evaluation, exactly: its test set (every 20th pose row of the
left camera in drives 0000 and 0006, no translation bound, no neighbour needed) and its ground truth
(one scan, z > 0, the nearest point per pixel, no occlusion filter)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from fisheyedepth.data import FisheyeDataModule, Kitti360Layout
from fisheyedepth.data.kitti360 import project_points, read_velodyne
from fisheyedepth.evaluation import PROTOCOLS

from conftest import TRAIN_SEQ

ROOT = Path(__file__).resolve().parents[1]


def write_poses(path: Path, rows: int, seed: int) -> list[int]:
    """``rows`` pose rows with sparse frame keys; the car stands still for a stretch (no parallax: the
    training loader drops those targets, the reference still scores them)."""
    rng = np.random.default_rng(seed)
    keys = np.cumsum(rng.integers(1, 4, rows))
    x = np.cumsum(np.where((np.arange(rows) > 40) & (np.arange(rows) < 90), 0.0, 0.8))
    lines = []
    for key, xi in zip(keys, x, strict=True):
        pose = np.eye(4)[:3]
        pose[0, 3] = xi
        lines.append(f"{key} " + " ".join(f"{v:.6f}" for v in pose.ravel()))
    path.parent.mkdir(parents=True)
    path.write_text("\n".join(lines) + "\n")
    return [int(k) for k in keys]


def test_the_kitti360_test_split_is_the_references_every_20th_row_unfiltered(kitti_data, tmp_path):
    root = tmp_path / "kitti360"
    shutil.copytree(kitti_data / "calibration", root / "calibration")
    rows = {"2013_05_28_drive_0000_sync": 437, "2013_05_28_drive_0006_sync": 263}
    keys = {
        seq: write_poses(root / "data_poses" / seq / "poses.txt", n, i)
        for i, (seq, n) in enumerate(rows.items())
    }
    splits = yaml.safe_load((ROOT / "conf" / "data" / "kitti360.yaml").read_text())["datamodule"]["splits"]
    dm = FisheyeDataModule(
        root, splits={"test": splits["test"]}, ground_truth="lidar", cache_dir=tmp_path / "c"
    )
    scored = dm.scoring_loader("test").dataset
    assert len(scored) == 22 + 14  # ceil(437 / 20) + ceil(263 / 20)
    got = [(it.sequence, dm.layout.frames(it.sequence)[it.row].key) for it in scored.items]
    assert got == [(seq, k) for seq in rows for k in keys[seq][::20]]
    assert {it.camera for it in scored.items} == {"image_02"}  # the left camera only
    trained = dm.dataset("test")  # the training loader's rules drop the first row and the standstill
    assert len(trained) < len(scored) and trained.dropped["below min_translation"] > 0


def test_the_reference_protocols_ground_truth_is_one_scan_z_positive_nearest_unfiltered(kitti_data):
    """Our projection keeps points beyond 90 degrees (z <= 0); the reference drops them first. On every
    pixel the kitti360 protocol scores (z > 0.3 m, range < 8 m: incidence below 88 degrees) both agree
    exactly, so one cache serves both."""
    layout = Kitti360Layout(kitti_data)
    p = PROTOCOLS["kitti360"]
    for camera_name in ("image_02", "image_03"):
        camera = layout.cameras[camera_name].camera
        T = layout.velo_to_camera(camera_name)
        for frame in layout.frames(TRAIN_SEQ)[::4]:
            points = read_velodyne(layout.lidar(TRAIN_SEQ, frame))
            ours, ours_z = project_points(points, T, camera)
            X = points[:, :3] @ T[:3, :3].T + T[:3, 3]
            theirs, theirs_z = project_points(points[X[:, 2] > 0], T, camera)
            scored = (theirs_z > p.z_range[0]) & (theirs_z < p.z_range[1]) & (theirs < p.max_range)
            assert scored.sum() > 100
            assert np.array_equal(ours[scored], theirs[scored]) and np.array_equal(
                ours_z[scored], theirs_z[scored]
            )
            ours_scored = (ours_z > p.z_range[0]) & (ours_z < p.z_range[1]) & (ours < p.max_range)
            assert np.array_equal(ours_scored, scored)
            assert (ours_z < 0).any() and not (theirs_z < 0).any()
    assert p.occlusion is None and p.z_range == (0.3, 60.0) and p.max_range == 8.0 and p.cap == (1e-3, 80.0)


def test_projection_keeps_the_nearest_point_at_the_rounded_pixel():
    """Hand-made points: two on one pixel's ray (the nearer wins, both its distance and its z), one
    rounded to its nearest pixel, one behind the camera beyond the model's field (dropped)."""
    from fisheyedepth.cameras import PinholeCamera

    camera = PinholeCamera(width=8, height=6, fx=4.0, fy=4.0, cx=3.5, cy=2.5)
    points = np.array(
        [
            [0.25, 0.05, 2.0, 0],  # u = 3.5 + 0.5 = 4.0, v = 2.5 + 0.1 = 2.6 -> pixel (4, 3)
            [0.5, 0.1, 4.0, 0],  # the same ray, twice as far: loses
            [-0.49, 0.26, 2.0, 0],  # u = 3.5 - 0.98 = 2.52 -> 3, v = 2.5 + 0.52 = 3.02 -> 3
            [0.0, 0.0, -1.0, 0],  # behind a pinhole camera: no projection
        ],
        np.float32,
    )
    d, z = project_points(points, np.eye(4), camera)
    assert np.count_nonzero(d) == 2
    assert d[3, 4] == pytest.approx(np.linalg.norm([0.25, 0.05, 2.0]), rel=1e-6) and z[3, 4] == 2.0
    assert d[3, 3] == pytest.approx(np.linalg.norm([-0.49, 0.26, 2.0]), rel=1e-6)


@pytest.fixture(scope="module")
def lidar_world(kitti_data, tmp_path_factory):
    """The synthetic world without its rendered maps, so ground truth comes from the Velodyne scans."""
    root = tmp_path_factory.mktemp("lidar") / "world"
    shutil.copytree(kitti_data, root, ignore=shutil.ignore_patterns("data_2d_distance"))
    return root


def test_evaluation_scores_unfiltered_lidar_and_each_protocol_filters_its_own(
    lidar_world, checkpoint, tmp_path
):
    from fisheyedepth.evaluation import Evaluator, evaluate
    from fisheyedepth.module import FisheyeDepthModule
    from fisheyedepth.runtimes import as_runtime

    model = as_runtime(FisheyeDepthModule.from_checkpoint(checkpoint))
    dm = FisheyeDataModule(lidar_world, ground_truth="lidar", cache_dir=tmp_path / "c")
    results = evaluate(model, dm.scoring_loader("test"), (64, 64), ["kitti360", "full"], ("none",))
    by_hand = {name: Evaluator(PROTOCOLS[name], ("none",)) for name in ("kitti360", "full")}
    for batch in dm.scoring_loader("test"):
        assert batch.distance_source == ["lidar"] * len(batch)  # every projected point, unfiltered
        pred = model.distance(batch.image, batch.camera).float()
        for i, camera in enumerate(batch.camera):
            for ev in by_hand.values():
                ev.update(pred[i, 0], batch.distance[i, 0], batch.mask[i, 0] > 0.5, camera, source="lidar")
    for name, ev in by_hand.items():
        assert results[name]["none"]["abs_rel"] == pytest.approx(ev.compute()["none"]["abs_rel"], rel=1e-6)
    assert results["kitti360"]["none"]["images"] > 0 and results["full"]["none"]["images"] > 0
    with pytest.raises(ValueError, match="kitti360 protocol scores every projected LiDAR point"):
        evaluate(model, dm.dataloader("test"), (64, 64), ["kitti360"], ("none",))  # training's filtered GT


def test_a_frame_without_a_scan_scores_nothing_under_auto_and_unreadable_frames_are_counted(
    lidar_world, checkpoint, tmp_path, caplog
):
    from fisheyedepth.evaluation import evaluate
    from fisheyedepth.module import FisheyeDepthModule

    root = tmp_path / "world"
    shutil.copytree(lidar_world, root)
    dm = FisheyeDataModule(root, ground_truth="auto", cache_dir=tmp_path / "c", skip_bad_frames=True)
    items = dm.scoring_loader("test").dataset.items
    first = dm.layout.frames(items[0].sequence)[items[0].row]
    dm.layout.lidar(items[0].sequence, first).unlink()  # no scan: its ground truth is unknown, all 0
    last = items[-1]
    image = dm.layout.image(last.sequence, last.camera, dm.layout.frames(last.sequence)[last.row])
    image.write_bytes(image.read_bytes()[:200])  # truncated: skipped, and counted
    sample = dm.scoring_loader("test").dataset[0]
    assert sample["distance_source"] == "none" and not sample["distance"].any()
    model = FisheyeDepthModule.from_checkpoint(checkpoint)
    with caplog.at_level("WARNING"):
        results = evaluate(model, dm.scoring_loader("test"), (64, 64), ["full"], ("none",))
    cameras_on_first = sum(1 for it in items if (it.sequence, it.row) == (items[0].sequence, items[0].row))
    assert results["full"]["none"]["images"] == len(items) - cameras_on_first - 1
    assert (
        results["full"]["skipped_frames"] == 1 and "1 frame(s) of the split could not be read" in caplog.text
    )


def test_an_unwritable_lidar_cache_is_reported_once_and_projection_goes_on(lidar_world, tmp_path, caplog):
    from fisheyedepth.data.kitti360 import LidarGroundTruth

    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "lidar").write_text("a file where the cache's folder should be")
    layout = Kitti360Layout(lidar_world)
    gt = LidarGroundTruth(layout, cache)
    cam = layout.cameras["image_02"].camera
    with caplog.at_level("WARNING"):
        maps = [gt(TRAIN_SEQ, "image_02", cam, f) for f in layout.frames(TRAIN_SEQ)[:3]]
    assert all((m[0] > 0).sum() > 100 for m in maps)
    assert caplog.text.count("cannot cache LiDAR projections") == 1
