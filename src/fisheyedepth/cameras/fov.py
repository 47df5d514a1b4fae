"""Field-of-view (FOV) camera model (Devernay and Faugeras, "Straight lines have to be straight", 2001).

The distortion maps the undistorted radius r = rho / z (rho = sqrt(x^2 + y^2)) to
    r_d = atan(2 r tan(w / 2)) / w,
w being the field of view of the ideal lens. Written with atan2, as Basalt's ``FovCamera`` does, it holds
for every incidence, beyond 90 degrees included:
    phi = atan2(2 tan(w / 2) rho, z) = w r_d,   u = fx r_d x / rho + cx,   v = fy r_d y / rho + cy
with the limit r_d / rho -> 2 tan(w / 2) / (w z) on the axis. phi increases strictly with the incidence
theta from 0 to pi (it is the angle of the point (cos theta, 2 tan(w / 2) sin theta) of an ellipse), so
the domain is every point but those on the optical axis behind the camera: theta < pi, whatever w.
Unprojection is closed form:
    m = ((u - cx) / fx, (v - cy) / fy),  r_d = |m|,  phi = w r_d   (needs phi < pi)
    ray = (sin(phi) / (2 tan(w / 2)) m / r_d, cos(phi)) / |...|
"""

from __future__ import annotations

import dataclasses
import math
from functools import cached_property

import torch
from torch import Tensor

from .base import (
    CameraModel,
    CameraParameterError,
    finite_where,
    register_model,
    safe_norm,
    split_uv,
    split_xyz,
)


@register_model
@dataclasses.dataclass(frozen=True, kw_only=True)
class FovCamera(CameraModel):
    fx: float
    fy: float
    cx: float
    cy: float
    w: float

    model_name = "fov"
    direct_unproject = True

    def _check(self) -> None:
        if not 0.0 < self.w < math.pi:
            raise CameraParameterError("w", f"field of view must lie in (0, pi) radians, got {self.w!r}")

    @cached_property
    def _two_tan(self) -> float:
        """``2 tan(w / 2)``: the slope of ``phi`` against ``rho / z`` at the axis."""
        return 2 * math.tan(self.w / 2)

    @property
    def max_incidence(self) -> float:
        return math.pi

    def paraxial_focal(self) -> tuple[float, float]:
        # r_d = 2 tan(w / 2) r / w + O(r^3)
        scale = self._two_tan / self.w
        return self.fx * scale, self.fy * scale

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        X, Y, Z = split_xyz(points)
        tiny = torch.finfo(points.dtype).tiny ** 0.5
        rho = safe_norm(points[..., :2])
        near_axis = rho <= tiny
        valid = (safe_norm(points) > tiny) & ~(near_axis & (Z <= 0))
        # invalid points are replaced by the axis, so that nothing below (nor its gradient) is singular
        axis = torch.zeros_like(points)
        axis[..., 2] = 1
        X, Y, Z = split_xyz(torch.where(valid[..., None], points, axis))
        rho = safe_norm(torch.stack((X, Y), dim=-1))
        phi = torch.atan2(self._two_tan * rho, Z)
        scale = torch.where(
            near_axis,
            self._two_tan / (self.w * finite_where(near_axis, Z, 1.0)),
            phi / (self.w * finite_where(~near_axis, rho, 1.0)),
        )
        uv = torch.stack((self.fx * scale * X + self.cx, self.fy * scale * Y + self.cy), dim=-1)
        return torch.where(valid[..., None], uv, torch.zeros_like(uv)), valid

    def unproject(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        u, v = split_uv(uv)
        mx, my = (u - self.cx) / self.fx, (v - self.cy) / self.fy
        rd = torch.sqrt(mx * mx + my * my)
        phi = self.w * rd
        valid = phi < math.pi
        phi = finite_where(valid, phi, 0.0)
        positive = rd > 0
        # sin(phi) / (2 tan(w / 2) r_d), with its limit w / (2 tan(w / 2)) at the centre
        s = torch.where(
            positive,
            torch.sin(phi) / (self._two_tan * finite_where(positive, rd, 1.0)),
            torch.full_like(rd, self.w / self._two_tan),
        )
        rays = torch.stack((s * mx, s * my, torch.cos(phi)), dim=-1)
        rays = rays / safe_norm(rays, keepdim=True)
        axis = torch.zeros_like(rays)
        axis[..., 2] = 1
        return torch.where(valid[..., None], rays, axis), valid
