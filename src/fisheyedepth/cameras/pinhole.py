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
    direct_unproject = True

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


PINHOLE_FOCALS = ("paraxial", "calibration")


def pinhole_like(camera: CameraModel, focal: str = "paraxial") -> PinholeCamera:
    """The pinhole camera a pinhole method would assume for ``camera``: same image size and principal
    point, and as focal length either ``"paraxial"``, the fisheye's magnification at the image centre
    (the pinhole that agrees with it near the axis), or ``"calibration"``, the focal-like parameters as
    the calibration file stores them (Mei's gamma1/gamma2, which are (1 + xi) times the paraxial focal:
    what a pinhole pipeline reading KITTI-360's projection_parameters as K would use)."""
    if focal == "paraxial":
        fx, fy = camera.paraxial_focal()
    elif focal == "calibration":
        fx, fy = getattr(camera, camera._fu), getattr(camera, camera._fv)
    else:
        raise ValueError(f"pinhole focal {focal!r}: one of {PINHOLE_FOCALS}")
    cx, cy = camera.principal_point
    return PinholeCamera(width=camera.width, height=camera.height, fx=fx, fy=fy, cx=cx, cy=cy)
