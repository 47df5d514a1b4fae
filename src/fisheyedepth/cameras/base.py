"""The one interface every camera model implements.

Conventions (all models):
- Camera frame: x right, y down, z forward (OpenCV). Points are ``[..., 3]`` tensors.
- Pixels: ``(u, v) = (column, row)``; integer coordinates are pixel *centres* (KITTI-360, OpenCV).
- ``project(points) -> (uv, valid)``: ``valid`` is False where the point lies outside the model's
  domain (behind a pinhole camera, beyond the fisheye's maximal incidence angle, at the centre of
  projection). ``uv`` is always finite. Whether ``uv`` falls inside the image is the warp's question
  (:func:`fisheyedepth.geometry.warp_to_source`), not the model's.
- ``unproject(uv) -> (rays, valid)``: unit rays; ``valid`` is False where the pixel has no ray in the
  model. ``rays`` is always finite (``(0, 0, 1)`` where invalid).
- Any leading batch shape, float32 or float64, on any device; gradients flow through ``project``.
  ``unproject`` builds ray caches and is not meant for gradients (its iterations are not differentiated).

A camera is an immutable value: equal parameters give equal, hashable cameras, which is what the
per-camera ray cache keys on.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar

import torch
from torch import Tensor


class CameraParameterError(ValueError):
    """A camera parameter is missing, non-finite or impossible. ``key`` names the parameter; None where the
    fault is the parameters together (a calibration that gives almost no pixel a ray)."""

    def __init__(self, key: str | None, message: str):
        super().__init__(message if key is None else f"{key}: {message}")
        self.key = key
        self.reason = message


# Registry of models by their serialised name; filled by ``register_model``.
CAMERA_MODELS: dict[str, type[CameraModel]] = {}


def register_model(cls: type[CameraModel]) -> type[CameraModel]:
    CAMERA_MODELS[cls.model_name] = cls
    return cls


@dataclasses.dataclass(frozen=True, kw_only=True)
class CameraModel:
    """Base class: image size plus the model's scalar parameters (plain floats, device-free)."""

    width: int
    height: int

    model_name: ClassVar[str] = ""
    # Whether ``unproject`` is direct: a closed form or a one-dimensional solve, about as fast per pixel
    # as a projection. Where it is not (a two-dimensional iteration), the ray cache unprojects a large
    # image through :func:`fisheyedepth.cameras.rays.interpolated_rays`.
    direct_unproject: ClassVar[bool] = False
    # Names of the parameters that are a focal length (pixels) along u and v, and the principal point.
    # Resizing and flipping are generic over these.
    _fu: ClassVar[str] = "fx"
    _fv: ClassVar[str] = "fy"
    _cu: ClassVar[str] = "cx"
    _cv: ClassVar[str] = "cy"

    # ---------------------------------------------------------------- construction and checks
    def __post_init__(self) -> None:
        for key in ("width", "height"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int | float) or value != int(value):
                raise CameraParameterError(key, f"must be a positive integer, got {value!r}")
            if value <= 0:
                raise CameraParameterError(key, f"must be a positive integer, got {value!r}")
            object.__setattr__(self, key, int(value))
        for key in self.param_names():
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise CameraParameterError(key, f"must be a number, got {value!r}")
            if not math.isfinite(value):
                raise CameraParameterError(key, f"must be finite, got {value!r}")
            object.__setattr__(self, key, float(value))
        for key in (self._fu, self._fv):
            if getattr(self, key) <= 0:
                raise CameraParameterError(key, f"focal length must be positive, got {getattr(self, key)!r}")
        self._check()

    def _check(self) -> None:
        """Model-specific parameter checks; raise :class:`CameraParameterError`."""

    @classmethod
    def param_names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls) if f.name not in ("width", "height"))

    # ---------------------------------------------------------------- the interface
    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        raise NotImplementedError

    def unproject(self, uv: Tensor) -> tuple[Tensor, Tensor]:
        raise NotImplementedError

    @property
    def max_incidence(self) -> float:
        """Largest angle (radians) between a ray and the optical axis inside the model's domain."""
        raise NotImplementedError

    def paraxial_focal(self) -> tuple[float, float]:
        """Pixels per radian at the principal point (the focal of the best pinhole near the centre)."""
        return getattr(self, self._fu), getattr(self, self._fv)

    def pixel_coverage(self, samples: int = 33) -> float:
        """Fraction of the image with a ray in the model, from a ``samples x samples`` grid of pixels."""
        u = torch.linspace(0, self.width - 1, samples, dtype=torch.float64)
        v = torch.linspace(0, self.height - 1, samples, dtype=torch.float64)
        uv = torch.stack(torch.meshgrid(u, v, indexing="xy"), dim=-1)
        return float(self.unproject(uv)[1].double().mean())

    def field_of_view(self, samples: int = 65) -> tuple[float, float]:
        """Degrees the image sees across its width and across its height, along the row and the column
        through the principal point: on each side of it, the largest incidence of a pixel with a ray, out
        to the image's outer edge (``-0.5`` and ``W - 0.5`` under the pixel-centre convention); the two
        sides summed (a fisheye whose image circle is inside the image sees its whole domain, 2 x
        ``max_incidence``). A side with no ray counts 0."""
        cu, cv = self.principal_point
        spans = []
        for size, centre, line in ((self.width, cu, 0), (self.height, cv, 1)):
            t = torch.linspace(-0.5, size - 0.5, samples, dtype=torch.float64)
            other = torch.full_like(t, (cv, cu)[line])
            rays, valid = self.unproject(torch.stack((t, other) if line == 0 else (other, t), dim=-1))
            theta = torch.acos(rays[..., 2].clamp(-1.0, 1.0))
            sides = [theta[valid & side] for side in (t < centre, t > centre)]
            spans.append(math.degrees(sum(float(s.max()) if len(s) else 0.0 for s in sides)))
        return spans[0], spans[1]

    @property
    def principal_point(self) -> tuple[float, float]:
        return getattr(self, self._cu), getattr(self, self._cv)

    # ---------------------------------------------------------------- derived cameras
    def resize(self, width: int, height: int) -> CameraModel:
        """The same camera for an image resampled to ``width x height``.

        Exact under the pixel-centre convention: a point at continuous pixel ``u`` of the original image
        is at ``(u + 0.5) * s - 0.5`` in the resized one, so focal lengths scale by ``s`` and the
        principal point maps like any pixel (the reference implementation scales ``u0`` by ``s`` alone,
        which is off by ``(1 - s) / 2`` px).
        """
        su, sv = width / self.width, height / self.height
        changes = {
            self._fu: getattr(self, self._fu) * su,
            self._fv: getattr(self, self._fv) * sv,
            self._cu: (getattr(self, self._cu) + 0.5) * su - 0.5,
            self._cv: (getattr(self, self._cv) + 0.5) * sv - 0.5,
        }
        return dataclasses.replace(self, width=width, height=height, **changes)

    def flip(self) -> CameraModel:
        """The camera that sees the horizontally flipped image (``u -> W - 1 - u``).

        It projects the mirrored point ``(-X, Y, Z)`` to ``W - 1 - u`` where this camera projects
        ``(X, Y, Z)`` to ``u``. Relative poses mirror with :func:`fisheyedepth.geometry.mirror_pose_x`.
        """
        changes = {self._cu: self.width - 1 - getattr(self, self._cu)}
        changes.update(self._flip_extra())
        return dataclasses.replace(self, **changes)

    def _flip_extra(self) -> dict[str, float]:
        return {}

    # ---------------------------------------------------------------- serialisation
    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"model": self.model_name, "width": self.width, "height": self.height}
        out.update({k: getattr(self, k) for k in self.param_names()})
        return out

    @staticmethod
    def from_dict(data: dict[str, Any]) -> CameraModel:
        """Build any registered model from :meth:`to_dict` output. Raises :class:`CameraParameterError`."""
        if "model" not in data:
            raise CameraParameterError("model", f"missing; one of {sorted(CAMERA_MODELS)}")
        name = str(data["model"]).lower()
        if name not in CAMERA_MODELS:
            raise CameraParameterError(
                "model", f"unknown camera model {data['model']!r}; one of {sorted(CAMERA_MODELS)}"
            )
        cls = CAMERA_MODELS[name]
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - set(fields) - {"model"})
        if unknown:
            raise CameraParameterError(unknown[0], f"not a parameter of the {name} model ({sorted(fields)})")
        for key, field in fields.items():
            no_default = field.default is dataclasses.MISSING
            if no_default and key not in data:
                raise CameraParameterError(key, f"missing (required by the {name} model)")
        return check_plausible(cls(**{k: v for k, v in data.items() if k != "model"}))


