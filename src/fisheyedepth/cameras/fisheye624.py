"""Fisheye624: Meta Project Aria's fisheye model, 6 radial, 2 tangential and 4 thin-prism coefficients.

Projection of a point X at incidence angle theta = atan2(sqrt(X^2 + Y^2), Z):
    theta_d = theta (1 + k0 theta^2 + k1 theta^4 + ... + k5 theta^12)
    (x_r, y_r) = theta_d (X, Y) / rho,   rho = sqrt(X^2 + Y^2),   r^2 = x_r^2 + y_r^2
    u_d = x_r + p0 (2 x_r^2 + r^2) + 2 p1 x_r y_r + s0 r^2 + s1 r^4
    v_d = y_r + p1 (2 y_r^2 + r^2) + 2 p0 x_r y_r + s2 r^2 + s3 r^4
    u = fx u_d + cx,  v = fy v_d + cy
Aria stores one focal (``fx = fy = f``); ``params = [f, cx, cy, k0..k5, p0, p1, s0..s3]``
(:meth:`Fisheye624Camera.from_aria`). Aria's own code takes theta = atan(|(X, Y)| / Z), which folds a
point behind the camera onto the one in front; here theta comes from ``atan2``, so rays beyond 90
degrees project where the polynomial puts them. The domain is theta < theta_max, the first angle where
theta_d stops increasing (at most pi), where also the tangential and thin-prism map keeps its orientation
(its Jacobian's determinant > 0). Unprojection inverts that map by Newton's method in two dimensions
(the Jacobian stays close to the identity), then the radial polynomial by safeguarded Newton.
"""

from __future__ import annotations

import dataclasses
import math
import os
from functools import cached_property
from pathlib import Path

import torch
from torch import Tensor

from .base import (
    CameraModel,
    CameraParameterError,
    check_plausible,
    finite_where,
    odd_poly_monotone_limit,
    register_model,
    split_uv,
    theta_poly_project,
    theta_poly_rays,
)

ARIA_MODEL = "FISHEYE624"
ARIA_PARAMS = ("f", "cx", "cy", "k0", "k1", "k2", "k3", "k4", "k5", "p0", "p1", "s0", "s1", "s2", "s3")


