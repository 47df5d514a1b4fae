"""Readers of the real image pairs with metric ground truth, each camera with its calibration and the
pose between them:

- Middlebury 2014 *Motorcycle* (``skimage.data.stereo_motorcycle()``, scikit-image, a development
  dependency): a rectified pinhole pair, 741x500, downsampled 4x from the benchmark, with its calibration
  (focal 994.978 px, principal point (311.193, 254.877), right principal point 31.086 px further right,
  baseline 193.001 mm) and the ground-truth disparity ``d``: depth ``z = f b / (d + doffs)``, distance
  along the ray ``z |ray| / ray_z``.
- Aria Digital Twin's two SLAM fisheyes (``adt_slam/``, native Fisheye624, 0.14 m apart, turned 75
  degrees): frames 0 and 1 with rendered depth, each camera the reference once, the stored extrinsics
  (``adt_sample.json``: ``cameras.<name>.T_device_camera``); frame 2 has no depth and serves the rig's
  refinement (:func:`adt_instants`).

A pair is scored on the reference's *overlap* (:func:`overlap`): the pixels with ground truth whose
point, at the ground-truth distance, lands inside the partner's image and field of view.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..cameras import CameraModel, PinholeCamera
from ..cameras.io import field
from ..geometry.se3 import invert_pose, make_pose, transform_points
from .frames import RAYS, Missing, load_adt, one_match, read_json, read_rgb

MOTORCYCLE = {"f": 994.978, "cx": 311.193, "cy": 254.877, "doffs": 31.086, "baseline": 0.193001}
ADT_CAMERAS = ("camera-slam-left", "camera-slam-right")
ADT_INSTANTS = (0, 1, 2)  # the same-instant image pairs of the folder (frames 0 and 1 with depth)


class RealPair(NamedTuple):
    """A reference image and its partner, ``[1, C, H, W]`` in [0, 1], with their cameras; ``T``: ``[4, 4]``
    float64 reference camera to partner (``X_partner = R X + t``, metres); ``distance``: ``[H, W]`` metres
    along the reference's rays, 0 without ground truth."""

    name: str
    image: Tensor
    camera: CameraModel
    partner_image: Tensor
    partner_camera: CameraModel
    T: Tensor
    distance: Tensor


def overlap(pair: RealPair) -> Tensor:
    """``[H, W]`` bool: reference pixels with ground truth whose point, at the ground-truth distance, the
    partner sees inside its image (to its outer edge, -0.5 to W - 0.5 under the pixel-centre convention)."""
    rays, has_ray = RAYS.get(pair.camera, dtype=torch.float64)
    points = rays * pair.distance.double()[..., None]
    uv, visible = pair.partner_camera.project(transform_points(pair.T.double(), points))
    w, h = pair.partner_camera.width, pair.partner_camera.height
    inside = (uv[..., 0] >= -0.5) & (uv[..., 0] <= w - 0.5) & (uv[..., 1] >= -0.5) & (uv[..., 1] <= h - 0.5)
    return has_ray & visible & inside & (pair.distance > 0)


def motorcycle() -> RealPair:
    """Middlebury 2014 Motorcycle, the left image the reference, with the exact geometry of its
    calibration. Needs scikit-image (``pip install scikit-image``)."""
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
    rays, _ = RAYS.get(left_camera, dtype=torch.float64)
    distance = torch.from_numpy(z) / rays[..., 2]
    T = make_pose(
        torch.eye(3, dtype=torch.float64), torch.tensor([-c["baseline"], 0.0, 0.0], dtype=torch.float64)
    )

    def image(rgb: np.ndarray) -> Tensor:
        return torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255

    return RealPair("middlebury_motorcycle", image(left), left_camera, image(right), right_camera, T,
                    distance.float())  # fmt: skip


def adt_extrinsics(path: Path, camera: str) -> Tensor:
    """``cameras.<camera>.T_device_camera`` of ``adt_sample.json``: a 4x4 rigid transform, float64."""
    key = f"cameras.{camera}.T_device_camera"
    value = field(read_json(path), key, path)
    matrix = np.asarray(value, dtype=np.float64) if isinstance(value, list) else np.zeros(0)
    if (
        matrix.shape != (4, 4)
        or not np.isfinite(matrix).all()
        or not np.allclose(matrix[:3, :3] @ matrix[:3, :3].T, np.eye(3), atol=1e-4)
        or not np.allclose(matrix[3], [0, 0, 0, 1])
    ):
        raise ValueError(f"{path}: {key}: expected a 4x4 rigid transform (a rotation and a translation)")
    return torch.from_numpy(matrix)


def adt_left_to_right(folder: Path) -> Tensor:
    """The stored pose of the right SLAM camera relative to the left one, ``[4, 4]`` float64."""
    calibration = folder / "adt_sample.json"
    left_to_device, right_to_device = (adt_extrinsics(calibration, c) for c in ADT_CAMERAS)
    return invert_pose(right_to_device) @ left_to_device


def adt_instants(folder: Path) -> list[tuple[Tensor, Tensor]]:
    """The (left, right) images of every same-instant pair in the folder (:data:`ADT_INSTANTS`), with or
    without depth: what refines the pair's rotation."""
    found = []
    for index in ADT_INSTANTS:
        paths = [one_match(folder, f"{c}_{index}_*.png") for c in ADT_CAMERAS]
        if None not in paths:
            found.append((read_rgb(paths[0]), read_rgb(paths[1])))
    return found


def adt_pairs(folder: Path, T_left_to_right: Tensor | None = None) -> list[RealPair | Missing]:
    """The ADT SLAM pairs with ground truth (frames 0 and 1, left and right each the reference), with
    ``T_left_to_right`` (default: the stored extrinsics, :func:`adt_left_to_right`)."""
    frames = {f.name: f for f in load_adt(folder)}
    gone = [f for f in frames.values() if isinstance(f, Missing)]
    if gone:
        return gone
    T = adt_left_to_right(folder) if T_left_to_right is None else T_left_to_right.double()
    out: list[RealPair | Missing] = []
    for index in (0, 1):
        for ref, src, pose in (("left", "right", T), ("right", "left", invert_pose(T))):
            a, b = frames[f"adt_{ref}_{index}"], frames[f"adt_{src}_{index}"]
            out.append(
                RealPair(
                    f"adt_{ref}_{index}", a.image, a.camera, b.image, b.camera, pose, a.distance * a.mask
                )
            )
    return out