# -------------------------------------------------------------------- plausibility
# The bounds of check_plausible. Every real calibration the project reads or ships (KITTI-360's two Mei
# fisheyes, TUM-VI's Kannala-Brandt and double sphere, Aria's Fisheye624 and Kannala-Brandt cameras,
# ScanNet++'s DSLR fisheye, ROS plumb_bob and rational_polynomial examples) and every camera the synthetic
# rigs draw has its paraxial focal between 0.19 and 1.3 times the image size along the same axis, its
# principal point within 3 % of the image size of its centre, and sees 45 to 203 degrees across its image.
#
# Fewer pixels with a ray than this: an impossible distortion coefficient, a wrong unit (KITTI-360's
# image_02 gives 87 % of its pixels a ray; the synthetic rigs draw cameras with at least 50 %).
MIN_PIXEL_COVERAGE = 0.05
# A paraxial focal below 1/20 of the image size would map the image's half-width to 10 radians at the
# centre's magnification: an equidistant lens would see 1146 degrees across, the most centre-compressing
# mapping the models have (stereographic: UCM alpha = 0.5, Mei xi = 1) 314 degrees, a pinhole 169.
# The widest fisheye lenses made see about 280 degrees (equidistant: 0.2 image sizes).
MIN_FOCAL_SIZES = 1 / 20
# Above 100 image sizes a pinhole sees 0.57 degrees across: narrower than any lens (a 2000 mm telephoto on
# a full-frame sensor, the longest made, sees 1 degree across: 55 image sizes).
MAX_FOCAL_SIZES = 100.0
# The narrowest view accepted across the image, whatever made it narrow (the focal or the distortion).
MIN_FIELD_OF_VIEW = 1.0  # degrees


