"""Rigid transforms as ``[..., 4, 4]`` homogeneous matrices (float32 or float64, any device).

Naming: ``T_a_to_b`` maps points of frame ``a`` into frame ``b``. A pose ``P`` (body to world) and an
extrinsic ``E`` (camera to body) are both such maps.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

# How far a rotation block may be from orthonormal (``|R R^T - I|``, elementwise) and the last row from
# ``0 0 0 1``: files keep rotations to about 1e-9 (KITTI-360) or 1e-6 (float32); a block scaled by 1.01 or
# sheared by half a degree is far beyond it.
RIGID_TOLERANCE = 1e-4


def rigid_problem(T: np.ndarray, tolerance: float = RIGID_TOLERANCE) -> str | None:
    """Why the float ``[4, 4]`` (or ``[3, 4]``) ``T`` is not a rigid transform, or None: a value that is not
    finite, a last row other than ``0 0 0 1``, a rotation block that is scaled, sheared or not a rotation
    (``|R R^T - I|`` over ``tolerance``), or a reflection (det -1)."""
    if T.shape not in ((4, 4), (3, 4)):
        return f"a 4x4 (or 3x4) rigid transform expected, got shape {T.shape}"
    if not np.isfinite(T).all():
        return "not a rigid transform: it holds a value that is not finite"
    if T.shape == (4, 4) and not np.abs(T[3] - (0, 0, 0, 1)).max() <= tolerance:
        last = np.round(T[3], 6).tolist()
        return f"not a rigid transform: the last row of a 4x4 transform must be 0 0 0 1, got {last}"
    R = T[:3, :3]
    error = float(np.abs(R @ R.T - np.eye(3)).max())
    if error > tolerance:
        return (
            f"not a rigid transform: its rotation is not orthonormal (|R R^T - I| = {error:.2g}, "
            f"tolerance {tolerance:g}): scaled, sheared or not a rotation"
        )
    if np.linalg.det(R) < 0:
        return "not a rigid transform: its rotation has det -1 (a reflection: a left-handed frame?)"
    return None


def rigid_transform(T, what: str, tolerance: float = RIGID_TOLERANCE) -> np.ndarray:
    """``T`` (a 4x4 or 3x4 matrix: array, tensor or nested lists) as a 4x4 float64 rigid transform, else a
    ValueError naming ``what`` and why (:func:`rigid_problem`). The one check every transform the project
    accepts goes through: calibrations, the live API's extrinsics and motion, recorded poses."""
    if isinstance(T, Tensor):
        T = T.detach().cpu().numpy()
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(
            f"{what}: a 4x4 matrix of numbers expected, got {type(T).__name__} {T!r:.60}"
        ) from None
    problem = rigid_problem(T, tolerance)
    if problem is not None:
        raise ValueError(f"{what}: {problem}")
    out = np.eye(4)
    out[:3] = T[:3]
    return out


# The farthest two cameras of one rig may lie apart, metres: a car is five metres long, a robot less;
# extrinsics written in millimetres put a rig's cameras hundreds of metres apart.
MAX_RIG_BASELINE = 10.0
# The farthest a body may move between two instants it is matched across, metres: a car at 36 m/s (130
# km/h) with instants 0.28 s apart; beyond it odometry in the wrong unit is the likelier reading.
MAX_MOTION = 10.0


def rig_extent_problem(cam_to_body) -> str | None:
    """Why a rig's extrinsics (``{camera: 4x4 camera -> body}``, metres) cannot be a rig: two cameras over
    :data:`MAX_RIG_BASELINE` apart (named with their distance); else None."""
    centres = {name: np.asarray(T, dtype=np.float64)[:3, 3] for name, T in cam_to_body.items()}
    names = list(centres)
    widest = max(
        (
            (float(np.linalg.norm(centres[a] - centres[b])), a, b)
            for i, a in enumerate(names)
            for b in names[i + 1 :]
        ),
        default=(0.0, "", ""),
    )
    if widest[0] > MAX_RIG_BASELINE:
        return (
            f"cameras {widest[1]!r} and {widest[2]!r} lie {widest[0]:.4g} m apart; a rig's cameras lie "
            f"within {MAX_RIG_BASELINE:g} m of each other (extrinsics are in metres: millimetres?)"
        )
    return None


def make_pose(R, t) -> Tensor:
    """``[..., 4, 4]`` from a rotation ``[..., 3, 3]`` and a translation ``[..., 3]`` (tensors, or arrays
    read as tensors: float64 NumPy in, float64 out; the translation takes the rotation's dtype)."""
    R = torch.as_tensor(R)
    t = torch.as_tensor(t, dtype=R.dtype, device=R.device)
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1
    return T


def pose_from_3x4(values) -> Tensor:
    """A KITTI 3x4 row-major matrix (12 numbers, ``[..., 12]`` or ``[..., 3, 4]``) as ``[..., 4, 4]``."""
    m = torch.as_tensor(values)
    if not m.is_floating_point():
        m = m.to(torch.float64)
    if m.shape[-1] == 12:
        m = m.reshape(*m.shape[:-1], 3, 4)
    if m.shape[-2:] != (3, 4):
        raise ValueError(f"expected 12 numbers or a 3x4 matrix, got shape {tuple(m.shape)}")
    return make_pose(m[..., :3], m[..., 3])


def invert_pose(T: Tensor) -> Tensor:
    """Exact inverse of a rigid transform: ``(R, t)^-1 = (R^T, -R^T t)``."""
    Rt = T[..., :3, :3].transpose(-1, -2)
    return make_pose(Rt, -(Rt @ T[..., :3, 3:4])[..., 0])


