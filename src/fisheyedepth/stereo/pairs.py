"""Real image pairs with metric ground truth that ship with installable packages, as sweep-stereo views.

- Middlebury 2014 *Motorcycle* (``skimage.data.stereo_motorcycle()``, scikit-image, a development
  dependency): a rectified pinhole pair, 741x500, downsampled 4x from the benchmark, with its calibration
  (focal 994.978 px, principal point (311.193, 254.877), right principal point 31.086 px further right,
  baseline 193.001 mm) and the ground-truth disparity ``d``: depth ``z = f b / (d + doffs)``, distance
  along the ray ``z |ray| / ray_z``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..cameras import PinholeCamera
from ..cameras.rays import compute_rays
from ..geometry.se3 import make_pose
from .sweep import View

MOTORCYCLE = {"f": 994.978, "cx": 311.193, "cy": 254.877, "doffs": 31.086, "baseline": 0.193001}


class RealPair(NamedTuple):
    name: str
    reference: View
    source: View
    distance: Tensor  # [H, W] metres along the reference's rays, 0 without ground truth


def motorcycle() -> RealPair:
    """Middlebury 2014 Motorcycle as a reference (left) and a source (right) view with the exact geometry
    of its calibration. Needs scikit-image (``pip install scikit-image``)."""
    try:
        from skimage.data import stereo_motorcycle
    except ImportError as err:  # pragma: no cover - a development dependency
        raise ImportError("the Middlebury pair ships with scikit-image: pip install scikit-image") from err
    left, right, disparity = stereo_motorcycle()
    height, width = left.shape[:2]
    c = MOTORCYCLE
    left_camera = PinholeCamera(width=width, height=height, fx=c["f"], fy=c["f"], cx=c["cx"], cy=c["cy"])
    right_camera = PinholeCamera(
        width=width, height=height, fx=c["f"], fy=c["f"], cx=c["cx"] + c["doffs"], cy=c["cy"]
    )
    disparity = np.where(np.isfinite(disparity), disparity, 0).astype(np.float64)
    z = np.where(disparity > 0, c["f"] * c["baseline"] / (disparity + c["doffs"]), 0.0)
    rays, _ = compute_rays(left_camera, dtype=torch.float64)
    distance = torch.from_numpy(z) / rays[..., 2]
    T_left_to_right = make_pose(torch.eye(3, dtype=torch.float64), torch.tensor([-c["baseline"], 0.0, 0.0]))

    def image(rgb: np.ndarray) -> Tensor:
        return torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255

    return RealPair(
        "middlebury_motorcycle",
        View(image(left), left_camera, torch.eye(4)),
        View(image(right), right_camera, T_left_to_right.float()),
        distance.float(),
    )