def check_plausible(camera: CameraModel) -> CameraModel:
    """``camera`` if its calibration can be a real camera's; else :class:`CameraParameterError` naming the
    parameter (its ``key``; None where no one parameter is to blame). The one rule, for every model:

    1. the principal point lies inside the image (``-0.5 <= cx <= W - 0.5``, the image's outer edge under
       the pixel-centre convention, no margin): the optical axis meets the sensor. Resizing and
       flipping map the image onto itself, so they keep a camera inside the rule;
    2. at least :data:`MIN_PIXEL_COVERAGE` of the image has a ray in the model (the image does not reach
       far beyond what the model can see);
    3. the paraxial focal (:meth:`CameraModel.paraxial_focal`) along each axis lies between
       :data:`MIN_FOCAL_SIZES` and :data:`MAX_FOCAL_SIZES` times the image size along it;
    4. the image sees at least :data:`MIN_FIELD_OF_VIEW` degrees across its width and across its height
       (:meth:`CameraModel.field_of_view`, from the model's rays: a sane focal with a distortion that
       squeezes the image into a sliver is refused too).

    Every reader of a calibration goes through it: :meth:`CameraModel.from_dict` (so every file the
    project reads, :func:`~fisheyedepth.cameras.io.camera_from_mapping`, and a ROS ``CameraInfo``),
    ``OpenCVCamera.from_ros`` and ``Fisheye624Camera.from_aria_params``.
    Cameras built by code (presets, resizing, flipping, the synthetic rigs' draws, cameras a computation
    builds for its own use) are not checked at construction: the tests check the presets and the draws.
    """
    sides = (
        ("width", camera.width, camera._fu, camera._cu),
        ("height", camera.height, camera._fv, camera._cv),
    )
    for side, size, _, centre_key in sides:
        centre = getattr(camera, centre_key)
        if not -0.5 <= centre <= size - 0.5:
            raise CameraParameterError(
                centre_key,
                f"the principal point's {centre:g} px lies outside the {size} px image {side} (-0.5 to "
                f"{size - 0.5:g}): the optical axis must meet the image (the principal point of a real "
                "camera lies near the image centre)",
            )
    coverage = camera.pixel_coverage()
    if coverage < MIN_PIXEL_COVERAGE:
        raise CameraParameterError(
            None,
            f"only {coverage:.1%} of the {camera.width}x{camera.height} image has a ray in this "
            f"{camera.model_name} model (at least {MIN_PIXEL_COVERAGE:.0%} expected): an impossible "
            "distortion or focal value?",
        )
    for (side, size, focal_key, _), paraxial in zip(sides, camera.paraxial_focal(), strict=True):
        value = getattr(camera, focal_key)
        fov = math.degrees(2 * math.atan2(size / 2, paraxial))  # a pinhole's, at the paraxial focal
        of = f"{value:g} px" + ("" if paraxial == value else f" (a paraxial focal length of {paraxial:g} px)")
        if paraxial > MAX_FOCAL_SIZES * size:
            raise CameraParameterError(
                focal_key,
                f"{of} gives a field of view of {fov:.2g} degrees across the {size} px image {side} (a "
                f"focal length of at most {MAX_FOCAL_SIZES:g} times the image {side}, "
                f"{MAX_FOCAL_SIZES * size:g} px, expected): a wrong unit or a corrupt value?",
            )
        if paraxial < MIN_FOCAL_SIZES * size:
            raise CameraParameterError(
                focal_key,
                f"{of} is less than 1/{1 / MIN_FOCAL_SIZES:g} of the {size} px image {side} (at least "
                f"{MIN_FOCAL_SIZES * size:g} px expected; a pinhole of this focal would see {fov:.3g} "
                "degrees across it): a wrong unit or a corrupt value?",
            )
    for (side, size, _, _), degrees in zip(sides, camera.field_of_view(), strict=True):
        if degrees < MIN_FIELD_OF_VIEW:
            raise CameraParameterError(
                None,
                f"the {camera.model_name} model sees {degrees:.2g} degrees across the {size} px image {side} "
                f"(at least {MIN_FIELD_OF_VIEW:g} degree expected): an impossible distortion coefficient?",
            )
    return camera


