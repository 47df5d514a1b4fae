"""Camera rigs for the synthetic world: cameras, camera-to-pose extrinsics, LiDAR and the ego body.

Frames follow KITTI-360: the pose frame is x forward, y right, z down; ``cam_to_pose`` maps a camera
into it; the Velodyne pose is ``E_00 @ inv(T_cam0_to_velo)``.

- ``kitti360``: the side-looking Mei fisheyes image_02 (left) and image_03 (right) with KITTI-360's real
  calibration scaled to the render size and its real extrinsics.
- ``surround4``: four fisheyes looking left (image_02, Mei), right (image_03, Mei), front (image_04,
  Kannala-Brandt) and back (image_05, Kannala-Brandt), like a robot's surround rig.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ...cameras import CameraModel, KannalaBrandtCamera
from ...geometry import make_pose, pose_from_3x4
from ..kitti360.presets import KITTI360_CAM0_TO_VELO, KITTI360_CAM_TO_POSE, kitti360_camera

RIGS = ("kitti360", "surround4")

# The ego vehicle's body as boxes in the pose frame (z down; the ground is at z = +0.73): a cabin with
# the roof 0.37 m below the side fisheyes, and a lower body (bonnet, boot, flanks). The lower part of the
# side fisheyes' images sees the roof and flanks, as in KITTI-360.
EGO_BODY = (
    (np.array([-1.9, -0.62, -0.70]), np.array([0.95, 1.22, 0.55])),
    (np.array([-3.4, -0.70, -0.15]), np.array([1.65, 1.30, 0.55])),
)


def _pose(values) -> np.ndarray:
    return pose_from_3x4(np.asarray(values, dtype=np.float64)).numpy()


def _looking(forward, right, position) -> np.ndarray:
    """Camera-to-pose for a camera whose optical axis is ``forward`` and image x axis ``right``."""
    z, x = np.asarray(forward, float), np.asarray(right, float)
    return make_pose(np.stack((x, np.cross(z, x), z), 1), position).numpy()


@dataclasses.dataclass
class Rig:
    name: str
    cameras: dict[str, CameraModel]  # render-size cameras, as a reader interprets the written files
    written: dict[str, CameraModel]  # what calibration/image_0X.yaml holds (KITTI-360: with p1/p2)
    cam_to_pose: dict[str, np.ndarray]  # every line of calib_cam_to_pose.txt
    cam0_to_velo: np.ndarray

    @property
    def velo_to_pose(self) -> np.ndarray:
        return self.cam_to_pose["image_00"] @ np.linalg.inv(self.cam0_to_velo)


def make_rig(name: str, size: int) -> Rig:
    if name not in RIGS:
        raise ValueError(f"unknown rig {name!r}; one of {RIGS}")
    cam_to_pose = {k: _pose(v) for k, v in KITTI360_CAM_TO_POSE.items()}
    written = {f"image_0{i}": kitti360_camera(i, tangential=True).resize(size, size) for i in (2, 3)}
    cameras = {f"image_0{i}": kitti360_camera(i).resize(size, size) for i in (2, 3)}
    if name == "surround4":
        f = 0.27 * size
        for cam_name, forward, right, position in (
            ("image_04", (1, 0, 0), (0, 1, 0), (1.7, 0.3, -0.95)),
            ("image_05", (-1, 0, 0), (0, -1, 0), (-3.5, 0.3, -0.95)),
        ):
            cam = KannalaBrandtCamera(
                width=size,
                height=size,
                fx=f,
                fy=f,
                cx=(size - 1) / 2,
                cy=(size - 1) / 2,
                k1=0.02,
                k2=-0.004,
                k3=0.0005,
                k4=0.0,
            )
            cameras[cam_name] = written[cam_name] = cam
            cam_to_pose[cam_name] = _looking(forward, right, position)
    return Rig(name, cameras, written, cam_to_pose, _pose(KITTI360_CAM0_TO_VELO))
