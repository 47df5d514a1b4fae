"""A rig's relative pose refined from its images: feature matches between two cameras, and the rotation and
translation direction that minimise the epipolar error on the unit sphere. The baseline's length is kept
(the calibration's or the odometry's), so the refined pose stays metric.

For bearings ``f_a`` (camera a) and ``f_b`` (camera b) of one scene point and ``X_b = R X_a + t``, the
point, both centres and both bearings lie in one plane: ``f_b . (t x R f_a) = 0``. The error of a match
is the angle between ``f_b`` and that epipolar plane, ``asin(|f_b . n|)`` with ``n = t x R f_a / |t x R
f_a|``; the pose minimises a robust (Cauchy) sum of those angles over matches that the starting pose
already nearly explains. Nothing is rectified: matches beyond 90 degrees of incidence count like the rest.
A few pixels of the calibration's error are what stops sweep stereo (a degree turned one real pair from
0.15 into 0.43 abs_rel); this is what removes them.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np
import torch
from torch import Tensor

from ..cameras.base import CameraModel
from ..geometry.se3 import axis_angle_to_matrix, make_pose


class Matches(NamedTuple):
    rays_a: Tensor  # [N, 3] float64 unit bearings in camera a
    rays_b: Tensor  # [N, 3] float64 unit bearings in camera b
    uv_a: np.ndarray  # [N, 2] pixels
    uv_b: np.ndarray

    @staticmethod
    def pooled(found: list[Matches]) -> Matches:
        """The matches of several image pairs of the same two cameras, as one set (empty for none)."""
        empty = Matches(torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, 3, dtype=torch.float64),
                        np.zeros((0, 2)), np.zeros((0, 2)))  # fmt: skip
        return Matches(
            torch.cat([m.rays_a for m in (empty, *found)]),
            torch.cat([m.rays_b for m in (empty, *found)]),
            np.concatenate([m.uv_a for m in (empty, *found)]),
            np.concatenate([m.uv_b for m in (empty, *found)]),
        )


class Refinement(NamedTuple):
    T_a_to_b: Tensor  # [4, 4] float64: the refined pose, with the starting baseline's length
    rotation_deg: float  # the correction's rotation angle
    direction_deg: float  # the change of b's centre's direction seen from a (0 with direction=False)
    error_before_px: float  # median epipolar error of the inliers, in pixels of camera b (paraxial focal)
    error_after_px: float
    inliers: int
    matches: int


def to_uint8(image: Tensor | np.ndarray) -> np.ndarray:
    """An ``[H, W]``, ``[1|3, H, W]`` or ``[1, 1|3, H, W]`` image in [0, 1] (or 0-255) as 8-bit grey."""
    array = (
        image.detach().cpu().float().numpy() if isinstance(image, Tensor) else np.asarray(image, np.float32)
    )
    array = array.squeeze()
    if array.ndim == 3:
        array = array.mean(0) if array.shape[0] == 3 else array.mean(-1)
    scale = 255.0 if array.max() <= 1.0 else 1.0
    return np.clip(array * scale, 0, 255).astype(np.uint8)


def match_features(
    image_a, camera_a: CameraModel, image_b, camera_b: CameraModel, ratio: float = 0.8, features: int = 4000
) -> Matches:
    """SIFT matches between the two images (Lowe's ratio test, kept only when mutual), as unit bearings of
    pixels that have a ray."""
    sift = cv2.SIFT_create(nfeatures=features)
    found = [sift.detectAndCompute(to_uint8(image), None) for image in (image_a, image_b)]
    (keys_a, desc_a), (keys_b, desc_b) = found
    empty = Matches.pooled([])
    if desc_a is None or desc_b is None or len(keys_a) < 2 or len(keys_b) < 2:
        return empty
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    forward = matcher.knnMatch(desc_a, desc_b, k=2)
    backward = {m.queryIdx: m.trainIdx for m, *_ in matcher.knnMatch(desc_b, desc_a, k=1) if m}
    pairs = [
        (m.queryIdx, m.trainIdx)
        for m, n in (p for p in forward if len(p) == 2)
        if m.distance < ratio * n.distance and backward.get(m.trainIdx) == m.queryIdx
    ]
    if not pairs:
        return empty
    uv_a = np.array([keys_a[i].pt for i, _ in pairs], np.float64)
    uv_b = np.array([keys_b[j].pt for _, j in pairs], np.float64)
    rays_a, ok_a = camera_a.unproject(torch.from_numpy(uv_a))
    rays_b, ok_b = camera_b.unproject(torch.from_numpy(uv_b))
    ok = (ok_a & ok_b).numpy()
    return Matches(rays_a[ok], rays_b[ok], uv_a[ok], uv_b[ok])


def epipolar_angles(rays_a: Tensor, rays_b: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """``[N]`` radians: each bearing of b's angle to the epipolar plane of its match in a."""
    normal = torch.linalg.cross(t.expand_as(rays_a), rays_a @ R.T, dim=-1)
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    return torch.asin((rays_b * normal).sum(-1).abs().clamp(max=1.0))


def _tangent_basis(t: Tensor) -> Tensor:
    """``[2, 3]``: two unit vectors perpendicular to ``t`` and to each other."""
    helper = torch.zeros_like(t)
    helper[int(t.abs().argmin())] = 1.0
    e1 = torch.linalg.cross(t, helper)
    e1 = e1 / e1.norm()
    return torch.stack((e1, torch.linalg.cross(t / t.norm(), e1)))


def refine_relative_pose(
    matches: Matches,
    T_a_to_b: Tensor,
    focal_px: float,
    gate_deg: float = 3.0,
    scale_px: float = 0.5,
    iterations: int = 30,
    direction: bool = True,
) -> Refinement:
    """The pose ``T_a_to_b`` (``X_b = R X_a + t``) refined on ``matches``: Gauss-Newton on Cauchy-weighted
    epipolar angles (scale ``scale_px`` pixels at ``focal_px``), over the inliers within ``gate_deg`` of
    the starting pose, the gate halved after each solve down to 4 ``scale_px``. Camera b turns about its
    own centre, and with ``direction`` that centre also moves on the sphere of radius ``|t|`` around a's:
    the baseline's length is kept, and with ``direction=False`` b's centre as seen from a too (only the
    rotation is refined: a short baseline before a far scene constrains its direction weakly, and a rig's
    lever arm is often measured better than its angles)."""
    T0 = torch.as_tensor(T_a_to_b, dtype=torch.float64)
    R0, t0 = T0[:3, :3], T0[:3, 3]
    length = float(t0.norm())
    if length <= 0:
        raise ValueError("T_a_to_b: the baseline has no length; a pure rotation has no epipolar geometry")
    if len(matches.rays_a) < 8:
        raise ValueError(
            f"matches: {len(matches.rays_a)} feature matches; at least 8 are needed to refine a pose"
        )
    a, b = matches.rays_a.to(torch.float64), matches.rays_b.to(torch.float64)
    direction0, basis = t0 / length, _tangent_basis(t0 / length)
    scale = scale_px / focal_px

    def pose(x: Tensor) -> tuple[Tensor, Tensor]:
        turn = axis_angle_to_matrix(x[:3])  # b turned about its centre carries t = -R c_b along
        direction = turn @ (direction0 + x[3:] @ basis)
        return turn @ R0, direction / direction.norm()

    x = torch.zeros(5, dtype=torch.float64)
    before = epipolar_angles(a, b, R0, direction0)
    gate = math.radians(gate_deg)
    inliers = before < gate
    for _ in range(iterations):
        if int(inliers.sum()) < 8:
            raise ValueError(
                f"matches: {int(inliers.sum())} of {len(a)} feature matches agree with the starting pose "
                f"within {gate_deg} degrees; the calibration is too far off (or the images do not overlap)"
            )
        A, B = a[inliers], b[inliers]

        def residual(x: Tensor, A=A, B=B) -> Tensor:
            R, direction = pose(x)
            normal = torch.linalg.cross(direction.expand_as(A), A @ R.T, dim=-1)
            return (B * normal).sum(-1) / normal.norm(dim=-1).clamp(min=1e-12)  # sin of the angle, signed

        r = residual(x)
        J = torch.func.jacfwd(residual)(x)  # [N, 5]: five forward passes
        w = 1 / (1 + (r / scale) ** 2)  # Cauchy weights (iteratively reweighted least squares)
        H = J.T @ (w[:, None] * J) + 1e-12 * torch.eye(5, dtype=torch.float64)
        step = -torch.linalg.solve(H, J.T @ (w * r))
        if not direction:
            step[3:] = 0
        x = x + step
        gate = max(gate / 2, 4 * scale)
        inliers = epipolar_angles(a, b, *pose(x)) < gate
        if float(step.norm()) < 1e-10 and gate == 4 * scale:
            break
    R, direction = pose(x)
    kept = epipolar_angles(a, b, R, direction) < 4 * scale
    cos_rotation = ((torch.trace(R @ R0.T) - 1) / 2).clamp(-1, 1)
    centre, centre0 = R.T @ direction, R0.T @ direction0  # b's centre seen from a, over the baseline
    return Refinement(
        T_a_to_b=make_pose(R, direction * length),
        rotation_deg=math.degrees(float(torch.acos(cos_rotation))),
        direction_deg=math.degrees(float(torch.acos((centre @ centre0).clamp(-1, 1)))),
        error_before_px=float(before[kept].median()) * focal_px if kept.any() else float("nan"),
        error_after_px=float(epipolar_angles(a[kept], b[kept], R, direction).median()) * focal_px,
        inliers=int(kept.sum()),
        matches=len(a),
    )


def refine_pair(
    image_a, camera_a: CameraModel, image_b, camera_b: CameraModel, T_a_to_b: Tensor, direction: bool = True
) -> Refinement:
    """:func:`match_features` then :func:`refine_relative_pose`, errors in pixels of camera b."""
    matches = match_features(image_a, camera_a, image_b, camera_b)
    focal = float(np.mean(camera_b.paraxial_focal()))
    return refine_relative_pose(matches, T_a_to_b, focal, direction=direction)