# -------------------------------------------------------------------- shared numerical helpers
def safe_norm(x: Tensor, dim: int = -1, keepdim: bool = False) -> Tensor:
    """Euclidean norm whose gradient is finite at zero."""
    if dim in (-1, x.dim() - 1) and x.shape[-1] <= 4:  # a point's few coordinates: added, not reduced
        sq = x[..., 0] * x[..., 0]
        for i in range(1, x.shape[-1]):
            sq = sq + x[..., i] * x[..., i]
        sq = sq[..., None] if keepdim else sq
    else:
        sq = (x * x).sum(dim=dim, keepdim=keepdim)
    tiny = torch.finfo(x.dtype).tiny
    return torch.sqrt(sq.clamp_min(tiny))


def split_uv(uv: Tensor) -> tuple[Tensor, Tensor]:
    if uv.shape[-1] != 2:
        raise ValueError(f"pixel coordinates must have a last dimension of 2, got shape {tuple(uv.shape)}")
    return uv[..., 0], uv[..., 1]


def split_xyz(points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    if points.shape[-1] != 3:
        raise ValueError(f"points must have a last dimension of 3, got shape {tuple(points.shape)}")
    return points[..., 0], points[..., 1], points[..., 2]


def finite_where(valid: Tensor, value: Tensor, fallback: float) -> Tensor:
    """``value`` where valid, ``fallback`` elsewhere (keeps outputs finite for invalid entries)."""
    return torch.where(valid, value, torch.full_like(value, fallback))


def odd_poly(r: Tensor, coeffs: tuple[float, ...]) -> tuple[Tensor, Tensor]:
    """``g(r) = r (1 + c1 r^2 + c2 r^4 + ...)`` and ``g'(r)``, by Horner's rule in ``r^2``."""
    r2 = r * r
    n = len(coeffs)
    acc = r2 * coeffs[n - 1]  # sum_i c_i r^(2i), Horner from the highest term
    dacc = r2 * ((2 * n + 1) * coeffs[n - 1])  # sum_i (2i + 1) c_i r^(2i)
    for i in range(n - 1, 0, -1):
        acc = (acc + coeffs[i - 1]) * r2
        dacc = (dacc + (2 * i + 1) * coeffs[i - 1]) * r2
    return r * (1 + acc), 1 + dacc


def odd_poly_monotone_limit(coeffs: tuple[float, ...], cap: float = math.inf) -> float:
    """Smallest ``r`` in ``(0, cap]`` where ``g'(r) = 1 + 3 c1 r^2 + 5 c2 r^4 + ...`` reaches zero.

    Beyond it the distortion folds back and projection is no longer one-to-one, so it bounds the
    model's domain. Returns ``cap`` when ``g`` stays increasing on ``(0, cap)``.
    """
    import numpy as np

    # g'(r) as a polynomial in s = r^2, highest power first for numpy.roots.
    poly = [(2 * i + 1) * c for i, c in reversed(list(enumerate(coeffs, start=1)))] + [1.0]
    while len(poly) > 1 and poly[0] == 0.0:
        poly = poly[1:]
    if len(poly) == 1:
        return cap
    roots = np.roots(poly)
    real = [float(s.real) for s in roots if abs(s.imag) <= 1e-12 * max(1.0, abs(s.real)) and s.real > 0]
    limit = math.sqrt(min(real)) if real else math.inf
    return min(limit, cap)


def theta_poly_project(
    points: Tensor, coeffs: tuple[float, ...], theta_max: float
) -> tuple[Tensor, Tensor, Tensor]:
    """The radial step of the models that distort the incidence angle (Kannala-Brandt, Fisheye624):
    ``theta = atan2(rho, Z)``, ``theta_d = g(theta)`` (:func:`odd_poly`), and ``(x_r, y_r) = theta_d (X, Y) /
    rho``, with its limit ``(X, Y) / Z`` on the axis. Returns ``(x_r, y_r, valid)``; ``valid`` is False
    beyond ``theta_max``, at the origin and on the axis behind the camera."""
    X, Y, Z = split_xyz(points)
    tiny = torch.finfo(points.dtype).tiny ** 0.5
    rho = safe_norm(points[..., :2])
    theta = torch.atan2(rho, Z)
    theta_d, _ = odd_poly(theta, coeffs)
    near_axis = rho <= tiny
    scale = torch.where(
        near_axis, 1.0 / finite_where(Z > 0, Z, 1.0), theta_d / finite_where(~near_axis, rho, 1.0)
    )
    valid = (theta < theta_max) & (safe_norm(points) > tiny) & ~(near_axis & (Z <= 0))
    return scale * X, scale * Y, valid


def theta_poly_rays(
    xr: Tensor, yr: Tensor, coeffs: tuple[float, ...], theta_max: float
) -> tuple[Tensor, Tensor]:
    """The inverse of :func:`theta_poly_project`: unit rays ``[..., 3]`` of ``(x_r, y_r)`` (``theta`` by
    :func:`solve_odd_poly` from ``theta_d = |(x_r, y_r)|``), the optical axis where invalid."""
    theta_d = torch.sqrt(xr * xr + yr * yr)
    theta, valid = solve_odd_poly(theta_d, coeffs, theta_max)
    positive = theta_d > 0
    s = torch.where(positive, torch.sin(theta) / finite_where(positive, theta_d, 1.0), torch.ones_like(theta))
    rays = torch.stack((s * xr, s * yr, torch.cos(theta)), dim=-1)
    rays = rays / safe_norm(rays, keepdim=True)
    axis = torch.zeros_like(rays)
    axis[..., 2] = 1
    return torch.where(valid[..., None], rays, axis), valid


def solve_odd_poly(
    target: Tensor, coeffs: tuple[float, ...], r_max: float, max_iter: int = 60
) -> tuple[Tensor, Tensor]:
    """Solve ``g(r) = target`` for ``r`` in ``[0, r_max]`` (:func:`odd_poly`, increasing there); returns
    ``(r, ok)`` (:func:`solve_increasing`)."""
    if not coeffs or all(c == 0.0 for c in coeffs):
        r = target.clone()
        return r, r <= r_max
    return solve_increasing(target, lambda r: odd_poly(r, coeffs), r_max, max_iter)


def solve_increasing(
    target: Tensor, g, r_max: float, max_iter: int = 60, ulps: int = 4, doublings: int = 64
) -> tuple[Tensor, Tensor]:
    """Solve ``g(r) = target`` for ``r`` in ``[0, r_max]``, where ``g(r) -> (value, derivative)`` is
    increasing with ``g(0) = 0``; returns ``(r, ok)``.

    Newton-Raphson with the analytic derivative, safeguarded by bisection: every step keeps a bracket
    ``[lo, hi]`` around the root and falls back to its midpoint when Newton would leave it, so it
    converges for every ``target`` in ``[0, g(r_max)]``. ``ok`` is False for targets beyond ``g(r_max)``.
    Where ``r_max`` is infinite the upper bracket is found by doubling (at most ``doublings`` times). It
    stops when every step, or every bracket, is within ``ulps`` units in the last place of ``r``.
    """
    eps = torch.finfo(target.dtype).eps
    target = target.detach()
    lo = torch.zeros_like(target)
    if math.isfinite(r_max):
        hi = torch.full_like(target, r_max)
        g_hi, _ = g(hi)
        ok = target <= g_hi * (1 + 16 * eps)
        target = torch.minimum(target, g_hi)
    else:
        hi = target.clone().clamp_min(1.0)
        ok = torch.ones_like(target, dtype=torch.bool)
        for _ in range(doublings):
            g_hi, _ = g(hi)
            short = g_hi < target
            if not bool(short.any()):
                break
            hi = torch.where(short, hi * 2, hi)
    r = torch.minimum(target, hi)
    for _ in range(max_iter):
        value, dg = g(r)
        f = value - target
        lo = torch.where(f < 0, r, lo)
        hi = torch.where(f > 0, r, hi)
        step = f / torch.where(dg > 0, dg, torch.ones_like(dg))
        r_new = r - step
        outside = (r_new < lo) | (r_new > hi) | ~(dg > 0) | ~torch.isfinite(r_new)
        r_new = torch.where(outside, 0.5 * (lo + hi), r_new)
        tol = ulps * eps * r_new.abs().clamp_min(1.0)
        done = ((r_new - r).abs() <= tol) | (hi - lo <= tol)
        r = r_new
        if bool(done.all()):
            break
    return r, ok
