"""Unified (Mei & Rives 2007) omnidirectional camera with radial-tangential distortion.

Projection of a point X (camera frame):
    s = X / |X|                                  point on the unit sphere
    x = s_x / (s_z + xi),  y = s_y / (s_z + xi)  mirror: projection from (0, 0, -xi)
    r^2 = x^2 + y^2,  rad = 1 + k1 r^2 + k2 r^4
    x_d = x rad + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y rad + p1 (r^2 + 2 y^2) + 2 p2 x y
    u = gamma1 x_d + u0,  v = gamma2 y_d + v0

Domain: the sphere points with s_z > -min(xi, 1/xi). For xi > 1 (KITTI-360: 2.2 and 2.55) the map
from the sphere to the plane folds at theta_max = arccos(-1/xi), where r reaches 1/sqrt(xi^2 - 1);
points beyond it would land on pixels already used by points inside it. A radial distortion that
stops increasing bounds the domain too.

Unprojection inverts the distortion (Newton with a bisection safeguard on the radial polynomial,
then a 2-D Newton step with the analytic Jacobian when p1/p2 are set) and lifts with the closed form
    f = (xi + sqrt(1 + (1 - xi^2) r^2)) / (1 + r^2),  ray = (f x, f y, f - xi).
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
    odd_poly_monotone_limit,
    register_model,
    safe_norm,
    solve_odd_poly,
    split_uv,
    split_xyz,
)


@register_model
@dataclasses.dataclass(frozen=True, kw_only=True)
class MeiCamera(CameraModel):
    xi: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    gamma1: float
    gamma2: float
    u0: float
    v0: float

    model_name = "mei"
    _fu, _fv, _cu, _cv = "gamma1", "gamma2", "u0", "v0"

    def _check(self) -> None:
        if self.xi < 0:
            raise CameraParameterError("xi", f"mirror parameter must be >= 0, got {self.xi!r}")

    @property
    def has_tangential(self) -> bool:
        return self.p1 != 0.0 or self.p2 != 0.0

    @property
    def direct_unproject(self) -> bool:  # the tangential terms need a two-dimensional Newton iteration
        return not self.has_tangential

    # -------------------------------------------------------------- domain
    @cached_property
    def _z_min(self) -> float:
        """Sphere points need s_z > _z_min = -min(xi, 1/xi)."""
        if self.xi == 0.0:
            return 0.0
        return -min(self.xi, 1.0 / self.xi)

    @cached_property
    def _r_mirror_max(self) -> float:
        return 1.0 / math.sqrt(self.xi**2 - 1.0) if self.xi > 1.0 else math.inf

    @cached_property
    def _r_max(self) -> float:
        """Largest undistorted radius on the normalised plane inside the domain."""
        return odd_poly_monotone_limit((self.k1, self.k2), cap=self._r_mirror_max)

    @property
    def max_incidence(self) -> float:
        r = self._r_max
        if r >= self._r_mirror_max:  # bounded by the mirror alone: theta_max = arccos(-min(xi, 1/xi))
            return math.acos(self._z_min)
        # sphere point of radius r on the plane: the lift, then its angle to the axis
        f = (self.xi + math.sqrt(max(0.0, 1 + (1 - self.xi**2) * r * r))) / (1 + r * r)
        return math.atan2(f * r, f - self.xi)

    def paraxial_focal(self) -> tuple[float, float]:
        return self.gamma1 / (1 + self.xi), self.gamma2 / (1 + self.xi)

    def _flip_extra(self) -> dict[str, float]:
        # x -> -x leaves the radial terms and p1 unchanged and flips the sign of p2's contribution.
        return {"p2": -self.p2}

    # -------------------------------------------------------------- distortion
    def _distort(self, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
        r2 = x * x + y * y
        rad = 1 + r2 * (self.k1 + self.k2 * r2)
        if not self.has_tangential:
            return x * rad, y * rad
        xy = x * y
        xd = x * rad + 2 * self.p1 * xy + self.p2 * (r2 + 2 * x * x)
        yd = y * rad + self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * xy
        return xd, yd

    def _jacobian(self, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """d(x_d, y_d) / d(x, y) of the radial-tangential distortion."""
        r2 = x * x + y * y
        rad = 1 + r2 * (self.k1 + self.k2 * r2)
        drad = 2 * (self.k1 + 2 * self.k2 * r2)  # d rad / d x = drad * x
        j11 = rad + drad * x * x + 2 * self.p1 * y + 6 * self.p2 * x
        j12 = drad * x * y + 2 * self.p1 * x + 2 * self.p2 * y  # = j21
        j22 = rad + drad * y * y + 6 * self.p1 * y + 2 * self.p2 * x
        return j11, j12, j12, j22

    def _folds(self, x: Tensor, y: Tensor) -> Tensor:
        """True where tangential distortion folds the plane (non-positive Jacobian determinant)."""
        j11, j12, j21, j22 = self._jacobian(x, y)
        return j11 * j22 - j12 * j21 <= 0

    def _undistort(self, xd: Tensor, yd: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        rd = torch.sqrt(xd * xd + yd * yd)
        r, ok = solve_odd_poly(rd, (self.k1, self.k2), self._r_max)
        scale = torch.where(rd > 0, r / torch.where(rd > 0, rd, torch.ones_like(rd)), torch.ones_like(rd))
        x, y = xd * scale, yd * scale
        if not self.has_tangential:
            return x, y, ok
        eps = torch.finfo(xd.dtype).eps
        for _ in range(20):  # 2-D Newton from the radial-only solution
            ex, ey = self._distort(x, y)
            ex, ey = ex - xd, ey - yd
            j11, j12, j21, j22 = self._jacobian(x, y)
            det = j11 * j22 - j12 * j21
            det = torch.where(det.abs() > eps, det, torch.ones_like(det))
            dx = (j22 * ex - j12 * ey) / det
            dy = (j11 * ey - j21 * ex) / det
            x, y = x - dx, y - dy
            if bool((torch.maximum(dx.abs(), dy.abs()) <= 4 * eps * (1 + rd)).all()):
                break
        # The radial solve only seeded the iteration (with tangential terms the distorted radius of a
        # valid point can exceed the radial-only bound): validity is decided by the residual, the
        # radial bound and an unfolded Jacobian.
        ex, ey = self._distort(x, y)
        residual = torch.maximum((ex - xd).abs(), (ey - yd).abs())
        ok = (residual <= 1e3 * eps * (1 + rd)) & (x * x + y * y <= self._r_max**2) & ~self._folds(x, y)
        return x, y, ok

    # -------------------------------------------------------------- interface
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        X, Y, Z = split_xyz(points)
        norm = safe_norm(points)
        # x = s_x / (s_z + xi) = X / (Z + xi |X|): no normalisation to the sphere needed
        denom = torch.add(Z, norm, alpha=self.xi)
        # The domain's rim is included up to rounding (a few ulps), so that rays unprojected from rim
        # pixels in float32 project back.
        slack = 16 * torch.finfo(points.dtype).eps
        valid = (
            (Z > (self._z_min - slack) * norm) & (norm > torch.finfo(points.dtype).tiny ** 0.5) & (denom > 0)
        )
        inv = 1.0 / finite_where(valid, denom, 1.0)
        x, y = X * inv, Y * inv
        if math.isfinite(self._r_max):
            valid = valid & (x * x + y * y <= self._r_max**2 * (1 + slack))
        if self.has_tangential:
            valid = valid & ~self._folds(x, y)
        xd, yd = self._distort(x, y)
        uv = torch.stack((self.gamma1 * xd + self.u0, self.gamma2 * yd + self.v0), dim=-1)
        return torch.where(valid[..., None], uv, torch.zeros_like(uv)), valid

    def unproject(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        u, v = split_uv(uv)
        x, y, valid = self._undistort((u - self.u0) / self.gamma1, (v - self.v0) / self.gamma2)
        r2 = x * x + y * y
        disc = 1 + (1 - self.xi * self.xi) * r2
        # rim pixels: allow the rounding error of disc itself (it cancels to 0 at the rim)
        valid = valid & (disc >= -16 * torch.finfo(disc.dtype).eps * (1 + self.xi * self.xi * r2))
        f = (self.xi + torch.sqrt(disc.clamp_min(0))) / (1 + r2)
        rays = torch.stack((f * x, f * y, f - self.xi), dim=-1)
        rays = rays / safe_norm(rays, keepdim=True)
        axis = torch.zeros_like(rays)
        axis[..., 2] = 1
        return torch.where(valid[..., None], rays, axis), valid
