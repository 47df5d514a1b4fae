"""A disparity on the rectified grid brought back to every pixel of the camera's own image.

Each pixel of the camera knows its grid position (its ray's two angles, from the cached rays) and its
angle ``theta`` from the baseline; its parallax is the grid disparity there times the grid's step, and
its distance the law of sines with its own ``theta`` (:meth:`.rectify.Rectification.distance`), so the
grid's coarser step costs no precision of the angle. The disparity is interpolated bilinearly where the
four grid pixels around the position are valid and agree within a pixel, else it is the nearest one's
(a depth edge is not blurred into points floating between the two surfaces).
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from .match import INVALID
from .rectify import Rectification, Side

EDGE = 1.0  # grid pixels: four neighbours further apart than this straddle a depth edge


class Evidence(NamedTuple):
    """What a pair's images say of its calibration and motion: ``answered`` pixels SGBM answered (inside
    the range and both views), ``returned`` those whose round trip closed; ``rows``: the row check
    (:func:`.match.row_offsets`: ``sampled``, ``median_px``, ``off_share``); ``contradicted``: why the
    images contradict the pair's geometry (its pixels are then dropped), None where they do not."""

    answered: int
    returned: int
    rows_sampled: int
    rows_median_px: float
    rows_off_share: float
    contradicted: str | None

    def record(self) -> dict:
        """The evidence as the summary writes it."""
        share = self.returned / self.answered if self.answered else None
        return {
            "round_trip_closed": None if share is None else round(share, 4),
            "row_offset_px": None if self.rows_sampled == 0 else round(self.rows_median_px, 3),
            "off_row_share": None if self.rows_sampled == 0 else round(self.rows_off_share, 4),
            "contradicted": self.contradicted,
        }


class PixelMaps(NamedTuple):
    """One camera's image against one partner, at the image's own pixels (0 where nothing)."""

    distance: np.ndarray  # [H, W] float32 metres along the ray, where the checks keep it
    dense: np.ndarray  # [H, W] float32 metres, the filled map (every pixel the partner could match)
    parallax: np.ndarray  # [H, W] float32 radians of the kept distance (0 where none)
    dense_parallax: np.ndarray  # [H, W] float32 radians of the filled map
    step: float  # radians of one grid pixel: a pixel of disparity error is step / parallax of distance
    roundtrip: np.ndarray | None = None  # [H, W] float32 grid pixels the kept match misses the way back by
    residual: float = 0.0  # grid pixels of the pair's pose its images leave unexplained (epipolar error)
    evidence: Evidence | None = None  # the pair's self-checks (:class:`Evidence`)


def sample(grid: np.ndarray, side: Side) -> np.ndarray:
    """``grid`` (a disparity on the rectified grid, :data:`INVALID` where none) at every pixel of the
    side's camera: bilinear where the four neighbours are valid and within :data:`EDGE`, else the
    nearest; :data:`INVALID` outside the grid or where the nearest is."""
    col, row = side.grid_col, side.grid_row
    valid = grid != INVALID
    constant = {"borderMode": cv2.BORDER_CONSTANT, "borderValue": 0.0}
    weight = cv2.remap(valid.astype(np.float32), col, row, cv2.INTER_LINEAR, **constant)
    bilinear = cv2.remap(np.where(valid, grid, 0).astype(np.float32), col, row, cv2.INTER_LINEAR, **constant)
    nearest = cv2.remap(
        grid, col, row, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=INVALID
    )
    block = np.ones((2, 2), np.uint8)  # each pixel and its right, lower and lower-right neighbours
    high = cv2.dilate(np.where(valid, grid, -1e6).astype(np.float32), block, anchor=(0, 0))
    low = cv2.erode(np.where(valid, grid, 1e6).astype(np.float32), block, anchor=(0, 0))
    corner = (np.floor(col), np.floor(row))  # the top-left of the four neighbours
    spread = cv2.remap(high - low, *corner, cv2.INTER_NEAREST, **constant)
    smooth = (weight > 1 - 1e-3) & (spread <= EDGE)
    out = np.where(smooth, bilinear, nearest)
    return np.where(side.inside & (smooth | (nearest != INVALID)), out, INVALID).astype(np.float32)


def to_pixels(
    checked: np.ndarray,
    filled: np.ndarray,
    rect: Rectification,
    side: str,
    roundtrip: np.ndarray | None = None,
) -> PixelMaps:
    """The checked and the filled grid disparity of camera ``side`` ("a" or "b") as distances at its
    pixels (:class:`PixelMaps`); ``roundtrip``: each grid pixel's round-trip miss, taken at the nearest."""
    own = rect.a if side == "a" else rect.b
    step = rect.grid.step
    out = []
    for grid in (checked, filled):
        disparity = sample(grid, own)
        has = disparity > 0
        alpha = disparity[has] * np.float32(step)
        distance = rect.distance(side, own.theta[has], alpha)
        good = np.isfinite(distance) & (distance > 0)
        metres, radians = np.zeros(disparity.shape, np.float32), np.zeros(disparity.shape, np.float32)
        metres[has] = np.where(good, distance, 0)
        radians[has] = np.where(good, alpha, 0)
        out.append((metres, radians))
    (distance, parallax), (dense, dense_parallax) = out
    miss = None
    if roundtrip is not None:
        miss = cv2.remap(roundtrip, own.grid_col, own.grid_row, cv2.INTER_NEAREST,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)  # fmt: skip
        miss = np.where(distance > 0, miss, 0).astype(np.float32)
    return PixelMaps(distance, dense, parallax, dense_parallax, step, miss)
