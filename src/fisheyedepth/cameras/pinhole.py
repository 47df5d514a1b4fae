"""Pinhole camera: what Monodepth2 assumes, and the "no fisheye projection" ablation.

u = fx X / Z + cx,  v = fy Y / Z + cy,   domain Z > 0.
"""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

from .base import CameraModel, finite_where, register_model, safe_norm, split_uv, split_xyz


@register_model
@dataclasses.dataclass(frozen=True, kw_only=True)
class PinholeCamera(CameraModel):
    fx: float
    fy: float
    cx: float
    cy: float

    model_name = "pinhole"

    @property
    def max_incidence(self) -> float:
        return math.pi / 2

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        X, Y, Z = split_xyz(points)
        valid = Z > torch.finfo(points.dtype).tiny ** 0.5
        inv = 1.0 / finite_where(valid, Z, 1.0)
        uv = torch.stack((self.fx * X * inv + self.cx, self.fy * Y * inv + self.cy), dim=-1)
        return torch.where(valid[..., None], uv, torch.zeros_like(uv)), valid

    def unproject(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        u, v = split_uv(uv)
        rays = torch.stack(((u - self.cx) / self.fx, (v - self.cy) / self.fy, torch.ones_like(u)), dim=-1)
        return rays / safe_norm(rays, keepdim=True), torch.ones_like(u, dtype=torch.bool)


def pinhole_like(camera: CameraModel) -> PinholeCamera:
    """The pinhole camera a pinhole method would assume for ``camera``: same image size, principal
    point, and the fisheye's paraxial focal length (its magnification at the image centre)."""
    fx, fy = camera.paraxial_focal()
    cx, cy = camera.principal_point
    return PinholeCamera(width=camera.width, height=camera.height, fx=fx, fy=fy, cx=cx, cy=cy)
