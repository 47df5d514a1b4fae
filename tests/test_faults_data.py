"""Data faults that used to train silently: non-rigid or duplicate poses, a camera that
vanishes, grayscale and truncated images, a training size of another aspect ratio, and
``skip_bad_frames`` settable without a leading ``+``."""

from __future__ import annotations

import logging
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from fisheyedepth.data import FisheyeDataModule, FisheyeDataset, Kitti360Layout, RigLayout, collate
from fisheyedepth.data import files as data_files
from fisheyedepth.data.kitti360 import read_cam_to_pose, read_poses

from conftest import TRAIN_SEQ, kitti02

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def damaged(kitti_data, tmp_path):
    root = tmp_path / "damaged"
    shutil.copytree(kitti_data, root, ignore=shutil.ignore_patterns("data_3d_raw"))
    return root


@pytest.fixture
def cache(tmp_path):
    return tmp_path / "cache"


def poses_file(root: Path) -> Path:
    return root / "data_poses" / TRAIN_SEQ / "poses.txt"


def image_path(root: Path, frame: int, cam: str = "image_02") -> Path:
    return root / "data_2d_raw" / TRAIN_SEQ / cam / "data_rgb" / f"{frame:010d}.png"


def row(T: np.ndarray) -> str:
    return " ".join(f"{v:.10f}" for v in T.reshape(-1))


def change_rotation(path: Path, lineno: int, change) -> int:
    """Replace the rotation of pose line ``lineno`` (1-based) by ``change(R)``; returns its frame index."""
    lines = path.read_text().splitlines()
    fields = lines[lineno - 1].split()
    T = np.array([float(x) for x in fields[1:]]).reshape(3, 4)
    T[:, :3] = change(T[:, :3])
    lines[lineno - 1] = f"{fields[0]} {row(T)}"
    path.write_text("\n".join(lines) + "\n")
    return int(fields[0])


def scaled(R):
    return 1.01 * R


