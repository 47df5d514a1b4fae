"""A rectified pair matched by OpenCV's semi-global block matcher (``cv2.StereoSGBM``), then checked.

Before matching, both images are normalised to local contrast: each pixel's distance from its
window's mean in units of the window's standard deviation, over the pixels the camera sees (vignetting
and gain differ between two cameras at 40-80 degrees of incidence; the matcher compares raw grey
values). One SGBM run per direction (its 3-way mode: a fifth of the full 8-path mode's time on a 640 px
fisheye pair) with its uniqueness test and left-right check gives the *matched* disparity; a disparity
is then kept where

- the winner is inside the range, two grid pixels or more from either end: at the near end the cost may
  fall further beyond it (low texture wins at the nearest or the farthest disparity in both directions);
  at the far end, within two pixels of no parallax, one pixel of error is half the distance or more
  (on the synthetic street's time pairs, the matches kept under two pixels were off by 121 % on the
  mean);
- the partner pixel it names lies inside the partner's view (a match against the black outside the
  image circle is no match);
- its own matching window holds contrast (:func:`textured`): a flat patch (a uniform wall rendered
  without noise, a saturated sky, a grey test image) matches every disparity equally, and SGBM's
  smoothness would otherwise hand it its neighbours' disparity (uniform grey images kept 13-19 % of
  their pixels at an abs_rel of 0.46 before this test, none after);

where the partner's own answer at the pixel it names leads back to it within a grid pixel (the round
trip, :func:`match_both`: both directions are matched whatever is asked; moving a camera forward, SGBM
answers the band outside the partner's view with a smaller wrong disparity, which finds no way back);
and where it belongs to a region of consistent disparity larger than a speckle: a solid angle
(``speckle_deg2``), so that the same scene detail counts as noise at any resolution (the *checked*
disparity, what the outputs and the filling start from; the *matched* one is SGBM's before it). The
pair as a whole is checked by :func:`row_offsets`: how far off their epipolar rows its matches correlate
best.

Disparities are SGBM's sixteenths of a grid pixel: sub-pixel from its parabola through the winner.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

MODES = {"sgbm": cv2.STEREO_SGBM_MODE_SGBM, "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
         "hh": cv2.STEREO_SGBM_MODE_HH, "hh4": cv2.STEREO_SGBM_MODE_HH4}  # fmt: skip
INVALID = -1.0  # a rejected disparity


@dataclass(frozen=True)
class SgbmParameters:
    """``block``: SGBM's block size (odd); ``p1``, ``p2``: its smoothness penalties per block pixel
    (OpenCV's recommended ``8`` and ``32`` times the block's area); ``mode``: a key of :data:`MODES`;
    ``uniqueness``: percent by which the winner must beat the runner-up; ``lr_check``: grid pixels of
    left-right disagreement allowed (``disp12MaxDiff``); ``speckle_deg2``: the largest region (square
    degrees) of disparities within ``speckle_range`` grid pixels of their neighbours that the checked
    output drops as noise; ``normalise_window``: the local contrast normalisation's window (odd, grid
    pixels; 0: off); ``end_margin``: grid pixels at each end of the range where a winner is rejected;
    ``round_trip``: grid pixels by which the partner's answer may miss the way back (:func:`round_trip`)."""

    block: int = 5
    p1: int = 8
    p2: int = 32
    mode: str = "3way"
    uniqueness: int = 10
    lr_check: int = 1
    speckle_deg2: float = 11.0
    speckle_range: float = 2.0
    normalise_window: int = 15
    end_margin: float = 2.0
    round_trip: float = 1.0

    def __post_init__(self) -> None:
        if self.block < 1 or self.block % 2 == 0 or self.block > 31:
            raise ValueError(f"block: {self.block} is not an odd number from 1 to 31")
        if self.mode not in MODES:
            raise ValueError(f"mode: {self.mode!r}; choose from {', '.join(MODES)}")
        if not 0 <= self.p1 < self.p2:
            raise ValueError(f"p1, p2: {self.p1}, {self.p2}; need 0 <= p1 < p2")
        if self.normalise_window and (self.normalise_window < 3 or self.normalise_window % 2 == 0):
            raise ValueError(f"normalise_window: {self.normalise_window} is not 0 or an odd number >= 3")
        if not self.round_trip > 0:
            raise ValueError(f"round_trip: {self.round_trip} grid pixels; must be > 0")
        if self.speckle_deg2 < 0 or self.speckle_range <= 0 or self.end_margin < 0:
            raise ValueError(
                f"speckle_deg2, speckle_range, end_margin: {self.speckle_deg2}, {self.speckle_range}, "
                f"{self.end_margin}; need >= 0, > 0, >= 0"
            )

    def create(self, disparities: int, first: int = 0) -> cv2.StereoSGBM:
        """OpenCV's matcher with these parameters for ``disparities`` grid pixels from ``first``."""
        area = self.block * self.block
        return cv2.StereoSGBM_create(
            minDisparity=first, numDisparities=disparities, blockSize=self.block, P1=self.p1 * area,
            P2=self.p2 * area, disp12MaxDiff=self.lr_check, uniquenessRatio=self.uniqueness,
            speckleWindowSize=0, speckleRange=0, mode=MODES[self.mode],
        )  # fmt: skip

    def speckle_pixels(self, step: float) -> int:
        """:attr:`speckle_deg2` in grid pixels of ``step`` radians."""
        return round(self.speckle_deg2 / math.degrees(step) ** 2)


