"""The reference implementation's KITTI-360 evaluation, exactly: its test set (every 20th pose row of the
left camera in drives 0000 and 0006, no translation bound, no neighbour needed) and its ground truth
(one scan, z > 0, the nearest point per pixel, no occlusion filter)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
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
