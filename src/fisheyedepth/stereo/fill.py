"""A checked disparity map filled: every pixel a partner could match gets a value.

A pixel the checks rejected is occluded (seen by one camera only, beside a nearer surface) or
untextured. Along its epipolar row (a grid row) it is filled from the nearest kept pixels on either
side: an occluded stretch is as wide as the disparity jump of the surface that hides it and lies behind
it, so it takes the background's (the smaller) disparity; a wider stretch is a surface without texture,
interpolated between its ends. A stretch with a kept pixel on one side only (the rim of the partner's
view, where it sees at 60-80 degrees of incidence) takes that pixel's value up to four matching windows
from it, no farther. The filled pixels are then smoothed by a median over the window around them (the
kept ones keep their measurement).
"""

from __future__ import annotations

import cv2
import numpy as np

from .match import INVALID
from .rectify import any_within


def matchable(
    seen: np.ndarray, partner_seen: np.ndarray, disparities: int, partner_left: bool, first: int = 0
) -> np.ndarray:
    """Grid pixels this camera sees whose partner sees some pixel of the same row within the disparity
    range (``disparities`` from ``first`` on): to the left of it (``partner_left``, the left image's
    partner) or to the right."""
    last = first + disparities - 1
    return seen & (
        any_within(partner_seen, last, -first) if partner_left else any_within(partner_seen, -first, last)
    )


def fill_rows(
    disparity: np.ndarray, where: np.ndarray, margin: float = 2.0, reach: float = 20.0, min_jump: float = 1.0
) -> np.ndarray:
    """``disparity`` with every :data:`INVALID` pixel of ``where`` filled along its row from the nearest
    valid pixels to its left and right. A hole between a nearer and a farther surface (ends more than
    ``min_jump`` grid pixels apart) no wider than their disparity jump and ``margin`` is what the nearer
    one hides from the partner: it takes the smaller disparity (the background's). Any other hole is a
    surface without texture: linear between its ends. Where only one side has a value (the rim of the
    partner's view), that one, up to ``reach`` grid pixels from it: beyond, nothing bounds the guess."""
    valid = disparity != INVALID
    todo = where & ~valid
    if not todo.any():
        return disparity.astype(np.float32)
    rows, cols = disparity.shape
    index = np.arange(cols, dtype=np.int32)
    left = np.maximum.accumulate(np.where(valid, index, -1), axis=1)
    right = np.minimum.accumulate(np.where(valid, index, cols)[:, ::-1], axis=1)[:, ::-1]
    r, c = np.nonzero(todo)  # only the pixels to fill from here on
    lo, hi = left[r, c], right[r, c]
    has_left, has_right = lo >= 0, hi < cols
    from_left = np.where(has_left, disparity[r, np.maximum(lo, 0)], np.inf)
    from_right = np.where(has_right, disparity[r, np.minimum(hi, cols - 1)], np.inf)
    both = has_left & has_right
    with np.errstate(invalid="ignore"):
        between = from_left + (c - lo) / np.maximum(hi - lo, 1) * (from_right - from_left)
        jump = np.abs(from_right - from_left)
        occluded = (jump > min_jump) & (hi - lo - 1 <= jump + margin)
    value = np.where(both & ~occluded, between, np.minimum(from_left, from_right))
    gap = np.minimum(np.where(has_left, c - lo, reach + 1), np.where(has_right, hi - c, reach + 1))
    value = np.where(both | (gap <= reach), value, np.inf)  # one side only: no farther than ``reach``
    out = disparity.astype(np.float32, copy=True)
    known = np.isfinite(value)
    out[r[known], c[known]] = value[known]
    return out


def fill(
    disparity: np.ndarray, where: np.ndarray, smooth: int = 5, margin: float = 2.0, reach: float = 20.0
) -> np.ndarray:
    """:func:`fill_rows` (``margin``: how much wider than its jump an occluded hole may be: the matcher's
    half block, which a foreground surface is widened by; ``reach``: how far a one-sided stretch is
    filled), then the filled pixels replaced by the median of the ``smooth`` x ``smooth`` window around
    them (3 or 5: what OpenCV's float median takes; 0: no smoothing)."""
    filled = fill_rows(disparity, where, margin, reach)
    if smooth:
        known = filled != INVALID
        median = cv2.medianBlur(np.where(known, filled, 0).astype(np.float32), smooth)
        # only where the whole window is known: a median over missing pixels (0) would pull it farther
        full = (
            cv2.boxFilter(known.astype(np.float32), -1, (smooth, smooth), normalize=False) >= smooth * smooth
        )
        new = (disparity == INVALID) & known & full
        filled = np.where(new, median, filled)
    return filled.astype(np.float32)
