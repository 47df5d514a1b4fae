"""Camera models behind one interface: project, unproject, resize, flip, serialise.

See :mod:`fisheyedepth.cameras.base` for the conventions shared by every model.
"""

from .base import CAMERA_MODELS, CameraModel, CameraParameterError, check_plausible
from .calibration_files import CalibratedCamera, read_basalt, read_calibration, read_kalibr
from .double_sphere import DoubleSphereCamera
from .fisheye624 import Fisheye624Camera
from .fov import FovCamera
from .io import (
    CalibrationError,
    camera_from_mapping,
    load_camera,
    load_json,
    load_yaml,
    opencv_yaml,
    save_camera,
)
from .kannala_brandt import KannalaBrandtCamera
from .mei import MeiCamera
from .opencv import OpenCVCamera
from .pinhole import PinholeCamera, pinhole_like
from .rays import RayCache, Rays, compute_rays, erode_field_of_view, pixel_grid
from .unified import ExtendedUnifiedCamera, UnifiedCamera

__all__ = [
    "CAMERA_MODELS",
    "CalibratedCamera",
    "CalibrationError",
    "CameraModel",
    "CameraParameterError",
    "DoubleSphereCamera",
    "ExtendedUnifiedCamera",
    "Fisheye624Camera",
    "FovCamera",
    "KannalaBrandtCamera",
    "MeiCamera",
    "OpenCVCamera",
    "PinholeCamera",
    "RayCache",
    "Rays",
    "UnifiedCamera",
    "camera_from_mapping",
    "check_plausible",
    "compute_rays",
    "erode_field_of_view",
    "load_camera",
    "opencv_yaml",
    "load_json",
    "load_yaml",
    "pinhole_like",
    "pixel_grid",
    "read_basalt",
    "read_calibration",
    "read_kalibr",
    "save_camera",
]
