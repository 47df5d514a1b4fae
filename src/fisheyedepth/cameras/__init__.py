"""Camera models behind one interface: project, unproject, resize, flip, serialise.

See :mod:`fisheyedepth.cameras.base` for the conventions shared by every model.
"""

from .base import CAMERA_MODELS, CameraModel, CameraParameterError
from .double_sphere import DoubleSphereCamera
from .fisheye624 import Fisheye624Camera
from .io import CalibrationError, camera_from_mapping, load_camera, load_yaml, opencv_yaml, save_camera
from .kannala_brandt import KannalaBrandtCamera
from .mei import MeiCamera
from .pinhole import PinholeCamera, pinhole_like
from .rays import RayCache, Rays, compute_rays, erode_field_of_view, pixel_grid

__all__ = [
    "CAMERA_MODELS",
    "CalibrationError",
    "CameraModel",
    "CameraParameterError",
    "DoubleSphereCamera",
    "Fisheye624Camera",
    "KannalaBrandtCamera",
    "MeiCamera",
    "PinholeCamera",
    "RayCache",
    "Rays",
    "camera_from_mapping",
    "compute_rays",
    "erode_field_of_view",
    "load_camera",
    "opencv_yaml",
    "load_yaml",
    "pinhole_like",
    "pixel_grid",
    "save_camera",
]
