"""Unified camera model (UCM) and extended unified camera model (EUCM), in the parametrisation of
Usenko, Demmel and Cremers, "The Double Sphere Camera Model" (3DV 2018), the one Basalt and Kalibr-style
calibration tools write.

UCM (Geyer & Daniilidis 2000; Mei & Rives 2007 with ``xi = alpha / (1 - alpha)`` and the focal scaled by
``1 - alpha``). EUCM (Khomenko, Rivas, Aravecchia and Lacroix 2016) replaces the sphere by an ellipsoid;
``beta = 1`` is the UCM. Projection of X = (x, y, z):
    d = sqrt(beta (x^2 + y^2) + z^2)                         (UCM: beta = 1, d = |X|)
    u = fx x / (alpha d + (1 - alpha) z) + cx,   v = fy y / (alpha d + (1 - alpha) z) + cy
Domain: z > -w d with w = alpha / (1 - alpha) if alpha <= 0.5 else (1 - alpha) / alpha; its rim is the
cone at incidence theta_max = atan2(sqrt(1 - w^2), -w sqrt(beta)) (arccos(-w) for the UCM).
Unprojection is closed form:
    m = ((u - cx) / fx, (v - cy) / fy),  r^2 = |m|^2,   needs r^2 < 1 / (beta (2 alpha - 1)) if alpha > 0.5
    m_z = (1 - beta alpha^2 r^2) / (alpha sqrt(1 - (2 alpha - 1) beta r^2) + 1 - alpha)
    ray = (m_x, m_y, m_z) / |(m_x, m_y, m_z)|
(the paper writes the UCM's in Mei's form, ``(xi + sqrt(1 + (1 - xi^2) r'^2)) / (1 + r'^2)
(m'_x, m'_y, 1) - (0, 0, xi)`` with ``m' = (1 - alpha) m``: the same ray, but without a pole at
alpha = 1). For alpha <= 0.5 every pixel has a ray (the image of the domain is the whole plane); for
alpha > 0.5 the image is the disc inside the rim's image.
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


def unified_w(alpha: float) -> float:
    """The domain's slope ``w``: points need ``z > -w d``."""
    return alpha / (1 - alpha) if alpha <= 0.5 else (1 - alpha) / alpha


def unified_theta_max(alpha: float, beta: float) -> float:
    """Incidence of the domain's rim ``z = -w d``: ``tan(theta)^2 = (1 - w^2) / (w^2 beta)``, ``z <= 0``."""
    w = unified_w(alpha)
    return math.atan2(math.sqrt(1 - w * w), -w * math.sqrt(beta))


def unified_project(
    points: Tensor, focal: tuple[float, float, float, float], alpha: float, beta: float
) -> tuple[Tensor, Tensor]:
    """``(uv, valid)`` of the EUCM with ``focal = (fx, fy, cx, cy)`` (the UCM for ``beta = 1``)."""
    fx, fy, cx, cy = focal
    X, Y, Z = split_xyz(points)
    finfo = torch.finfo(points.dtype)
    d = torch.sqrt((beta * (X * X + Y * Y) + Z * Z).clamp_min(finfo.tiny))
    denom = alpha * d + (1 - alpha) * Z
    # The rim is included up to rounding (a few ulps), so that rays unprojected from rim pixels in float32
    # project back; the denominator must stay clear of zero (it vanishes on the rim when alpha <= 0.5).
    slack = 16 * finfo.eps
    valid = (
        (Z > -(unified_w(alpha) + slack) * d)
        & (safe_norm(points) > finfo.tiny**0.5)
        & (denom > finfo.tiny**0.5 * d)
    )
    inv = 1.0 / finite_where(valid, denom, 1.0)
    uv = torch.stack((fx * X * inv + cx, fy * Y * inv + cy), dim=-1)
    return torch.where(valid[..., None], uv, torch.zeros_like(uv)), valid