def sheared(R):
    return R @ np.array([[1.0, 0.02, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def mirrored(R):
    return R * np.array([-1.0, 1.0, 1.0])  # first column negated: det -1


# 1. Bad poses ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "change,why",
    [(scaled, "not orthonormal"), (sheared, "not orthonormal"), (mirrored, "det -1")],
)
def test_non_rigid_pose_is_refused_naming_file_and_line(damaged, cache, change, why):
    path = poses_file(damaged)
    frame = change_rotation(path, 4, change)
    message = rf"^{re.escape(str(path))}:4: frame {frame}: not a rigid transform: .*{why}"
    with pytest.raises(ValueError, match=message):
        FisheyeDataset(Kitti360Layout(damaged), [{"sequence": TRAIN_SEQ}], cache_dir=cache)


def test_duplicate_frame_index_is_refused_naming_both_lines(damaged):
    path = poses_file(damaged)
    lines = path.read_text().splitlines()
    frame = int(lines[1].split()[0])
    shifted = lines[1].split()
    shifted[4] = str(float(shifted[4]) + 5.0)  # the same frame, 5 m away: the last line used to win
    path.write_text("\n".join([*lines, " ".join(shifted)]) + "\n")
    message = rf"^{re.escape(str(path))}:{len(lines) + 1}: frame {frame} already has a pose on line 2$"
    with pytest.raises(ValueError, match=message):
        Kitti360Layout(damaged).frames(TRAIN_SEQ)


def test_poses_written_with_real_precision_pass(damaged):
    """KITTI-360 writes ~1e-9 precise rotations; even 6 significant digits stay far inside the tolerance."""
    path = poses_file(damaged)
    exact = read_poses(path)
    lines = [
        " ".join([line.split()[0], *(f"{float(v):.5e}" for v in line.split()[1:])])
        for line in path.read_text().splitlines()
    ]
    path.write_text("\n".join(lines) + "\n")
    rounded = read_poses(path)
    assert sorted(rounded) == sorted(exact) and len(exact) == 6
    for k, T in exact.items():
        assert np.abs(rounded[k] - T).max() < 1e-4


def test_real_kitti360_extrinsics_pass_the_rigidity_check(realdata):
    E = read_cam_to_pose(realdata / "kitti360_frame" / "calib_cam_to_pose.txt")
    assert sorted(E) == ["image_00", "image_01", "image_02", "image_03"]
    assert E["image_02"][0, 3] == pytest.approx(0.7264036936)


def test_non_rigid_extrinsic_names_file_line_and_camera(damaged):
    path = damaged / "calibration" / "calib_cam_to_pose.txt"
    lines = path.read_text().splitlines()
    lineno = next(i for i, line in enumerate(lines, start=1) if line.startswith("image_03:"))
    T = np.array([float(x) for x in lines[lineno - 1].split()[1:]]).reshape(3, 4)
    T[:, :3] *= 1.05
    lines[lineno - 1] = f"image_03: {row(T)}"
    path.write_text("\n".join(lines) + "\n")
    message = rf"^{re.escape(str(path))}:{lineno}: camera 'image_03': not a rigid transform: its rotation"
    with pytest.raises(ValueError, match=message):
        Kitti360Layout(damaged)


def test_duplicate_extrinsic_line_is_refused(damaged):
    path = damaged / "calibration" / "calib_cam_to_pose.txt"
    lines = path.read_text().splitlines()
    first = next(i for i, line in enumerate(lines, start=1) if line.startswith("image_02:"))
    path.write_text("\n".join([*lines, lines[first - 1]]) + "\n")
    message = rf"^{re.escape(str(path))}:{len(lines) + 1}: camera 'image_02' already given on line {first}"
    with pytest.raises(ValueError, match=message):
        Kitti360Layout(damaged)


def write_tiny_rig(root: Path, stamps: list[int], xs: list[float], images: list[int]) -> Path:
    """A one-camera rig recording: poses at ``stamps`` (x translation ``xs``), images at ``images``."""
    cam = kitti02().resize(64, 64)
    rig = {"cameras": [{"name": "cam", "model": cam.to_dict(), "cam_to_body": np.eye(4)[:3].tolist()}]}
    (root / "drive" / "images" / "cam").mkdir(parents=True)
    (root / "rig.yaml").write_text(yaml.safe_dump(rig))
    lines = ["# timestamp_ns tx ty tz qx qy qz qw"]
    lines += [f"{t} {x} 0 0 0 0 0 1" for t, x in zip(stamps, xs, strict=True)]
    (root / "drive" / "poses.txt").write_text("\n".join(lines) + "\n")
    for t in images:
        cv2.imwrite(str(root / "drive" / "images" / "cam" / f"{t}.png"), np.zeros((64, 64, 3), np.uint8))
    return root / "drive" / "poses.txt"


def test_rig_duplicate_timestamp_names_the_lines(tmp_path):
    t0 = 1_700_000_000_000_000_000
    path = write_tiny_rig(tmp_path, [t0, t0 + 10**8, t0], [0.0, 1.0, 5.0], [t0 + 5 * 10**7])
    with pytest.raises(
        ValueError, match=rf"^{re.escape(str(path))}:4: timestamp {t0} already has a pose on line 2"
    ):
        RigLayout(tmp_path).frames("drive", "cam")


def test_rig_timestamps_are_exact_to_the_nanosecond(tmp_path):
    """Timestamps of today (~1.7e18 ns) 100 ns apart: read as floats they collided (256 ns spacing)."""
    t0 = 1_700_000_000_000_000_000
    write_tiny_rig(tmp_path, [t0, t0 + 100, t0 + 200], [0.0, 1.0, 2.0], [t0 + 50, t0 + 150])
    frames = RigLayout(tmp_path).frames("drive", "cam")
    assert [f.key for f in frames] == [t0 + 50, t0 + 150]
    assert [f.pose[0, 3] for f in frames] == [0.5, 1.5]


# 2. A camera vanishes ----------------------------------------------------------------------------------


def test_missing_calibration_yaml_of_a_recorded_camera_is_an_error(damaged, cache):
    (damaged / "calibration" / "image_02.yaml").unlink()
    yaml_file = damaged / "calibration" / "image_02.yaml"
    message = rf"{re.escape(str(yaml_file))}: calibration file of camera 'image_02' not found"
    with pytest.raises(FileNotFoundError, match=message):
        Kitti360Layout(damaged)
    dm = FisheyeDataModule(damaged, size=(64, 64), cache_dir=cache)  # the synthetic config: cameras null
    with pytest.raises(FileNotFoundError, match=message):
        dm.setup("fit")


@pytest.mark.parametrize("cameras", [None, ["image_02", "image_03"]])
def test_missing_extrinsic_line_is_an_error(damaged, cameras):
    path = damaged / "calibration" / "calib_cam_to_pose.txt"
    lines = path.read_text().splitlines()
    path.write_text("\n".join(line for line in lines if not line.startswith("image_02:")) + "\n")
    with pytest.raises(KeyError, match=rf"{re.escape(str(path))}: no line for camera 'image_02'"):
        Kitti360Layout(damaged, cameras=cameras)


def test_perspective_cameras_are_not_demanded(damaged):
    """KITTI-360's image_00/01 have data_rect folders and extrinsic lines but no yaml: not fisheyes."""
    for cam in ("image_00", "image_01"):
        folder = damaged / "data_2d_raw" / TRAIN_SEQ / cam / "data_rect"
        folder.mkdir(parents=True)
        shutil.copy(image_path(damaged, 2), folder / f"{2:010d}.png")
    assert list(Kitti360Layout(damaged).cameras) == ["image_02", "image_03"]


def test_a_camera_with_images_but_nothing_else_is_named(damaged):
    folder = damaged / "data_2d_raw" / TRAIN_SEQ / "image_04" / "data_rgb"
    folder.mkdir(parents=True)
    with pytest.raises(KeyError, match=r"calib_cam_to_pose.txt: no line for camera 'image_04'"):
        Kitti360Layout(damaged)


def compose_train(overrides):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose(config_name="train", overrides=overrides)


def test_configs_name_their_cameras_and_kitti360_refuses_a_missing_one(damaged, cache):
    assert compose_train([]).data.datamodule.cameras is None  # synthetic: every camera of the chosen rig
    cfg = compose_train(
        ["data=kitti360", f"data.datamodule.root={damaged}", f"data.datamodule.cache_dir={cache}"]
    )
    assert list(cfg.data.datamodule.cameras) == ["image_02", "image_03"]
    (damaged / "calibration" / "image_03.yaml").unlink()
    dm = instantiate(cfg.data.datamodule)
    with pytest.raises(FileNotFoundError, match=r"image_03.yaml: calibration file of camera 'image_03'"):
        dm.layout  # noqa: B018  (the layout is built on first use)


# 3. Grayscale and truncated images ---------------------------------------------------------------------


def grayscale_records(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if "grayscale" in r.getMessage()]


def test_grayscale_camera_warns_once_naming_the_file(damaged, cache, caplog, monkeypatch):
    folder = image_path(damaged, 0, "image_03").parent
    for path in sorted(folder.glob("*.png")):
        cv2.imwrite(str(path), cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2GRAY))
    assert cv2.imread(str(next(folder.glob("*.png"))), cv2.IMREAD_UNCHANGED).ndim == 2
    caplog.set_level(logging.WARNING)
    for size in (None, (64, 64)):
        ds = FisheyeDataset(Kitti360Layout(damaged), [{"sequence": TRAIN_SEQ}], size=size, cache_dir=cache)
        samples = [ds[i] for i in range(len(ds))]
    messages = grayscale_records(caplog)
    assert len(messages) == 1, messages  # one camera folder, many frames and two sizes: one warning
    assert str(folder) in messages[0] and "replicated to 3 channels" in messages[0]
    grey = [s for s, item in zip(samples, ds.items, strict=True) if item.camera == "image_03"]
    colour = [s for s, item in zip(samples, ds.items, strict=True) if item.camera == "image_02"]
    assert len(grey) == len(colour) == 4
    assert all(torch_equal_channels(s["image"]) for s in grey)
    assert not any(torch_equal_channels(s["image"]) for s in colour)
    # every later read comes from the resize cache, and the start-up probe still reports the camera
    monkeypatch.setattr(data_files, "_reported", set())
    caplog.clear()
    FisheyeDataset(Kitti360Layout(damaged), [{"sequence": TRAIN_SEQ}], size=(64, 64), cache_dir=cache)
    assert len(grayscale_records(caplog)) == 1


def torch_equal_channels(image) -> bool:
    return bool((image[0] == image[1]).all() and (image[1] == image[2]).all())


@pytest.mark.parametrize("size", [None, (64, 64)])
def test_truncated_image_names_the_file_or_is_a_counted_skip(damaged, cache, size):
    path = image_path(damaged, 3)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    ds = FisheyeDataset(Kitti360Layout(damaged), [{"sequence": TRAIN_SEQ}], size=size, cache_dir=cache)
    with pytest.raises(ValueError, match=rf"{re.escape(str(path))}: truncated PNG"):
        [ds[i] for i in range(len(ds))]
    ds = FisheyeDataset(
        Kitti360Layout(damaged), [{"sequence": TRAIN_SEQ}], size=size, skip_bad_frames=True, cache_dir=cache
    )
    batch = collate([ds[i] for i in range(len(ds))])
    # frame 3 is the target of one sample and a neighbour of two others
    assert len(batch.skipped_frames) == 3
    assert all(f"{path}: truncated PNG" in reason for reason in batch.skipped_frames)
    assert batch.image.shape[0] == len(ds) - 3


# 4. A training size of another aspect ratio ------------------------------------------------------------


def aspect_records(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if "training size" in r.getMessage()]


def test_training_size_of_another_aspect_warns_once_per_camera(kitti_data, cache, caplog):
    caplog.set_level(logging.WARNING)
    dm = FisheyeDataModule(kitti_data, size=(96, 64), cache_dir=cache)
    dm.setup("fit")  # train and val: two datasets, still one warning per camera
    messages = aspect_records(caplog)
    assert len(messages) == 2, messages
    for cam, message in zip(("image_02", "image_03"), messages, strict=True):
        assert f"camera {cam} is 256x256" in message and "training size is 96x64" in message
        assert "stretched horizontally" in message
    assert dm.dataset("train")[0]["image"].shape == (3, 64, 96)  # still trains: a warning, not an error


@pytest.mark.parametrize("size", [(128, 128), (129, 128)])
def test_training_size_of_the_same_aspect_is_quiet(kitti_data, cache, caplog, size):
    caplog.set_level(logging.WARNING)
    FisheyeDataModule(kitti_data, size=size, cache_dir=cache).setup("fit")
    assert aspect_records(caplog) == []


# 5. skip_bad_frames without a leading + ----------------------------------------------------------------


@pytest.mark.parametrize("data", ["synthetic", "kitti360", "rig"])
def test_skip_bad_frames_is_declared(data):
    assert compose_train([f"data={data}"]).data.datamodule.skip_bad_frames is False
    cfg = compose_train([f"data={data}", "data.datamodule.skip_bad_frames=true"])
    assert cfg.data.datamodule.skip_bad_frames is True
