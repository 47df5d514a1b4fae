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
    odd_poly_monotone_limit,
    register_model,
    split_uv,
    theta_poly_project,
    theta_poly_rays,
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
    direct_unproject = True

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
        xr, yr, valid = theta_poly_project(points, self._coeffs, self._theta_max)
        uv = torch.stack((self.fx * xr + self.cx, self.fy * yr + self.cy), dim=-1)
        return torch.where(valid[..., None], uv, torch.zeros_like(uv)), valid

    def unproject(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        u, v = split_uv(uv)
        return theta_poly_rays(
            (u - self.cx) / self.fx, (v - self.cy) / self.fy, self._coeffs, self._theta_max
        )
