"""Pinhole camera with OpenCV's lens distortion: ROS ``plumb_bob`` and ``rational_polynomial``.

Projection of X = (X, Y, Z), exactly ``cv2.projectPoints`` with ``distCoeffs = (k1, k2, p1, p2, k3, k4, k5,
k6)`` (OpenCV's "Camera Calibration and 3D Reconstruction" model):
    x = X / Z,  y = Y / Z,  s = r^2 = x^2 + y^2
    f(s) = (1 + k1 s + k2 s^2 + k3 s^3) / (1 + k4 s + k5 s^2 + k6 s^3)
    x_d = x f + 2 p1 x y + p2 (s + 2 x^2),   y_d = y f + p1 (s + 2 y^2) + 2 p2 x y
    u = fx x_d + cx,  v = fy y_d + cy
With k4 = k5 = k6 = 0 it is ROS ``plumb_bob`` (D = [k1, k2, p1, p2, k3]); with them ``rational_polynomial``
(D = [k1, k2, p1, p2, k3, k4, k5, k6]); see :meth:`OpenCVCamera.from_ros`.

Domain: Z > 0 and r < r_max, the first radius where the radial map g(r) = r f(r^2) stops increasing
(g'(r) = 0, or a pole of f), beyond which projection is no longer one-to-one; with p1/p2 also where the
distortion keeps the plane's orientation (its Jacobian's determinant > 0; it folds in a sliver next to
r_max on one side). ``max_incidence`` is atan of the largest radius whose whole disc is in the domain
(atan(r_max) without p1/p2), pi / 2 where g increases for ever.

Unprojection inverts g by Newton's method safeguarded by bisection (like OpenCV's ``undistortPoints``, but
converged to rounding), then, with p1/p2, refines by Newton's method in two dimensions with the analytic
Jacobian; pixels beyond the image of the domain get no ray.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from functools import cached_property
from typing import Any

import numpy as np
import torch
from numpy.polynomial import polynomial as npoly
from torch import Tensor

from .base import (
    CameraModel,
    CameraParameterError,
    check_plausible,
    finite_where,
    register_model,
    safe_norm,
    solve_increasing,
    split_uv,
    split_xyz,
)

# ROS sensor_msgs/CameraInfo distortion models and the coefficients of their D arrays
ROS_MODELS: dict[str, tuple[str, ...]] = {
    "plumb_bob": ("k1", "k2", "p1", "p2", "k3"),
    "rational_polynomial": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}

# A pole of f bounds the domain this far short of it (g is finite there, and about 1e7 times r).
POLE_MARGIN = 1e-7
# Where g increases for ever, tangential folds are looked for out to this radius (89.94 degrees).
FOLD_SEARCH_RADIUS = 1e3


def _smallest_positive_root(coeffs: Sequence[float]) -> float:
    """Smallest real root > 0 of the polynomial with ``coeffs`` (lowest power first, ``coeffs[0] > 0``);
    ``inf`` if none.

    Two independent searches, the smaller root wins: the companion matrix's eigenvalues (real ones, polished
    by Newton's method on the polynomial), and the first sign change on a grid of 8192 points out to the
    Cauchy bound of the roots (or the first search's root), bisected to rounding; the grid catches a root
    the eigenvalues report as slightly complex, the eigenvalues one past the grid's reach.
    """
    coeffs = npoly.polytrim(np.asarray(coeffs, dtype=np.float64), tol=0.0)
    if len(coeffs) < 2:
        return math.inf
    real = [
        float(s.real)
        for s in npoly.polyroots(coeffs)
        if s.real > 0 and abs(s.imag) <= 1e-9 * max(1.0, abs(s.real))
    ]
    root = min(real, default=math.inf)
    deriv = npoly.polyder(coeffs)
    for _ in range(8 if math.isfinite(root) else 0):
        slope = npoly.polyval(root, deriv)
        step = npoly.polyval(root, coeffs) / slope if slope != 0 else 0.0
        if not abs(step) < 0.5 * root:  # a polish must not jump to another root
            break
        root -= step
    bound = min(root, 1 + float(np.max(np.abs(coeffs[:-1] / coeffs[-1]))))
    grid = np.linspace(0.0, bound, 8193)
    below = np.nonzero(npoly.polyval(grid[1:], coeffs) <= 0)[0]
    if len(below) and below[0] < len(grid) - 2:  # a sign change before the last cell: bisect it
        lo, hi = grid[below[0]], grid[below[0] + 1]
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            if mid in (lo, hi):
                break
            lo, hi = (lo, mid) if npoly.polyval(mid, coeffs) <= 0 else (mid, hi)
        root = min(root, hi)
    return root


def radial_monotone_limit(num: Sequence[float], den: Sequence[float]) -> tuple[float, bool]:
    """``(r_max, at_pole)``: the first ``r > 0`` where ``g(r) = r N(r^2) / D(r^2)`` stops increasing.

    ``N(s) = 1 + num[0] s + num[1] s^2 + ...`` and ``D`` likewise. ``g'(r) = P(s) / D(s)^2`` with
    ``P = N D + 2 s (N' D - N D')`` (derivatives in s), so ``r_max^2`` is the smallest positive root of
    ``P`` or of ``D`` (a pole, where ``g -> +inf``: it comes first only if ``N > 0`` there; then ``r_max`` is
    :data:`POLE_MARGIN` short of it). ``(inf, False)`` where ``g`` increases for ever.
    """
    N = np.array([1.0, *num])
    D = np.array([1.0, *den])
    P = npoly.polyadd(
        npoly.polymul(N, D),
        npoly.polymul(
            [0.0, 2.0], npoly.polysub(npoly.polymul(npoly.polyder(N), D), npoly.polymul(N, npoly.polyder(D)))
        ),
    )
    s_fold, s_pole = _smallest_positive_root(P), _smallest_positive_root(D)
    if s_pole < s_fold:
        return math.sqrt(s_pole) * (1 - POLE_MARGIN), True
    return math.sqrt(s_fold), False


def ros_matrix_fault(K: Sequence[float]) -> tuple[str, str] | None:
    """``(field, what is wrong)`` for a ROS ``CameraInfo.K`` (9 numbers, row-major) that is not
    ``[fx 0 cx 0 fy cy 0 0 1]`` (its skew ``K[1]`` aside), or None. A ``K`` written column-major (cx, cy
    in ``K[6]``, ``K[7]``) is named as such: read row-major it would give cx = cy = 0, a plausible
    principal point in the image's corner."""
    k = [float(v) for v in K]
    if k[6] != 0 or k[7] != 0:
        if k[2] == 0 and k[5] == 0:
            return "K", (
                f"written column-major: cx = K[6] = {k[6]:g} and cy = K[7] = {k[7]:g} where K[2] = K[5] = 0; "
                "K is row-major, [fx 0 cx 0 fy cy 0 0 1]"
            )
        return "K[6]" if k[6] != 0 else "K[7]", f"must be 0 (K = [fx 0 cx 0 fy cy 0 0 1]), got {k}"
    if k[3] != 0:
        return "K[3]", f"must be 0 (K = [fx 0 cx 0 fy cy 0 0 1]), got {k}"
    if k[8] != 1:
        return "K[8]", f"must be 1 (K = [fx 0 cx 0 fy cy 0 0 1]), got {k[8]:g}"
    return None


def _ros_matrix(K: Any) -> np.ndarray:
    try:
        K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    except (TypeError, ValueError):
        raise CameraParameterError("K", f"expected 9 numbers (a 3x3 matrix, row-major), got {K!r}") from None
    if K[0, 1] != 0:
        raise CameraParameterError("K", f"skew K[0][1] = {K[0, 1]!r} is not supported (must be 0)")
    fault = ros_matrix_fault(K.ravel())
    if fault is not None:
        raise CameraParameterError(*fault)
    return K


@register_model
@dataclasses.dataclass(frozen=True, kw_only=True)
class OpenCVCamera(CameraModel):
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    k5: float = 0.0
    k6: float = 0.0

    model_name = "opencv"

    # -------------------------------------------------------------- ROS CameraInfo
    @classmethod
    def from_ros(
        cls, width: int, height: int, K: Any, D: Sequence[float], distortion_model: str | None = None
    ) -> OpenCVCamera:
        """From a ROS ``sensor_msgs/CameraInfo``: ``K`` (9 numbers, row-major, or 3x3) and ``D``, 5
        coefficients (``plumb_bob``: k1 k2 p1 p2 k3) or 8 (``rational_polynomial``: ... k4 k5 k6).
        ``distortion_model``, when given, must name the model ``D``'s length implies. Raises
        :class:`CameraParameterError` naming ``K`` (or the entry of it: a column-major ``K``, ``K[8]`` not
        1), ``D``, ``distortion_model``, or the parameter of a calibration that cannot be a real camera's
        (:func:`~fisheyedepth.cameras.base.check_plausible`)."""
        coeffs = list(D) if isinstance(D, Sequence | np.ndarray) else None
        lengths = {len(names): model for model, names in ROS_MODELS.items()}
        if coeffs is None or len(coeffs) not in lengths:
            got = f"{len(coeffs)}" if coeffs is not None else repr(D)
            raise CameraParameterError(
                "D", f"expected 5 (plumb_bob) or 8 (rational_polynomial) distortion coefficients, got {got}"
            )
        model = lengths[len(coeffs)]
        if distortion_model is not None and distortion_model != model:
            expected = {m: len(n) for m, n in ROS_MODELS.items()}
            raise CameraParameterError(
                "distortion_model",
                f"{distortion_model!r} with {len(coeffs)} coefficients in D; supported: {expected}",
            )
        K = _ros_matrix(K)
        values = {}
        for name, value in zip(ROS_MODELS[model], coeffs, strict=True):
            if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
                raise CameraParameterError("D", f"{name} must be a number, got {value!r}")
            values[name] = float(value)
        camera = cls(width=width, height=height, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], **values)
        return check_plausible(camera)

    def to_ros(self) -> dict[str, Any]:
        """The ``sensor_msgs/CameraInfo`` fields of this camera: ``plumb_bob`` when k4 = k5 = k6 = 0."""
        model = "plumb_bob" if self._den == (0.0, 0.0, 0.0) else "rational_polynomial"
        return {
            "width": self.width,
            "height": self.height,
            "distortion_model": model,
            "D": [getattr(self, name) for name in ROS_MODELS[model]],
            "K": [self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0],
        }

    # -------------------------------------------------------------- domain
    @property
    def _num(self) -> tuple[float, float, float]:
        return (self.k1, self.k2, self.k3)

    @property
    def _den(self) -> tuple[float, float, float]:
        return (self.k4, self.k5, self.k6)

    @property
    def has_tangential(self) -> bool:
        return self.p1 != 0.0 or self.p2 != 0.0

    @cached_property
    def _radial_limit(self) -> tuple[float, bool]:
        return radial_monotone_limit(self._num, self._den)

    @property
    def _r_max(self) -> float:
        """Largest undistorted radius on the normalised plane inside the domain."""
        return self._radial_limit[0]

    @cached_property
    def _r_disc(self) -> float:
        """Largest radius whose whole disc is in the domain: the nearest fold of the tangential
        distortion (over all azimuths; found on a grid, then bisected), at most ``_r_max``."""
        if not self.has_tangential:
            return self._r_max
        if math.isfinite(self._r_max):
            grid = np.linspace(0.0, self._r_max, 513)[1:]
        else:  # g increases for ever: radii over six decades, out to FOLD_SEARCH_RADIUS
            grid = np.geomspace(FOLD_SEARCH_RADIUS * 1e-6, FOLD_SEARCH_RADIUS, 1024)

        def fold_radius(phi: np.ndarray) -> np.ndarray:
            c, s = np.cos(phi)[:, None], np.sin(phi)[:, None]
            r = grid[None]
            folded = self._fold_det(r * c, r * s) <= 0
            first = np.where(folded.any(axis=1), folded.argmax(axis=1), -1)
            lo = np.where(first > 0, r[0, np.maximum(first - 1, 0)], 0.0)
            up = np.where(first >= 0, r[0, np.maximum(first, 0)], np.inf)
            for _ in range(64):  # bisection where a fold was found
                mid = 0.5 * (lo + np.where(np.isfinite(up), up, lo))
                bad = self._fold_det(mid * c[:, 0], mid * s[:, 0]) <= 0
                up = np.where(np.isfinite(up) & bad, mid, up)
                lo = np.where(np.isfinite(up) & ~bad, mid, lo)
            return np.where(np.isfinite(up), lo, np.inf)

        coarse = np.linspace(0.0, 2 * math.pi, 361)[:-1]
        radii = fold_radius(coarse)
        if not np.isfinite(radii).any():
            return self._r_max
        best = coarse[int(np.argmin(radii))]
        step = coarse[1] - coarse[0]
        fine = fold_radius(np.linspace(best - step, best + step, 201))
        return float(min(radii.min(), fine.min(), self._r_max))

    @property
    def max_incidence(self) -> float:
        return math.atan(self._r_disc) if math.isfinite(self._r_disc) else math.pi / 2

    def _flip_extra(self) -> dict[str, float]:
        # x -> -x leaves the radial terms and p1 unchanged and flips the sign of p2's contribution
        return {"p2": -self.p2}

    # -------------------------------------------------------------- distortion (tensors or arrays)
    def _radial(self, s):
        """``f(s)`` and ``f'(s)`` (derivative in ``s = r^2``)."""
        k1, k2, k3 = self._num
        k4, k5, k6 = self._den
        n = 1 + s * (k1 + s * (k2 + s * k3))
        dn = k1 + s * (2 * k2 + s * (3 * k3))
        if self._den == (0.0, 0.0, 0.0):
            return n, dn
        d = 1 + s * (k4 + s * (k5 + s * k6))
        dd = k4 + s * (2 * k5 + s * (3 * k6))
        return n / d, (dn * d - n * dd) / (d * d)

    def _g(self, r):
        """The radial map ``g(r) = r f(r^2)`` and ``g'(r) = f + 2 r^2 f'``."""
        s = r * r
        f, df = self._radial(s)
        return r * f, f + 2 * s * df

    def _distort(self, x, y):
        s = x * x + y * y
        f, _ = self._radial(s)
        if not self.has_tangential:
            return x * f, y * f
        xy = x * y
        xd = x * f + 2 * self.p1 * xy + self.p2 * (s + 2 * x * x)
        yd = y * f + self.p1 * (s + 2 * y * y) + 2 * self.p2 * xy
        return xd, yd

    def _jacobian(self, x, y):
        """``d(x_d, y_d) / d(x, y)``: ``[[j11, j12], [j12, j22]]`` (symmetric)."""
        s = x * x + y * y
        f, df = self._radial(s)
        j11 = f + 2 * df * x * x + 2 * self.p1 * y + 6 * self.p2 * x
        j12 = 2 * df * x * y + 2 * self.p1 * x + 2 * self.p2 * y
        j22 = f + 2 * df * y * y + 6 * self.p1 * y + 2 * self.p2 * x
        return j11, j12, j22

    def _fold_det(self, x, y):
        j11, j12, j22 = self._jacobian(x, y)
        return j11 * j22 - j12 * j12

    # -------------------------------------------------------------- inverse distortion
    def _solve_radial(self, target: Tensor) -> tuple[Tensor, Tensor]:
        """``r`` in ``[0, r_max]`` with ``g(r) = target``, and whether there is one."""
        if self._num == (0.0, 0.0, 0.0) and self._den == (0.0, 0.0, 0.0):
            return target.clone(), torch.ones_like(target, dtype=torch.bool)
        # g is unbounded where r_max is infinite: doubling finds the upper bracket of any target
        return solve_increasing(target, self._g, self._r_max, max_iter=80, ulps=16, doublings=1100)

    def _undistort(self, xd: Tensor, yd: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(x, y)`` with ``_distort(x, y) = (x_d, y_d)`` inside the domain, and whether there is one."""
        rd = torch.sqrt(xd * xd + yd * yd)
        r, ok = self._solve_radial(rd)
        positive = rd > 0
        scale = torch.where(positive, r / finite_where(positive, rd, 1.0), torch.ones_like(rd))
        x, y = xd * scale, yd * scale
        if not self.has_tangential:
            return x, y, ok
        eps = torch.finfo(xd.dtype).eps
        for _ in range(30):  # 2-D Newton from the radial-only solution
            ex, ey = self._distort(x, y)
            ex, ey = ex - xd, ey - yd
            j11, j12, j22 = self._jacobian(x, y)
            det = j11 * j22 - j12 * j12
            det = torch.where(det.abs() > eps, det, torch.ones_like(det))
            dx = (j22 * ex - j12 * ey) / det
            dy = (j11 * ey - j12 * ex) / det
            x, y = x - dx, y - dy
            if bool((torch.maximum(dx.abs(), dy.abs()) <= 16 * eps * (1 + x.abs() + y.abs())).all()):
                break
        # The radial solve only seeded the iteration: validity is decided by the residual, the radial
        # bound and an unfolded Jacobian.
        ex, ey = self._distort(x, y)
        residual = torch.maximum((ex - xd).abs(), (ey - yd).abs())
        ok = (
            (residual <= 1e3 * eps * (1 + rd))
            & (x * x + y * y <= self._r_max**2)
            & (self._fold_det(x, y) > 0)
        )
        return x, y, ok

    # -------------------------------------------------------------- interface
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        X, Y, Z = split_xyz(points)
        valid = Z > torch.finfo(points.dtype).tiny ** 0.5
        inv = 1.0 / finite_where(valid, Z, 1.0)
        x, y = X * inv, Y * inv
        if math.isfinite(self._r_max):
            # the rim is included up to rounding, so that rays unprojected from rim pixels project back
            slack = 16 * torch.finfo(points.dtype).eps
            valid = valid & (x * x + y * y <= self._r_max**2 * (1 + slack))
        # invalid points are moved to the axis: nothing below (nor its gradient) overflows or divides by 0
        x, y = finite_where(valid, x, 0.0), finite_where(valid, y, 0.0)
        if self.has_tangential:
            valid = valid & (self._fold_det(x, y) > 0)
        xd, yd = self._distort(x, y)
        uv = torch.stack((self.fx * xd + self.cx, self.fy * yd + self.cy), dim=-1)
        valid = valid & torch.isfinite(uv).all(dim=-1)
        return torch.where(valid[..., None], uv, torch.zeros_like(uv)), valid

    def unproject(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        u, v = split_uv(uv)
        x, y, valid = self._undistort((u - self.cx) / self.fx, (v - self.cy) / self.fy)
        valid = valid & torch.isfinite(x) & torch.isfinite(y)
        x, y = finite_where(valid, x, 0.0), finite_where(valid, y, 0.0)
        rays = torch.stack((x, y, torch.ones_like(x)), dim=-1)
        return rays / safe_norm(rays, keepdim=True), valid
