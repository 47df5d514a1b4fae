"""The official KITTI-360 layout (and the synthetic world's, which writes the same files)."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ...cameras import load_camera
from ...files import path_name
from ..layouts import CameraSpec, Frame, RecordingFiles, existing
from .files import read_cam_to_pose, read_cam_to_velo, read_poses

log = logging.getLogger(__name__)


_WARNED: set[Path] = set()


def warn_no_mask(camera: str, expected: Path) -> None:
    """Once per process and file: a camera without a body mask scores and samples every pixel, the
    vehicle's own body included (KITTI-360 ships none; the paper masks the body)."""
    if expected in _WARNED:
        return
    _WARNED.add(expected)
    log.warning(
        "camera %s has no body mask (expected %s): every pixel counts as usable, the vehicle's body "
        "included; estimate it from a recording (fisheyedepth-estimate-mask --root ROOT --sequence SEQ "
        "--camera %s), write that PNG yourself (255 = usable) or pass data.datamodule.masks={%s: FILE}",
        camera,
        expected,
        camera,
        camera,
    )


class Kitti360Layout(RecordingFiles):
    """The official KITTI-360 layout (and the synthetic world's)."""

    name = "kitti360"

    def __init__(
        self,
        root: str | os.PathLike,
        cameras: list[str] | None = None,
        masks: dict[str, str | os.PathLike] | None = None,
        keep_tangential: bool = False,
        expect_masks: bool = True,
    ):
        """``expect_masks``: warn (once per file) about a camera without a body mask; off for the
        command that is about to write it. ``mask_paths``: where each camera's mask is read from,
        whether it exists or not."""
        self.root = Path(root)
        calib = self.root / "calibration"
        extrinsics_file = existing(calib / "calib_cam_to_pose.txt", "calibration file")
        extrinsics = read_cam_to_pose(extrinsics_file)
        source = "cameras" if cameras is not None else self.root  # the option, or the folders found
        if cameras is None:
            cameras = self.discover_cameras()
        self.cameras: dict[str, CameraSpec] = {}
        self.mask_paths: dict[str, Path | None] = {}
        for name in cameras:
            path_name(name, "camera", source)  # calibration/<name>.yaml, data_2d_raw/<seq>/<name>/
            if name not in extrinsics:
                raise KeyError(f"{extrinsics_file}: no line for camera {name!r}")
            calibration = existing(calib / f"{name}.yaml", f"calibration file of camera {name!r}")
            camera = load_camera(calibration, keep_tangential)
            mask = Path(masks[name]) if masks and name in masks else calib / f"body_mask_{name}.png"
            if masks and name in masks:
                existing(mask, "body mask")
            if not mask.is_file() and expect_masks:
                warn_no_mask(name, mask)
            self.mask_paths[name] = mask
            self.cameras[name] = CameraSpec(name, camera, extrinsics[name], mask if mask.is_file() else None)
        self.cam_to_pose, self._extrinsics_file = extrinsics, extrinsics_file  # every camera, image_00 too
        self._cam0_to_velo: np.ndarray | None = None
        self._frames: dict[str, list[Frame]] = {}

    def discover_cameras(self) -> list[str]:
        """The fisheye cameras of the dataset: every ``calibration/image_0X.yaml`` and every image folder
        ``data_2d_raw/<seq>/<camera>/data_rgb``. Each must have both a calibration yaml and a line in
        ``calib_cam_to_pose.txt``, checked by the caller, so a camera never vanishes without a word.
        KITTI-360's perspective cameras (``image_00/01``: ``data_rect`` folders, no yaml) are not fisheyes
        and are not demanded."""
        calibrated = {p.stem for p in (self.root / "calibration").glob("image_0*.yaml")}
        recorded = {p.parent.name for p in (self.root / "data_2d_raw").glob("*/*/data_rgb") if p.is_dir()}
        cameras = sorted(calibrated | recorded)
        if not cameras:
            raise FileNotFoundError(
                f"{self.root}: no camera found (no calibration/image_0X.yaml, "
                "no data_2d_raw/<sequence>/<camera>/data_rgb folder)"
            )
        return cameras

    def sequences(self) -> list[str]:
        return sorted(p.name for p in (self.root / "data_poses").iterdir() if (p / "poses.txt").is_file())

    def frames(self, sequence: str, camera: str | None = None) -> list[Frame]:
        """The sequence's frames in ``poses.txt`` row order (the same for every camera)."""
        if sequence not in self._frames:
            path_name(sequence, "sequence", self.root)  # from a split or an option: a folder under root
            poses = read_poses(existing(self.root / "data_poses" / sequence / "poses.txt", "pose file"))
            self._frames[sequence] = [Frame(k, poses[k]) for k in sorted(poses)]
        return self._frames[sequence]

    def image(self, sequence: str, camera: str, frame: Frame) -> Path:
        return self.root / "data_2d_raw" / sequence / camera / "data_rgb" / f"{frame.key:010d}.png"

    def distance(self, sequence: str, camera: str, frame: Frame) -> Path | None:
        path = self.root / "data_2d_distance" / sequence / camera / f"{frame.key:010d}.npy"
        return path if path.is_file() else None

    def moving(self, sequence: str, camera: str, frame: Frame) -> Path | None:
        """The frame's mask of pixels that see a moving object (a PNG, nonzero = moving), if any."""
        path = self.root / "data_2d_moving" / sequence / camera / f"{frame.key:010d}.png"
        return path if path.is_file() else None

    def velo_to_camera(self, camera: str) -> np.ndarray:
        """``inv(E_cam) @ E_00 @ inv(T_cam0_to_velo)``: the Velodyne frame to ``camera``'s frame, from the
        extrinsics parsed at construction and ``calib_cam_to_velo.txt`` (read once, on first use)."""
        if "image_00" not in self.cam_to_pose:
            raise KeyError(
                f"{self._extrinsics_file}: no line for image_00, which the Velodyne is calibrated to"
            )
        if self._cam0_to_velo is None:
            path = existing(self.root / "calibration" / "calib_cam_to_velo.txt", "calibration file")
            self._cam0_to_velo = read_cam_to_velo(path)
        velo_to_pose = self.cam_to_pose["image_00"] @ np.linalg.inv(self._cam0_to_velo)
        return np.linalg.inv(self.cam_to_pose[camera]) @ velo_to_pose

    def lidar(self, sequence: str, frame: Frame) -> Path:
        return self.root / "data_3d_raw" / sequence / "velodyne_points" / "data" / f"{frame.key:010d}.bin"
