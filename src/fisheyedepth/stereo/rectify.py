"""Two calibrated cameras rectified on the sphere: any model, rays beyond 90 degrees included.

Camera a's centre is the origin, camera b's lies at ``L e`` (``e`` the unit baseline, ``L`` its length, in
a's frame). A direction ``d`` is written with two angles: ``phi``, which plane through the baseline it
lies in (about ``e``), and ``psi = pi - theta``, ``theta`` its angle from ``e``. A scene point lies in one
plane through the baseline for both cameras, so it has one ``phi`` for both: rows of constant ``phi`` are
epipolar lines. Seen from b it lies farther from ``e`` than seen from a (``theta_b > theta_a``), so its
column ``psi`` is smaller in b by the parallax ``alpha = theta_b - theta_a``: a's image is the left image
of a rectified pair and ``alpha / step`` the disparity a stereo matcher measures. The triangle (a, b,
point) gives the distance from either camera by the law of sines:

    |a X| = L sin(theta_b) / sin(alpha),        |b X| = L sin(theta_a) / sin(alpha).

The grid has uniform steps in both angles (``step`` radians, by default the coarser camera's angular
resolution): a point at any incidence gets the same treatment, and near the epipoles (where no parallax
is) rows crowd together rather than thin out; where the grid wraps around the whole circle (an epipole
in view) and no column lies across the baseline (a narrow camera moving along its axis), its rows are as
coarse as keeps a row step on the sphere within a column's. It covers the rays both cameras see, padded
by the disparity range on the side each camera's partner lies, so that the first columns can be
answered; each camera's matches need only its own span of columns. The range is the parallax the
cameras asked for can show between the farthest and the nearest distance. Every table depends on the
two cameras and the pose only: built once per rig pair, and once per motion for one camera at two
instants (:class:`RectificationCache`, an LRU of them).
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..cameras.base import CameraModel
from ..cameras.rays import RayCache

RAYS = RayCache(max_entries=32)  # each camera's rays at its own size, unprojected once
MAX_GRID_PIXELS = 16_000_000  # a rectified grid larger than this is a mistake (a step far too fine)
# columns past each end of a camera's span that its matches still see: more than SGBM's window and the
# row check's, so that no window of a kept pixel reaches the cut
SPAN_MARGIN = 16
MAX_ROW_STEP = 4  # a whole circle's rows are at most this many times its columns' step
SEAM = 4  # rows repeated past each end of a grid that wraps around the whole circle: the matcher's window


@dataclass(frozen=True)
class SphericalGrid:
    """The rectified grid: ``rows x cols`` pixels, row ``i`` at ``phi0 + i row_step`` and column ``j``
    at ``psi0 + j step``; ``frame`` ``[3, 3]`` holds ``e``, ``m`` and ``n`` as rows (a's frame to the
    grid's: ``phi = atan2(d.n, d.m)``). A row step of ``phi`` is ``sin theta`` of it on the sphere:
    ``row_step`` (None: ``step``) is coarser where no column of the grid lies across the baseline."""

    frame: np.ndarray
    baseline: float
    step: float
    phi0: float
    psi0: float
    rows: int
    cols: int
    row_step: float | None = None

    @property
    def phi_step(self) -> float:
        """Radians of ``phi`` between two rows."""
        return self.step if self.row_step is None else self.row_step

    def row_scale(self) -> np.ndarray:
        """``[cols]``: the length of a row step on the sphere at each column, in column steps."""
        theta = math.pi - (self.psi0 + self.step * np.arange(self.cols))
        return np.sin(theta) * self.phi_step / self.step

    def directions(self) -> Tensor:
        """``[rows, cols, 3]`` float64 unit directions of the grid's pixels, in a's frame."""
        phi = self.phi0 + self.phi_step * torch.arange(self.rows, dtype=torch.float64)
        theta = math.pi - (self.psi0 + self.step * torch.arange(self.cols, dtype=torch.float64))
        e, m, n = torch.from_numpy(self.frame)
        sin_t, cos_t = torch.sin(theta)[None, :, None], torch.cos(theta)[None, :, None]
        around = torch.cos(phi)[:, None, None] * m + torch.sin(phi)[:, None, None] * n  # [rows, 1, 3]
        return cos_t * e + sin_t * around

    def angles(self, directions: Tensor) -> tuple[Tensor, Tensor]:
        """``phi`` within pi of the grid's middle row (the seam where it wraps lies behind the grid) and
        ``theta`` of directions ``[..., 3]`` in a's frame."""
        local = directions @ torch.from_numpy(self.frame).to(directions.dtype).T
        across = torch.sqrt(local[..., 1] ** 2 + local[..., 2] ** 2)
        theta = torch.atan2(across, local[..., 0])
        phi = torch.atan2(local[..., 2], local[..., 1])
        centre = self.phi0 + self.phi_step * (self.rows - 1) / 2
        phi = torch.remainder(phi - centre + math.pi, 2 * math.pi) - math.pi + centre
        return phi, theta

    def pixels(self, directions: Tensor) -> tuple[Tensor, Tensor]:
        """Fractional ``(row, column)`` ``[..., 2]`` of directions in a's frame, and their ``theta``."""
        phi, theta = self.angles(directions)
        return torch.stack(
            ((phi - self.phi0) / self.phi_step, (math.pi - theta - self.psi0) / self.step), -1
        ), theta


@dataclass(frozen=True)
class Side:
    """One camera of a rectified pair. ``map_x``, ``map_y``: ``[rows, cols]`` float32 pixel of the
    camera (at ``image_size``, the size its image is resampled to before the remap) seen by each grid
    pixel, for ``cv2.remap``; ``valid``: the grid pixels it sees. ``grid_row``, ``grid_col``: ``[H, W]``
    float32 grid position of each of the camera's own pixels (at its calibrated size), for ``cv2.remap``
    the other way; ``theta``: their angle from the baseline; ``inside``: pixels with a ray that fall
    inside the grid. The three are empty where the grid does not answer the camera's pixels."""

    camera: CameraModel
    image_size: tuple[int, int]
    map_x: np.ndarray
    map_y: np.ndarray
    valid: np.ndarray
    grid_row: np.ndarray
    grid_col: np.ndarray
    theta: np.ndarray
    inside: np.ndarray


@dataclass(frozen=True)
class Rectification:
    """Cameras ``a`` and ``b`` on one :class:`SphericalGrid`. The matcher's range: ``disparities`` grid
    pixels (a multiple of 16) from ``first_disparity`` on, from a little below the least parallax of the
    farthest distance (0 where an epipole is in view) up to the parallax of the nearest; ``directions``:
    which camera's pixels the grid can answer (a, b); ``spans``: for each camera, the half-open range of
    grid columns its own matches need (:func:`_spans`), None for the whole grid."""

    grid: SphericalGrid
    a: Side
    b: Side
    disparities: int
    first_disparity: int = 0
    directions: tuple[bool, bool] = (True, True)
    spans: tuple[tuple[int, int], tuple[int, int]] | None = None

    def distance(self, side: str, theta: np.ndarray, alpha: np.ndarray) -> np.ndarray:
        """Metres from camera ``side`` ("a" or "b") along a ray at ``theta`` from the baseline, for
        parallax ``alpha`` radians (> 0): the law of sines."""
        other = theta + alpha if side == "a" else theta - alpha  # the partner's angle from the baseline
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.grid.baseline * np.sin(other) / np.sin(alpha)


def angular_resolution(camera: CameraModel) -> float:
    """Radians per pixel at the principal point (the coarser of the two axes)."""
    return 1.0 / min(camera.paraxial_focal())


def pair_step(camera_a: CameraModel, camera_b: CameraModel, step: float | None = None) -> float:
    """Radians per grid pixel of a pair: ``step``, or the coarser camera's :func:`angular_resolution`."""
    return max(angular_resolution(camera_a), angular_resolution(camera_b)) if step is None else float(step)


def nearest_parallax(baseline: float, min_distance: float, step: float) -> int:
    """Grid pixels of the largest parallax a point ``min_distance`` or farther from a camera can show,
    ``asin(L / min_distance)``, rounded up."""
    return math.ceil(math.asin(min(1.0, baseline / min_distance)) / step)


def farthest_parallax(
    theta_a: np.ndarray, theta_b: np.ndarray, baseline: float, max_distance: float
) -> float:
    """Radians of the least parallax a point ``max_distance`` from its camera shows at any of the angles
    from the baseline given: seen from a at ``theta``, it lies at ``atan2(D sin theta, D cos theta - L)``
    from b; seen from b, at ``atan2(D sin theta, D cos theta + L)`` from a. Near an epipole it is 0."""
    D, L = max_distance, baseline
    least = [np.min(np.arctan2(D * np.sin(t), D * np.cos(t) - L) - t) for t in (theta_a,) if len(t)]
    least += [np.min(t - np.arctan2(D * np.sin(t), D * np.cos(t) + L)) for t in (theta_b,) if len(t)]
    return max(0.0, float(min(least)))


def largest_parallax(theta_a: np.ndarray, theta_b: np.ndarray, baseline: float, min_distance: float) -> float:
    """Radians of the largest parallax a point ``min_distance`` from its camera shows at any of the angles
    from the baseline given (the mirror of :func:`farthest_parallax`): at most ``asin(L / D)``, reached
    only where a ray runs across the baseline; a forward camera whose rays stay near its epipole sees far
    less (a car's front camera moving 1.3 m, 50 degrees off its axis at 2.6 m: 16 degrees, not 30)."""
    D, L = min_distance, baseline
    most = [np.max(np.arctan2(D * np.sin(t), D * np.cos(t) - L) - t) for t in (theta_a,) if len(t)]
    most += [np.max(t - np.arctan2(D * np.sin(t), D * np.cos(t) + L)) for t in (theta_b,) if len(t)]
    return max(0.0, float(max(most)))


def _frame(e: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Rows ``e``, ``m``, ``n``: ``m`` the mean of the cameras' optical axes across the baseline (phi = 0
    where they look; the seam behind them), ``n = e x m``."""
    m = axes.mean(0) - (axes.mean(0) @ e) * e
    if np.linalg.norm(m) < 1e-6:  # looking along the baseline: any direction across it
        m = np.cross(e, [1.0, 0.0, 0.0] if abs(e[0]) < 0.9 else [0.0, 1.0, 0.0])
    m /= np.linalg.norm(m)
    return np.stack((e, m, np.cross(e, m)))


def _image_size(camera: CameraModel, step: float) -> tuple[int, int]:
    """The size to resample a camera's image to before the remap: its own, or smaller where its pixels
    are finer than the grid's (so that the remap does not alias)."""
    scale = angular_resolution(camera) / step
    if scale > 1 / 1.25:
        return camera.width, camera.height
    return max(2, round(camera.width * scale)), max(2, round(camera.height * scale))


def _side(
    camera: CameraModel, rotation: np.ndarray, grid: SphericalGrid, directions: Tensor, answers: bool
) -> Side:
    """``rotation``: a's frame to this camera's (identity for a); ``directions``: the grid's, float32;
    ``answers``: the camera's pixels are answered (their grid positions are kept), else only the remap."""
    size = _image_size(camera, grid.step)
    sampled = camera if size == (camera.width, camera.height) else camera.resize(*size)
    R = torch.from_numpy(rotation).float()
    uv, projects = sampled.project(directions @ R.T)
    w, h = size
    valid = projects & (uv[..., 0] >= -0.5) & (uv[..., 0] <= w - 0.5) & (uv[..., 1] >= -0.5)
    valid &= uv[..., 1] <= h - 0.5
    uv = torch.where(valid[..., None], uv, torch.full_like(uv, -10.0))
    none = np.zeros((0, 0), np.float32)
    row = col = theta = none
    inside = none.astype(bool)
    if answers:
        rays, has_ray = RAYS.get(camera)
        to_grid, angle = grid.pixels(rays @ R)  # this camera's rays in a's frame
        row, col = (np.ascontiguousarray(to_grid[..., i].float().numpy()) for i in (0, 1))
        theta = angle.float().numpy()
        inside = has_ray.numpy() & (row >= -0.5) & (row <= grid.rows - 0.5) & (col >= -0.5)
        inside &= col <= grid.cols - 0.5
    return Side(
        camera=camera,
        image_size=size,
        map_x=uv[..., 0].numpy(),
        map_y=uv[..., 1].numpy(),
        valid=valid.numpy(),
        grid_row=row,
        grid_col=col,
        theta=theta,
        inside=inside,
    )


def _occupancy(grid: SphericalGrid, camera: CameraModel, R: Tensor) -> Tensor:
    """``[rows, cols]`` bool: the cells of ``grid`` (the whole sphere) that some ray of ``camera`` falls
    in (``R``: the rotation from a's frame to the camera's), closed over two cells so that no cell between
    two rays is missed (a ray a cell at the principal point; where the image compresses, two)."""
    rays, has_ray = RAYS.get(camera)
    stride = max(1, int(grid.step / angular_resolution(camera)))  # a ray a cell: the closing fills the rest
    rc, _ = grid.pixels(rays[::stride, ::stride][has_ray[::stride, ::stride]] @ R.float())
    index = rc.round().long()
    index[:, 0].clamp_(0, grid.rows - 1)
    index[:, 1].clamp_(0, grid.cols - 1)
    seen = torch.zeros(grid.rows, grid.cols, dtype=torch.bool)
    seen[index[:, 0], index[:, 1]] = True
    return F.max_pool2d(seen[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0


def any_within(seen: np.ndarray, before: int, after: int) -> np.ndarray:
    """``[rows, cols]`` bool: some pixel of ``seen`` in columns ``[j - before, j + after]`` of row ``j``'s
    row (``after`` may be negative: a window wholly to the left)."""
    counts = np.pad(np.cumsum(seen, axis=1, dtype=np.int32), ((0, 0), (1, 0)))
    cols = seen.shape[1]
    j = np.arange(cols)
    lo, hi = np.clip(j - before, 0, cols), np.clip(j + after + 1, 0, cols)
    return counts[:, hi] - counts[:, lo] > 0


def _extent(
    frame, baseline, step, min_distance, max_distance, margin, camera_a, camera_b, R_ab, directions, asked
) -> tuple:
    """The grid's ``phi0``, ``psi0``, rows and columns, and the matcher's first disparity and count: the
    rows and columns where a's cells have a partner in b within the parallax of the nearest distance (a
    point at ``psi`` in a lies at ``psi - alpha`` in b) or b's in a (each as ``directions`` asks); the
    range from ``margin`` pixels below the least parallax of the farthest distance in those columns (0
    where an epipole is in view) to as far above the largest parallax of the nearest distance in the
    columns of the cameras ``asked`` (the matcher's end checks reject within ``margin`` of either end), a
    multiple of 16;
    a's columns padded by it on the left, b's on the right. Found on the whole sphere in cells of up to a
    few grid pixels (about a million cells), then widened by a cell. Last, the step between rows: the
    column's step, or where the grid wraps around the whole circle, as coarse as keeps a row step on the
    sphere within a column's at the column farthest from the baseline's axis."""
    cell = max(1, math.ceil(math.sqrt(2 * math.pi * math.pi / step**2 / 1e6)))
    coarse = step * cell
    sphere = SphericalGrid(
        frame, baseline, coarse, -math.pi, 0.0, round(2 * math.pi / coarse), round(math.pi / coarse) + 1
    )
    seen_a = _occupancy(sphere, camera_a, torch.eye(3, dtype=torch.float64))
    seen_b = _occupancy(sphere, camera_b, torch.from_numpy(R_ab))
    nearest = nearest_parallax(baseline, min_distance, step)
    reach = math.ceil((nearest + 1 + margin) / cell)
    seen_a, seen_b = seen_a.numpy(), seen_b.numpy()
    matched_a = seen_a & any_within(seen_b, reach, 0) & directions[0]
    matched_b = seen_b & any_within(seen_a, 0, reach) & directions[1]
    both = matched_a | matched_b
    if not bool(both.any()):
        raise ValueError("cameras: no ray of one is seen by the other within the disparity range; no overlap")
    rows_used = np.flatnonzero(both.any(1))
    cols_a, cols_b = np.flatnonzero(matched_a.any(0)), np.flatnonzero(matched_b.any(0))
    first = 0
    theta_a, theta_b = (math.pi - coarse * np.arange(c.min() - 1, c.max() + 2) if len(c) else c
                        for c in (cols_a, cols_b))  # fmt: skip
    if max_distance is not None:
        first = max(
            0, math.floor(farthest_parallax(theta_a, theta_b, baseline, max_distance) / step) - margin
        )
    if baseline < min_distance:  # else a point beyond the partner may show any parallax up to pi
        mine = [t if ask else t[:0] for t, ask in zip((theta_a, theta_b), asked, strict=True)]
        largest = largest_parallax(*mine, baseline, min_distance)
        nearest = min(nearest, math.ceil(largest / step))
    count = max(16, 16 * math.ceil((nearest + 1 + margin - first) / 16))
    pad = first + count
    lows, highs = [], []
    if len(cols_a):  # in grid pixels of step, a cell of margin
        lows.append((int(cols_a.min()) - 1) * cell - pad)
        highs.append((int(cols_a.max()) + 1) * cell)
    if len(cols_b):
        lows.append((int(cols_b.min()) - 1) * cell)
        highs.append((int(cols_b.max()) + 1) * cell + pad)
    left, cols = min(lows), max(highs) - min(lows) + 1
    first_row, last_row = (int(rows_used.min()) - 1) * cell, (int(rows_used.max()) + 1) * cell
    phi_lo, rows = sphere.phi0 + step * first_row, last_row - first_row + 1
    row_step = step
    if rows * step >= 2 * math.pi - 2 * coarse:  # the whole circle (an epipole in view): it wraps, and the
        # matcher's window at the seam sees the rows past it. Its rows need be no finer on the sphere than
        # its columns where they lie farthest apart: at the column farthest from the baseline's axis
        across = max(float(np.max(np.abs(np.sin(t)))) for t in (theta_a, theta_b) if len(t))
        row_step = step / max(across, 1 / MAX_ROW_STEP)
        phi_lo, rows = -math.pi - SEAM * row_step, math.ceil(2 * math.pi / row_step) + 2 * SEAM
    return phi_lo, step * left, rows, cols, first, count, row_step


def build_rectification(
    camera_a: CameraModel,
    camera_b: CameraModel,
    T_a_to_b: np.ndarray,
    min_distance: float,
    step: float | None = None,
    directions: tuple[bool, bool] = (True, True),
    max_distance: float | None = None,
    margin: int = 2,
    asked: tuple[bool, bool] | None = None,
) -> Rectification:
    """The grid and both cameras' tables for the pair (``T_a_to_b``: ``X_b = R X_a + t``, metres).
    ``step``: radians per grid pixel; None: the coarser camera's :func:`angular_resolution`;
    ``directions``: the cameras whose pixels it must answer (a motion pair answers the newer image only:
    its grid is narrower by the disparity range); ``min_distance``, ``max_distance``: metres, the range
    searched (None: to infinity); ``margin``: grid pixels the matcher rejects at each end of its range
    (:attr:`.match.SgbmParameters.end_margin`), added to it; ``asked``: the cameras whose own distances
    are wanted (None: ``directions``): the range reaches the largest parallax their pixels can show at
    ``min_distance``; a camera matched only for the round trip needs no more, as a point shows one
    parallax from either camera."""
    if not 0 < min_distance < (math.inf if max_distance is None else max_distance):
        raise ValueError(f"min_distance, max_distance: {min_distance}, {max_distance}; need 0 < min < max")
    T = np.asarray(T_a_to_b, dtype=np.float64)
    R_ab, t_ab = T[:3, :3], T[:3, 3]
    centre_b = -R_ab.T @ t_ab
    baseline = float(np.linalg.norm(centre_b))
    if not baseline > 0:
        raise ValueError(
            "T_a_to_b: the two camera centres coincide; a pair without a baseline has no parallax"
        )
    step = pair_step(camera_a, camera_b, step)
    if not step > 0:
        raise ValueError(f"step: {step} radians per pixel; must be > 0")
    e = centre_b / baseline
    frame = _frame(e, np.stack((np.array([0.0, 0.0, 1.0]), R_ab.T @ np.array([0.0, 0.0, 1.0]))))
    if not any(directions):
        raise ValueError("directions: neither camera asked for; nothing to rectify for")
    asked = directions if asked is None else asked
    phi_lo, psi_lo, rows, cols, first, count, row_step = _extent(
        frame, baseline, step, min_distance, max_distance, math.ceil(margin), camera_a, camera_b, R_ab,
        directions, asked,
    )  # fmt: skip
    if rows * cols > MAX_GRID_PIXELS:
        raise ValueError(
            f"resolution: a step of {math.degrees(step):.4g} degrees makes a {rows} x {cols} rectified grid "
            f"(at most {MAX_GRID_PIXELS:,} pixels); choose a coarser step"
        )
    grid = SphericalGrid(frame, baseline, step, phi_lo, psi_lo, rows, cols, row_step)
    looking = grid.directions().float()
    side_a = _side(camera_a, np.eye(3), grid, looking, directions[0])
    side_b = _side(camera_b, R_ab, grid, looking, directions[1])
    spans = _spans(side_a.valid, side_b.valid)
    return Rectification(grid, side_a, side_b, count, first, tuple(bool(x) for x in directions), spans)


def _spans(seen_a: np.ndarray, seen_b: np.ndarray) -> tuple[tuple[int, int], tuple[int, int]]:
    """Each camera's span of grid columns (half-open), from where each sees: a's pixel at column ``j``
    matches b's at ``j - d``, so a's matches need nothing right of the last column a sees; b's match a's
    at ``j + d``, so they need nothing left of the first column b sees. Each widened by
    :data:`SPAN_MARGIN`: the columns cut hold only what neither camera of that direction sees, so its
    result is the whole grid's but where the matcher's paths start."""
    cols = seen_a.shape[1]
    in_a, in_b = np.flatnonzero(seen_a.any(0)), np.flatnonzero(seen_b.any(0))
    a = (0, min(cols, int(in_a.max()) + 1 + SPAN_MARGIN)) if in_a.size else (0, 0)
    b = (max(0, int(in_b.min()) - SPAN_MARGIN), cols) if in_b.size else (0, 0)
    return a, b


def remap(image: np.ndarray, side: Side) -> np.ndarray:
    """An image of ``side``'s camera (``H x W`` or ``H x W x C``, any dtype cv2 remaps) on the grid:
    resampled to the side's ``image_size`` first where its pixels are finer than the grid's (area
    averaging), then remapped bilinearly; 0 where the camera does not see."""
    if (image.shape[1], image.shape[0]) != (side.camera.width, side.camera.height):
        raise ValueError(
            f"image: {image.shape[1]}x{image.shape[0]} pixels, but its camera is "
            f"{side.camera.width}x{side.camera.height}"
        )
    if side.image_size != (side.camera.width, side.camera.height):
        image = cv2.resize(image, side.image_size, interpolation=cv2.INTER_AREA)
    return cv2.remap(image, side.map_x, side.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


class RectificationCache:
    """An LRU of :class:`Rectification`, keyed by both cameras, the pose (to the micrometre and the
    microradian), the range, the step, the directions and the cameras asked."""

    def __init__(self, max_entries: int = 32):
        self.max_entries = max_entries
        self._entries: OrderedDict[tuple, Rectification] = OrderedDict()
        self._lock = threading.Lock()  # pairs are built from worker threads
        self.misses = 0

    def get(
        self, camera_a, camera_b, T_a_to_b, min_distance: float, step: float | None = None,
        directions: tuple[bool, bool] = (True, True), max_distance: float | None = None, margin: int = 2,
        asked: tuple[bool, bool] | None = None,
    ) -> Rectification:  # fmt: skip
        T = np.asarray(T_a_to_b, dtype=np.float64)
        pose = tuple(np.round(T[:3].ravel(), 6))
        asked = tuple(directions if asked is None else asked)
        key = (camera_a, camera_b, pose, float(min_distance), max_distance, step, tuple(directions), margin,
               asked)  # fmt: skip
        with self._lock:
            entry = self._entries.get(key)
            if entry is not None:
                self._entries.move_to_end(key)
                return entry
            self.misses += 1
        entry = build_rectification(
            camera_a, camera_b, T, min_distance, step, directions, max_distance, margin, asked
        )
        with self._lock:
            self._entries[key] = entry
            if len(self._entries) > self.max_entries:
                self._entries.popitem(last=False)
        return entry


RECTIFICATIONS = RectificationCache()