def relative_pose(P_t: Tensor, P_s: Tensor, E_t: Tensor, E_s: Tensor | None = None) -> Tensor:
    """``T_{t->s} = E_s^-1 P_s^-1 P_t E_t``: camera at time t to (possibly another) camera at time s.

    ``P``: body-to-world poses at t and s; ``E``: camera-to-body extrinsics of the target camera (t) and
    the source camera (s, default: the same camera). With one camera this is KITTI-360's
    ``E^-1 P_s^-1 P_t E``.
    """
    E_s = E_t if E_s is None else E_s
    return invert_pose(E_s) @ invert_pose(P_s) @ P_t @ E_t


def transform_points(T: Tensor, points: Tensor) -> Tensor:
    """Apply ``T [B, 4, 4]`` (or ``[4, 4]``) to ``points [B, ..., 3]`` (or ``[..., 3]``)."""
    R, t = T[..., :3, :3], T[..., :3, 3]
    if T.dim() == 2:
        return points @ R.transpose(0, 1) + t
    batch = T.shape[:-2]
    flat = points.reshape(*batch, -1, 3)
    out = flat @ R.transpose(-1, -2) + t[..., None, :]
    return out.reshape(points.shape)


def axis_angle_to_matrix(axis_angle: Tensor) -> Tensor:
    """Rodrigues' formula, ``[..., 3] -> [..., 3, 3]``, with a Taylor expansion near zero angle."""
    theta2 = (axis_angle * axis_angle).sum(-1, keepdim=True)[..., None]  # [..., 1, 1]
    small = theta2 < 1e-8
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(theta2_safe)
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2_safe)
    x, y, z = axis_angle.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack((zero, -z, y, z, zero, -x, -y, x, zero), dim=-1).reshape(*axis_angle.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device).expand_as(K)
    return eye + a * K + b * (K @ K)


_MIRROR_X = (-1.0, 1.0, 1.0, 1.0)


def mirror_pose_x(T: Tensor) -> Tensor:
    """The transform between horizontally flipped cameras: ``M T M`` with ``M = diag(-1, 1, 1, 1)``.

    If a camera is flipped (see ``CameraModel.flip``), points are mirrored ``X -> -X`` in both the
    target and the source frame, so the relative pose conjugates by ``M``.
    """
    m = torch.tensor(_MIRROR_X, dtype=T.dtype, device=T.device)
    return T * m[:, None] * m[None, :]


def quaternion_to_matrix(q_xyzw: Tensor) -> Tensor:
    """Unit quaternion ``[..., 4]`` in (x, y, z, w) order (ROS, Aria, scipy) to ``[..., 3, 3]``.

    The quaternion is normalised first, so a slightly denormalised input still gives a rotation.
    """
    q = q_xyzw / torch.linalg.vector_norm(q_xyzw, dim=-1, keepdim=True)
    x, y, z, w = q.unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z),
        2 * (x * y - z * w),
        2 * (x * z + y * w),
        2 * (x * y + z * w),
        1 - 2 * (x * x + z * z),
        2 * (y * z - x * w),
        2 * (x * z - y * w),
        2 * (y * z + x * w),
        1 - 2 * (x * x + y * y),
    )
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def matrix_to_quaternion(R) -> np.ndarray:
    """A rotation matrix ``3 x 3`` as the unit quaternion (x, y, z, w) with ``w >= 0`` (ROS's
    ``geometry_msgs/Quaternion``), by Shepperd's method: the largest of the four squared components first,
    so no division by a small number at any angle, half turns included."""
    m = np.asarray(R, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    squares = (1 + 2 * m[0, 0] - trace, 1 + 2 * m[1, 1] - trace, 1 + 2 * m[2, 2] - trace, 1 + trace)
    largest = int(np.argmax(squares))
    q = np.empty(4)
    q[largest] = np.sqrt(max(squares[largest], 0.0)) / 2
    f = 1 / (4 * q[largest])
    x, y, z, w = range(4)
    pairs = {  # the other three from the off-diagonal sums and differences
        x: ((y, m[0, 1] + m[1, 0]), (z, m[0, 2] + m[2, 0]), (w, m[2, 1] - m[1, 2])),
        y: ((x, m[0, 1] + m[1, 0]), (z, m[1, 2] + m[2, 1]), (w, m[0, 2] - m[2, 0])),
        z: ((x, m[0, 2] + m[2, 0]), (y, m[1, 2] + m[2, 1]), (w, m[1, 0] - m[0, 1])),
        w: ((x, m[2, 1] - m[1, 2]), (y, m[0, 2] - m[2, 0]), (z, m[1, 0] - m[0, 1])),
    }
    for index, value in pairs[largest]:
        q[index] = value * f
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def rotation_error_deg(T_a: Tensor, T_b: Tensor) -> Tensor:
    """Angle (degrees) of the rotation ``R_a^T R_b`` between two ``[..., 4, 4]`` poses."""
    R = T_a[..., :3, :3].transpose(-1, -2) @ T_b[..., :3, :3]
    cos = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.acos(cos))


def translation_direction_error_deg(T_a: Tensor, T_b: Tensor, eps: float = 1e-9) -> Tensor:
    """Angle (degrees) between the translations of two ``[..., 4, 4]`` poses: scale-free, for a PoseNet
    whose translation has no metric scale."""
    a, b = T_a[..., :3, 3], T_b[..., :3, 3]
    cos = (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1)).clamp_min(eps)
    return torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0)))
