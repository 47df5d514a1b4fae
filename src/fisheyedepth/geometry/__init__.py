"""Rigid-body helpers and the fisheye photometric warp."""

from .se3 import (
    axis_angle_to_matrix,
    finite_transform,
    invert_pose,
    make_pose,
    mirror_pose_x,
    pose_from_3x4,
    quaternion_to_matrix,
    relative_pose,
    rotation_error_deg,
    transform_points,
    translation_direction_error_deg,
)
from .warp import (
    ALIGN_CORNERS,
    Warp,
    distance_to_depth,
    grid_to_pixels,
    pixels_to_grid,
    project_cameras,
    sample,
    warp_to_source,
)

__all__ = [
    "ALIGN_CORNERS",
    "Warp",
    "axis_angle_to_matrix",
    "distance_to_depth",
    "finite_transform",
    "grid_to_pixels",
    "invert_pose",
    "make_pose",
    "mirror_pose_x",
    "pixels_to_grid",
    "pose_from_3x4",
    "quaternion_to_matrix",
    "project_cameras",
    "relative_pose",
    "rotation_error_deg",
    "sample",
    "transform_points",
    "translation_direction_error_deg",
    "warp_to_source",
]