def unified_unproject(
    uv: Tensor, focal: tuple[float, float, float, float], alpha: float, beta: float
) -> tuple[Tensor, Tensor]:
    """``(rays, valid)``: the closed-form inverse of :func:`unified_project`."""
    fx, fy, cx, cy = focal
    u, v = split_uv(uv)
    mx, my = (u - cx) / fx, (v - cy) / fy
    r2 = mx * mx + my * my
    bend = (2 * alpha - 1) * beta
    inner = 1 - bend * r2
    # alpha <= 0.5: inner >= 1 for every pixel; alpha > 0.5: the circle inner = 0 is the rim's image,
    # included up to the rounding error of inner itself (it cancels to 0 there)
    valid = inner >= -16 * torch.finfo(inner.dtype).eps * (1 + abs(bend) * r2)
    mx, my, r2 = finite_where(valid, mx, 0.0), finite_where(valid, my, 0.0), finite_where(valid, r2, 0.0)
    if bend > 0:  # pixels past the rim's image by rounding only: onto it, so that their ray is the rim's
        shrink = torch.sqrt((1 / (bend * r2.clamp_min(torch.finfo(r2.dtype).tiny))).clamp(max=1.0))
        mx, my, r2 = mx * shrink, my * shrink, r2 * shrink * shrink
    inner = (1 - bend * r2).clamp_min(0)
    if alpha < 1:
        mz = (1 - beta * alpha * alpha * r2) / (alpha * torch.sqrt(inner) + 1 - alpha)
    else:  # the same, (1 - beta r^2) / sqrt(1 - beta r^2), without its 0 / 0 on the rim
        mz = torch.sqrt(inner)
    rays = torch.stack((mx, my, mz), dim=-1)
    rays = rays / safe_norm(rays, keepdim=True)
    axis = torch.zeros_like(rays)
    axis[..., 2] = 1
    return torch.where(valid[..., None], rays, axis), valid


def _check_alpha(alpha: float) -> None:
    if not 0.0 <= alpha <= 1.0:
        raise CameraParameterError("alpha", f"must lie in [0, 1], got {alpha!r}")


@register_model
@dataclasses.dataclass(frozen=True, kw_only=True)
class UnifiedCamera(CameraModel):
    """The unified camera model (UCM) in Usenko et al.'s ``alpha`` form; ``alpha = 0`` is a pinhole."""

    fx: float
    fy: float
    cx: float
    cy: float
    alpha: float

    model_name = "ucm"
    direct_unproject = True

    def _check(self) -> None:
        _check_alpha(self.alpha)

    @property
    def _focal(self) -> tuple[float, float, float, float]:
        return (self.fx, self.fy, self.cx, self.cy)

    @cached_property
    def _theta_max(self) -> float:
        return unified_theta_max(self.alpha, 1.0)

    @property
    def max_incidence(self) -> float:
        return self._theta_max

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        return unified_project(points, self._focal, self.alpha, 1.0)

    def unproject(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        return unified_unproject(uv, self._focal, self.alpha, 1.0)


@register_model
@dataclasses.dataclass(frozen=True, kw_only=True)
class ExtendedUnifiedCamera(CameraModel):
    """The extended unified camera model (EUCM); ``beta = 1`` is the :class:`UnifiedCamera`."""

    fx: float
    fy: float
    cx: float
    cy: float
    alpha: float
    beta: float

    model_name = "eucm"
    direct_unproject = True

    def _check(self) -> None:
        _check_alpha(self.alpha)
        if not self.beta > 0:
            raise CameraParameterError("beta", f"must be positive, got {self.beta!r}")

    @property
    def _focal(self) -> tuple[float, float, float, float]:
        return (self.fx, self.fy, self.cx, self.cy)

    @cached_property
    def _theta_max(self) -> float:
        return unified_theta_max(self.alpha, self.beta)

    @property
    def max_incidence(self) -> float:
        return self._theta_max

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        return unified_project(points, self._focal, self.alpha, self.beta)

    def unproject(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        return unified_unproject(uv, self._focal, self.alpha, self.beta)
