"""KITTI-360 in one place: its file readers, its folder layout, its LiDAR ground truth and its published
calibration. The synthetic world writes the same layout, so everything here reads both."""

from .files import read_cam_to_pose, read_cam_to_velo, read_poses, read_velodyne
from .layout import Kitti360Layout
from .lidar import OCCLUSION, LidarGroundTruth, occlusion_filter, project_points
from .presets import KITTI360_CAM0_TO_VELO, KITTI360_CAM_TO_POSE, KITTI360_MEI, kitti360_camera

__all__ = [
    "KITTI360_CAM0_TO_VELO",
    "KITTI360_CAM_TO_POSE",
    "KITTI360_MEI",
    "Kitti360Layout",
    "LidarGroundTruth",
    "OCCLUSION",
    "kitti360_camera",
    "occlusion_filter",
    "project_points",
    "read_cam_to_pose",
    "read_cam_to_velo",
    "read_poses",
    "read_velodyne",
]
