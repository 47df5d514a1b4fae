"""Double sphere camera model (Usenko, Demmel, Cremers, 3DV 2018).

Projection of X = (x, y, z):
    d1 = |X|,  d2 = sqrt(x^2 + y^2 + (xi d1 + z)^2)
    u = fx x / (alpha d2 + (1 - alpha)(xi d1 + z)) + cx   (v likewise)
Domain: z > -w2 d1 with w1 = alpha / (1 - alpha) if alpha <= 0.5 else (1 - alpha) / alpha and
w2 = (w1 + xi) / sqrt(2 w1 xi + xi^2 + 1). Unprojection is closed form:
    m = ((u - cx) / fx, (v - cy) / fy),  r^2 = |m|^2  (needs r^2 <= 1 / (2 alpha - 1) if alpha > 0.5)
    mz = (1 - alpha^2 r^2) / (alpha sqrt(1 - (2 alpha - 1) r^2) + 1 - alpha)
    ray = (mz xi + sqrt(mz^2 + (1 - xi^2) r^2)) / (mz^2 + r^2) * (mx, my, mz) - (0, 0, xi)
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
class DoubleSphereCamera(CameraModel):
    fx: float
    fy: float
    cx: float
    cy: float
    xi: float
    alpha: float

    model_name = "double_sphere"
    direct_unproject = True

    def _check(self) -> None:
        if not -1.0 < self.xi <= 1.0:
            raise CameraParameterError("xi", f"must lie in (-1, 1], got {self.xi!r}")
        if not 0.0 <= self.alpha < 1.0:
            raise CameraParameterError("alpha", f"must lie in [0, 1), got {self.alpha!r}")

    @cached_property
    def _w2(self) -> float:
        a, xi = self.alpha, self.xi
        w1 = a / (1 - a) if a <= 0.5 else (1 - a) / a
        return (w1 + xi) / math.sqrt(2 * w1 * xi + xi * xi + 1)

    @property
    def max_incidence(self) -> float:
        return math.acos(-self._w2)

    def paraxial_focal(self) -> tuple[float, float]:
        return self.fx / (1 + self.xi), self.fy / (1 + self.xi)

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        X, Y, Z = split_xyz(points)
        d1 = safe_norm(points)
        zx = self.xi * d1 + Z
        d2 = torch.sqrt((X * X + Y * Y + zx * zx).clamp_min(torch.finfo(points.dtype).tiny))
        denom = self.alpha * d2 + (1 - self.alpha) * zx
        valid = (Z > -self._w2 * d1) & (d1 > torch.finfo(points.dtype).tiny ** 0.5) & (denom > 0)
        inv = 1.0 / finite_where(valid, denom, 1.0)
        uv = torch.stack((self.fx * X * inv + self.cx, self.fy * Y * inv + self.cy), dim=-1)
        return torch.where(valid[..., None], uv, torch.zeros_like(uv)), valid

    def unproject(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        u, v = split_uv(uv)
        mx, my = (u - self.cx) / self.fx, (v - self.cy) / self.fy
        r2 = mx * mx + my * my
        a, xi = self.alpha, self.xi
        inner = 1 - (2 * a - 1) * r2
        valid = inner >= 0
        mz = (1 - a * a * r2) / (a * torch.sqrt(inner.clamp_min(0)) + 1 - a)
        k = (mz * xi + torch.sqrt((mz * mz + (1 - xi * xi) * r2).clamp_min(0))) / (mz * mz + r2)
        rays = torch.stack((k * mx, k * my, k * mz - xi), dim=-1)
        rays = rays / safe_norm(rays, keepdim=True)
        # pixels whose lifted ray falls outside the projection domain are not images of any point
        valid = valid & (rays[..., 2] > -self._w2)
        axis = torch.zeros_like(rays)
        axis[..., 2] = 1
        return torch.where(valid[..., None], rays, axis), valid
