"""Kannala-Brandt equidistant fisheye model in OpenCV's ``cv2.fisheye`` convention.

Projection of a point X at incidence angle theta = atan2(sqrt(X^2 + Y^2), Z):
    theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
    u = fx theta_d X / rho + cx,  v = fy theta_d Y / rho + cy,   rho = sqrt(X^2 + Y^2)
Unlike ``cv2.fisheye`` (which goes through X/Z), this works beyond 90 degrees of incidence. The domain
is theta < theta_max, the first angle where theta_d stops increasing (at most pi).
"""

from __future__ import annotations

import dataclasses
import math
from functools import cached_property

import torch
from torch import Tensor

from .base import (
    CameraModel,
    finite_where,
    odd_poly,
    odd_poly_monotone_limit,
    register_model,
    safe_norm,
    solve_odd_poly,
    split_uv,
    split_xyz,
)


@register_model
@dataclasses.dataclass(frozen=True, kw_only=True)
class KannalaBrandtCamera(CameraModel):
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0

    model_name = "kannala_brandt"

    @property
    def _coeffs(self) -> tuple[float, float, float, float]:
        return (self.k1, self.k2, self.k3, self.k4)

    @cached_property
    def _theta_max(self) -> float:
        return odd_poly_monotone_limit(self._coeffs, cap=math.pi)

    @property
    def max_incidence(self) -> float:
        return self._theta_max

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        X, Y, Z = split_xyz(points)
        tiny = torch.finfo(points.dtype).tiny ** 0.5
        rho = safe_norm(points[..., :2])
        theta = torch.atan2(rho, Z)
        theta_d, _ = odd_poly(theta, self._coeffs)
        near_axis = rho <= tiny
        # theta_d / rho, with its limit 1/Z (times the distortion factor, 1 on the axis) where rho -> 0
        scale = torch.where(
            near_axis, 1.0 / finite_where(Z > 0, Z, 1.0), theta_d / finite_where(~near_axis, rho, 1.0)
        )
        valid = (theta < self._theta_max) & (safe_norm(points) > tiny) & ~(near_axis & (Z <= 0))
        uv = torch.stack((self.fx * scale * X + self.cx, self.fy * scale * Y + self.cy), dim=-1)
        return torch.where(valid[..., None], uv, torch.zeros_like(uv)), valid

    def unproject(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        u, v = split_uv(uv)
        mx, my = (u - self.cx) / self.fx, (v - self.cy) / self.fy
        theta_d = torch.sqrt(mx * mx + my * my)
        theta, valid = solve_odd_poly(theta_d, self._coeffs, self._theta_max)
        positive = theta_d > 0
        s = torch.where(
            positive, torch.sin(theta) / finite_where(positive, theta_d, 1.0), torch.ones_like(theta)
        )
        rays = torch.stack((s * mx, s * my, torch.cos(theta)), dim=-1)
        rays = rays / safe_norm(rays, keepdim=True)
        axis = torch.zeros_like(rays)
        axis[..., 2] = 1
        return torch.where(valid[..., None], rays, axis), valid