class Disparity(NamedTuple):
    """One camera's disparity on the grid, :data:`INVALID` where there is none."""

    matched: np.ndarray  # float32: SGBM's, inside the range and the partner's view
    checked: np.ndarray  # float32: the matched ones outside speckles


def local_spread(image: np.ndarray, seen: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """The mean and the standard deviation of float32 ``image`` over the ``window`` around each pixel,
    among the ``seen`` pixels only."""
    weight = seen.astype(np.float32)
    size = (window, window)
    count = np.maximum(cv2.boxFilter(weight, -1, size, normalize=False), 1)
    mean = cv2.boxFilter(image * weight, -1, size, normalize=False) / count
    square = cv2.boxFilter(image * image * weight, -1, size, normalize=False) / count
    return mean, np.sqrt(np.maximum(square - mean * mean, 0))


def normalise(image: np.ndarray, seen: np.ndarray, window: int) -> np.ndarray:
    """``uint8``: ``128 + 32 (I - mean) / std`` over the ``window`` around each pixel, among the pixels the
    camera sees (0 outside them); ``window=0``: the image scaled to 8 bits."""
    image = image.astype(np.float32)
    if image.ndim == 3:
        image = image.mean(2)
    if not window:
        top = float(image[seen].max()) if seen.any() else 1.0
        return np.where(seen, np.clip(image * (255.0 / max(top, 1e-6)), 0, 255), 0).astype(np.uint8)
    mean, spread = local_spread(image, seen, window)
    floor = 1e-3 * max(float(spread.max()), 1e-6)  # a thousandth of the strongest contrast: flat stays flat
    z = (image - mean) / np.maximum(spread, floor)
    return np.where(seen, np.clip(128 + 32 * z, 1, 255), 0).astype(np.uint8)


FLAT = 1e-3  # of the image's range: a thousandth, under an 8-bit camera's one level in 255


def textured(image: np.ndarray, seen: np.ndarray, window: int) -> np.ndarray:
    """Where the ``window`` around a seen pixel holds contrast: a standard deviation over
    :data:`FLAT` of the image's range (its 1st to 99th percentile over the seen pixels). On any scale
    (uint8, uint16, float 0-1) a real camera's noise alone lies above it; an image without range has no
    textured pixel. The seen pixels on the rim of the view are left out of the windows (the rectified
    image blends them with the black beyond it: contrast that is not the scene's)."""
    image = image.astype(np.float32)
    seen = off_the_rim(seen)
    values = image[seen]
    if values.size == 0:
        return np.zeros(image.shape, bool)
    low, high = np.percentile(values, (1, 99))
    if not high > low:
        return np.zeros(image.shape, bool)
    return seen & (local_spread(image, seen, window)[1] > FLAT * (high - low))


def off_the_rim(seen: np.ndarray) -> np.ndarray:
    """``seen`` less its rim of one pixel: what :func:`textured` can judge."""
    return cv2.erode(seen.astype(np.uint8), np.ones((3, 3), np.uint8), borderValue=0) > 0


@functools.lru_cache(maxsize=16)
def _rows(rows: int, cols: int) -> np.ndarray:
    """``[rows, cols]`` float32: each pixel's row, for ``cv2.remap`` along the rows."""
    return np.ascontiguousarray(np.broadcast_to(np.arange(rows, dtype=np.float32)[:, None], (rows, cols)))


def despeckle(disparity: np.ndarray, pixels: int, spread: float) -> np.ndarray:
    """``disparity`` without its regions of fewer than ``pixels`` pixels whose neighbours differ by at
    most ``spread`` (OpenCV's ``filterSpeckles``, on sixteenths of a pixel)."""
    if pixels <= 0:
        return disparity
    sixteenths = np.where(disparity == INVALID, -16, np.round(disparity * 16)).astype(np.int16)
    cv2.filterSpeckles(sixteenths, -16, pixels, int(round(spread * 16)))
    return np.where(sixteenths == -16, INVALID, disparity).astype(np.float32)


def match(
    left: np.ndarray,
    right: np.ndarray,
    left_seen: np.ndarray,
    right_seen: np.ndarray,
    disparities: int,
    step: float,
    settings: SgbmParameters,
    first: int = 0,
) -> Disparity:
    """The :class:`Disparity` of every pixel of ``left`` (``right``'s match at ``column - disparity``),
    searched over ``disparities`` grid pixels from ``first`` on. Images: the rectified pair (any dtype),
    ``*_seen`` where each camera sees; ``step``: radians per grid pixel."""
    matched = _matched(left, right, left_seen, right_seen, disparities, settings, first)
    return Disparity(matched, despeckle(matched, settings.speckle_pixels(step), settings.speckle_range))


def _matched(left, right, left_seen, right_seen, disparities: int, settings: SgbmParameters, first: int,
             normalised: tuple | None = None):  # fmt: skip
    """SGBM's disparity of ``left``'s pixels, :data:`INVALID` where a check of the module rejects it
    (``normalised``: both images already normalised)."""
    a, b = normalised or (normalise(x, seen, settings.normalise_window)
                          for x, seen in ((left, left_seen), (right, right_seen)))  # fmt: skip
    raw = settings.create(disparities, first).compute(np.ascontiguousarray(a), np.ascontiguousarray(b))
    raw = raw.astype(np.float32) / 16.0
    lowest, highest = first + settings.end_margin, first + disparities - 1 - settings.end_margin
    ok = textured(left, left_seen, settings.block) & (raw >= lowest) & (raw <= highest)
    # the partner's pixel, looked up at column - disparity: outside its view, no match
    rows, cols = raw.shape
    at = np.arange(cols, dtype=np.float32)[None] - np.where(ok, raw, np.float32(0))
    ok &= cv2.remap(right_seen.astype(np.uint8), at, _rows(rows, cols), cv2.INTER_NEAREST,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0  # fmt: skip
    return np.where(ok, raw, INVALID).astype(np.float32)


def round_trip(own: np.ndarray, partner: np.ndarray, own_is_left: bool) -> np.ndarray:
    """Grid pixels by which each pixel's disparity misses the way back: the partner's disparity at the
    pixel ``own`` names (``column - d`` in the right image for the left one, ``column + d`` the other
    way), the nearer of the two columns around it; ``inf`` where neither has one (or ``own`` has none)."""
    rows, cols = own.shape
    has = own != INVALID
    at = np.arange(cols, dtype=np.float32)[None] + np.where(has, -own if own_is_left else own, 0)
    best = np.full(own.shape, np.inf, np.float32)
    for column in (np.floor(at), np.floor(at) + 1):
        back = cv2.remap(partner, column.astype(np.float32), _rows(rows, cols), cv2.INTER_NEAREST,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=INVALID)  # fmt: skip
        best = np.minimum(best, np.where(back != INVALID, np.abs(back - own), np.inf))
    return np.where(has, best, np.inf).astype(np.float32)


class Both(NamedTuple):
    """Both cameras' disparities of a pair after the round trip, and what the round trip found."""

    a: Disparity | None
    b: Disparity | None
    roundtrip_a: np.ndarray | None  # float32 grid pixels each kept pixel of a misses the way back by
    roundtrip_b: np.ndarray | None
    answered: int  # pixels of the asked cameras that SGBM answered inside the range and the views
    returned: int  # of those, the ones whose partner's answer leads back within ``round_trip``
    normalised: tuple[np.ndarray, np.ndarray]  # both images contrast-normalised, as the matcher saw them


def match_both(
    a: np.ndarray,
    b: np.ndarray,
    a_seen: np.ndarray,
    b_seen: np.ndarray,
    disparities: int,
    step: float,
    settings: SgbmParameters,
    directions: tuple[bool, bool] = (True, True),
    first: int = 0,
    spans: tuple[tuple[int, int], tuple[int, int]] | None = None,
) -> Both:
    """Both directions matched (``a`` the left image; for b's pixels both images are mirrored, so that b
    becomes the left image), each answer kept only where the partner's answer at the pixel it names leads
    back to it within ``settings.round_trip`` grid pixels (:func:`round_trip`): an answer where the
    partner cannot see the point (outside its view, occluded) finds no way back. Then each camera asked
    for in ``directions`` is despeckled. ``spans``: the columns each direction's matches need
    (:attr:`.rectify.Rectification.spans`; None: all): each is matched over its own span only, since
    a grid that answers both cameras is padded on each side for one of them."""
    w = settings.normalise_window
    na, nb = normalise(a, a_seen, w), normalise(b, b_seen, w)  # once: the window is symmetric
    cols = a.shape[1]
    (a0, a1), (b0, b1) = spans or ((0, cols), (0, cols))
    for_a = np.full(a.shape, INVALID, np.float32)
    for_b = np.full(a.shape, INVALID, np.float32)
    if a1 > a0:
        part = slice(a0, a1)
        for_a[:, part] = _matched(a[:, part], b[:, part], a_seen[:, part], b_seen[:, part], disparities,
                                  settings, first, (na[:, part], nb[:, part]))  # fmt: skip
    if b1 > b0:
        part = slice(b1 - 1, b0 - 1 if b0 > 0 else None, -1)  # b's span, mirrored
        mirrored = _matched(b[:, part], a[:, part], b_seen[:, part], a_seen[:, part], disparities, settings,
                            first, (nb[:, part], na[:, part]))  # fmt: skip
        for_b[:, b0:b1] = mirrored[:, ::-1]
    out: list = [None, None, None, None]
    answered = returned = 0
    for i, (own, partner, left) in enumerate(((for_a, for_b, True), (for_b, for_a, False))):
        if not directions[i]:
            continue
        miss = round_trip(own, partner, left)
        back = miss <= settings.round_trip
        answered += int((own != INVALID).sum())
        returned += int(back.sum())
        kept = np.where(back, own, INVALID).astype(np.float32)
        out[i] = Disparity(kept, despeckle(kept, settings.speckle_pixels(step), settings.speckle_range))
        out[2 + i] = np.where(back, miss, 0).astype(np.float32)
    return Both(*out, answered, returned, (na, nb))


class RowCheck(NamedTuple):
    """How far off its epipolar row a pair's matches lie (:func:`row_offsets`)."""

    sampled: int  # matches sampled
    median_px: float  # median |row offset| of the best-correlating window, grid pixels
    off_share: float  # share of matches whose best window lies more than a pixel off their row


def row_offsets(
    left: np.ndarray,
    right: np.ndarray,
    disparity: np.ndarray,
    window: int,
    row_scale: np.ndarray | None = None,
    reach: int = 4,
    samples: int = 500,
    seed: int = 0,
) -> RowCheck:
    """Whether the matches lie on their epipolar rows: at up to ``samples`` matched pixels of ``left``
    (``disparity``: its checked disparity), where in ``[-reach, reach]`` grid pixels of rows and of
    columns around the partner's pixel (``column - disparity``) the partner's window correlates best with
    the pixel's own (zero-mean normalised cross-correlation of ``window`` x ``window`` contrast-normalised
    pixels), and how far off the row that lies, sub-pixel by a parabola. The columns are searched too, so
    that the matcher's own choice of the disparity (the best along the row) does not favour the row: a
    pair whose calibration and motion are right has its best window within a fraction of a pixel of its
    row; images that contradict them (another scene, noise, a wrong pose or focal length) put it anywhere
    in the square: a median of about half the reach. ``row_scale``: per column, the length of a row step
    in column steps (on the sphere, ``sin theta`` of the column's angle from the baseline); only columns
    where it is a half or more are sampled: nearer an epipole the rows crowd together, neighbouring rows
    hold nearly the same pixels and the best one is a matter of noise. ``left``, ``right``: the rectified
    pair contrast-normalised, as the matcher saw it (:attr:`Both.normalised`)."""
    rows, cols = disparity.shape
    half = window // 2
    where = np.flatnonzero((disparity != INVALID).ravel())
    r, c = np.unravel_index(where, disparity.shape)
    inner = (r >= half + reach) & (r < rows - half - reach) & (c >= half) & (c < cols - half)
    if row_scale is not None:
        inner &= np.abs(row_scale[c]) >= 0.5
    r, c = r[inner], c[inner]
    if len(r) > samples:
        pick = np.random.default_rng(seed).choice(len(r), samples, replace=False)
        r, c = r[pick], c[pick]
    if len(r) == 0:
        return RowCheck(0, float("nan"), float("nan"))
    a, b = np.ascontiguousarray(left, np.float32), np.ascontiguousarray(right, np.float32)
    offsets = np.arange(-half, half + 1)
    dy, dx = np.meshgrid(offsets, offsets, indexing="ij")
    own = a[r[:, None, None] + dy, c[:, None, None] + dx].reshape(len(r), -1)
    own = own - own.mean(1, keepdims=True)
    own_norm = np.linalg.norm(own, axis=1) + 1e-6
    x0 = (c - disparity[r, c])[:, None, None] + dx
    y0 = r[:, None, None] + dy
    scores = np.full((len(r), 2 * reach + 1), -np.inf, np.float32)  # the best over the columns, per row
    for row_shift in range(-reach, reach + 1):
        y = np.ascontiguousarray((y0 + row_shift).reshape(len(r), -1), np.float32)
        for column_shift in range(-reach, reach + 1):
            x = np.ascontiguousarray((x0 + column_shift).reshape(len(r), -1), np.float32)
            theirs = cv2.remap(b, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            theirs = theirs - theirs.mean(1, keepdims=True)
            ncc = (own * theirs).sum(1) / (own_norm * (np.linalg.norm(theirs, axis=1) + 1e-6))
            scores[:, row_shift + reach] = np.maximum(scores[:, row_shift + reach], ncc)
    best = scores.argmax(1)
    inside = (best > 0) & (best < 2 * reach)
    lo, mid, hi = (scores[np.arange(len(r)), np.clip(best + k, 0, 2 * reach)] for k in (-1, 0, 1))
    curve = lo - 2 * mid + hi
    with np.errstate(divide="ignore", invalid="ignore"):
        sub = np.where(inside & (curve < 0), 0.5 * (lo - hi) / curve, 0.0)
    offset = np.abs(best - reach + np.clip(sub, -0.5, 0.5))
    return RowCheck(len(r), float(np.median(offset)), float((offset > 1.0).mean()))
