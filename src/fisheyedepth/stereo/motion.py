"""A time pair's motion checked against its images (:func:`check_motion`): the odometry's pose refined
from its images' feature matches where that is worth it, and the pair left out, and why said, where its
images do not explain its motion to about a pixel."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from ..cameras.base import CameraModel
from .features import Features, match_described
from .refine import MIN_MOTION_INLIERS, refine_relative_pose, worth_it


class MotionCheck(NamedTuple):
    """One camera's motion between two of its images, as its images see it (:func:`check_motion`)."""

    T_a_to_b: np.ndarray  # [4, 4] float64: the pose to match with (refined where that is worth it)
    before_px: float  # median epipolar error of the matches under the odometry's pose, pixels of camera b
    after_px: float  # the same under the pose matched with
    inliers: int
    matches: int
    applied: bool
    left_out: str | None  # why the pair cannot be trusted, None where it can
    residual: float = 0.0  # radians: ``after_px`` as an angle, what fusion counts against the pair

    def record(self) -> dict:
        return {"epipolar_px_before": _rounded(self.before_px), "epipolar_px_after": _rounded(self.after_px),
                "inliers": self.inliers, "matches": self.matches, "refined": self.applied,
                "left_out": self.left_out}  # fmt: skip


def _rounded(value: float) -> float | None:
    return round(value, 3) if math.isfinite(value) else None


# A time pair is matched when its images explain its pose to about a pixel (what SGBM needs on its
# epipolar rows), from at least MIN_MOTION_INLIERS feature matches.
MAX_MOTION_RESIDUAL_PX = 1.0
# SIFT features an image brings to the motion check: a thousand leave hundreds of matches (a 968x608
# camera moving 1.3 m: 483 of 485), and matching them takes a tenth of the time four thousand take
MOTION_FEATURES = 1000


def check_motion(
    found_a: Features, camera_a: CameraModel, found_b: Features, camera_b: CameraModel, T_a_to_b: np.ndarray
) -> MotionCheck:
    """A time pair's pose (the odometry's ``T_a_to_b``) checked and refined from its images' feature
    matches: rotation and the direction of travel (:func:`refine_relative_pose`, the odometry's length
    kept), applied where it lowers the epipolar error by more than what it leaves (:func:`worth_it`). The
    pair is left out, and why said, where its matches are too few to check it or where the error left is
    over :data:`MAX_MOTION_RESIDUAL_PX`: odometry is not a calibration (a hand-held camera's poses were 2.6-9
    px inconsistent with its images)."""
    matches = match_described(found_a, camera_a, found_b, camera_b)
    focal = float(np.mean(camera_b.paraxial_focal()))
    nan = float("nan")
    if len(matches.rays_a) < MIN_MOTION_INLIERS:
        why = f"{len(matches.rays_a)} feature matches between its images; its motion cannot be checked"
        return MotionCheck(np.asarray(T_a_to_b), nan, nan, 0, len(matches.rays_a), False, why)
    try:
        refined = refine_relative_pose(matches, torch.as_tensor(T_a_to_b, dtype=torch.float64), focal)
    except ValueError as err:
        return MotionCheck(np.asarray(T_a_to_b), nan, nan, 0, len(matches.rays_a), False, str(err))
    applied = worth_it(refined)
    T = refined.T_a_to_b.numpy() if applied else np.asarray(T_a_to_b, np.float64)
    after = refined.error_after_px if applied else refined.error_before_px
    why = None
    if refined.inliers < MIN_MOTION_INLIERS:
        why = f"{refined.inliers} of {refined.matches} feature matches fit its motion; too few to check it"
    elif not after <= MAX_MOTION_RESIDUAL_PX:
        why = (
            f"its images leave {after:.2f} px of epipolar error under its motion (refined: "
            f"{refined.error_after_px:.2f} px); stereo needs about {MAX_MOTION_RESIDUAL_PX:g}"
        )
    return MotionCheck(T, refined.error_before_px, after, refined.inliers, refined.matches, applied, why,
                       after / focal)  # fmt: skip