@register_model
@dataclasses.dataclass(frozen=True, kw_only=True)
class Fisheye624Camera(CameraModel):
    fx: float
    fy: float
    cx: float
    cy: float
    k0: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    k5: float = 0.0
    p0: float = 0.0
    p1: float = 0.0
    s0: float = 0.0
    s1: float = 0.0
    s2: float = 0.0
    s3: float = 0.0

    model_name = "fisheye624"

    @property
    def _radial(self) -> tuple[float, ...]:
        return (self.k0, self.k1, self.k2, self.k3, self.k4, self.k5)

    @cached_property
    def _theta_max(self) -> float:
        return odd_poly_monotone_limit(self._radial, cap=math.pi)

    @property
    def max_incidence(self) -> float:
        return self._theta_max

    def _flip_extra(self) -> dict[str, float]:
        # the mirrored camera sees (-x_r, y_r): u_d must change sign, v_d not
        return {"p0": -self.p0, "s0": -self.s0, "s1": -self.s1}

    # ------------------------------------------------------------------ the tangential/prism map
    def _distort(self, xr: Tensor, yr: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """``(u_d, v_d)`` of ``(x_r, y_r)`` and the map's Jacobian ``[[a, b], [c, d]]``."""
        r2 = xr * xr + yr * yr
        ud = xr + self.p0 * (2 * xr * xr + r2) + 2 * self.p1 * xr * yr + (self.s0 + self.s1 * r2) * r2
        vd = yr + self.p1 * (2 * yr * yr + r2) + 2 * self.p0 * xr * yr + (self.s2 + self.s3 * r2) * r2
        prism_u = 2 * self.s0 + 4 * self.s1 * r2  # d(s0 r^2 + s1 r^4) / d(x_r) / x_r
        prism_v = 2 * self.s2 + 4 * self.s3 * r2
        a = 1 + 6 * self.p0 * xr + 2 * self.p1 * yr + prism_u * xr
        b = 2 * self.p0 * yr + 2 * self.p1 * xr + prism_u * yr
        c = 2 * self.p1 * xr + 2 * self.p0 * yr + prism_v * xr
        d = 1 + 6 * self.p1 * yr + 2 * self.p0 * xr + prism_v * yr
        return ud, vd, a, b, c, d

    def _undistort(self, mu: Tensor, mv: Tensor, iterations: int = 30) -> tuple[Tensor, Tensor, Tensor]:
        """``(x_r, y_r)`` with ``_distort(x_r, y_r) = (mu, mv)``, and whether Newton converged there."""
        xr, yr = mu.clone(), mv.clone()
        eps = torch.finfo(mu.dtype).eps
        for _ in range(iterations):
            ud, vd, a, b, c, d = self._distort(xr, yr)
            det = a * d - b * c
            det = torch.where(det.abs() > eps, det, torch.full_like(det, eps))
            ru, rv = mu - ud, mv - vd
            xr = xr + (d * ru - b * rv) / det
            yr = yr + (a * rv - c * ru) / det
        ud, vd, a, b, c, d = self._distort(xr, yr)
        residual = torch.sqrt((ud - mu) ** 2 + (vd - mv) ** 2)
        scale = 1.0 + torch.sqrt(mu * mu + mv * mv)
        converged = torch.isfinite(residual) & (residual <= 1e3 * eps * scale) & (a * d - b * c > 0)
        return xr, yr, converged

    # ------------------------------------------------------------------ the interface
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        xr, yr, valid = theta_poly_project(points, self._radial, self._theta_max)
        ud, vd, a, b, c, d = self._distort(xr, yr)
        valid = valid & (a * d - b * c > 0) & torch.isfinite(ud) & torch.isfinite(vd)
        uv = torch.stack((self.fx * ud + self.cx, self.fy * vd + self.cy), dim=-1)
        return torch.where(valid[..., None], uv, torch.zeros_like(uv)), valid

    def unproject(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        u, v = split_uv(uv)
        xr, yr, converged = self._undistort((u - self.cx) / self.fx, (v - self.cy) / self.fy)
        # where Newton did not converge, (0, 0): the optical axis, as for every pixel without a ray
        xr, yr = finite_where(converged, xr, 0.0), finite_where(converged, yr, 0.0)
        rays, valid = theta_poly_rays(xr, yr, self._radial, self._theta_max)
        return rays, converged & valid

    # ------------------------------------------------------------------ Aria's calibration files
    @classmethod
    def from_aria_params(cls, params, size) -> Fisheye624Camera:
        """From Aria's ``params`` ``[f, cx, cy, k0..k5, p0, p1, s0..s3]`` and ``size`` ``[W, H]``; a
        calibration that cannot be a real camera's is refused (:func:`.base.check_plausible`)."""
        values = dict(zip(ARIA_PARAMS, (float(p) for p in params), strict=True))
        f = values.pop("f")
        # no int(): a size of 512.7 is refused by the model's checks, not truncated to 512
        return check_plausible(cls(width=float(size[0]), height=float(size[1]), fx=f, fy=f, **values))

    @classmethod
    def from_aria(cls, path: str | os.PathLike, camera_name: str) -> Fisheye624Camera:
        """Camera ``camera_name`` of an Aria calibration JSON in the layout of
        ``aria_gen2_rig/calib_slam_fisheye624.json``: ``{name: {"model": "...FISHEYE624", "params":
        [15 numbers], "size": [W, H], "T_device_camera": 4x4}}``. Errors name the file and the field."""
        from .io import CalibrationError, load_json

        path = Path(path)
        try:
            text = path.read_bytes()
        except FileNotFoundError:
            raise FileNotFoundError(f"{path}: no such Aria calibration file") from None
        except OSError as err:
            raise CalibrationError(path, None, f"not readable ({err.strerror or err})") from None
        data = load_json(text, path)
        if not isinstance(data, dict) or camera_name not in data:
            names = sorted(data) if isinstance(data, dict) else []
            raise CalibrationError(path, camera_name, f"no such camera; the file has {names}")
        entry = data[camera_name]
        for key in ("model", "params", "size"):
            if not isinstance(entry, dict) or key not in entry:
                raise CalibrationError(path, f"{camera_name}.{key}", "missing")
        if not str(entry["model"]).upper().endswith(ARIA_MODEL):
            raise CalibrationError(
                path, f"{camera_name}.model", f"{entry['model']!r} is not a {ARIA_MODEL} calibration"
            )
        params, size = entry["params"], entry["size"]
        if not isinstance(params, list) or len(params) != len(ARIA_PARAMS):
            count = len(params) if isinstance(params, list) else type(params).__name__
            raise CalibrationError(
                path,
                f"{camera_name}.params",
                f"expected {len(ARIA_PARAMS)} numbers {ARIA_PARAMS}, got {count}",
            )
        if not isinstance(size, list) or len(size) != 2:
            raise CalibrationError(path, f"{camera_name}.size", f"expected [width, height], got {size!r}")
        for axis, value in zip(("width", "height"), size, strict=True):
            whole = (
                isinstance(value, int | float) and not isinstance(value, bool) and float(value).is_integer()
            )
            if not whole or value <= 0:
                raise CalibrationError(
                    path,
                    f"{camera_name}.size",
                    f"the {axis} must be a positive whole number of pixels, got {value!r}",
                )
        try:
            return cls.from_aria_params(params, size)
        except (CameraParameterError, TypeError, ValueError) as err:
            key = getattr(err, "key", "params")  # None: the parameters together (no pixel has a ray)
            where = camera_name if key is None else f"{camera_name}.{key}"
            raise CalibrationError(path, where, getattr(err, "reason", str(err))) from None
