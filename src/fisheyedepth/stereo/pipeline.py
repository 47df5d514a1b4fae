"""One pair of images to distance from geometry, by the rectified SGBM pipeline: :class:`SgbmSettings`,
:func:`rectify_pair` (its range and grid step from the pair's geometry) and :func:`match_pair`, which runs a
pair (a rig pair at one instant, or one camera at two instants) through :mod:`.rectify`, :mod:`.match`,
:mod:`.fill` and :mod:`.mapback`, for either image or both. The live rig (:mod:`.live`) and a recording's
run (:mod:`.sgbm`) are built on it. Metric throughout: the calibration's baselines and the odometry's
motion carry the scale.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from ..cameras.base import CameraModel
from ..utils import is_number, is_whole
from .fill import fill, matchable
from .fuse import Fused
from .mapback import Evidence, PixelMaps, to_pixels
from .match import SgbmParameters, match_both, row_offsets
from .pairing import MIN_BASELINE
from .rectify import (
    RECTIFICATIONS,
    Rectification,
    RectificationCache,
    nearest_parallax,
    pair_step,
    remap,
)

STAGES = ("motion", "rectify", "match", "fill", "map_back", "fuse")  # "motion": a time pair's check
# A rig pair whose parallax at the nearest distance is under this many grid pixels is left out: one pixel
# of disparity error is already 6 % of the nearest distance there, and 25 % at four times it.
MIN_PARALLAX = 16


@dataclass(frozen=True)
class SgbmSettings:
    """``min_distance``, ``max_distance``: metres, the range searched (the nearest sets the disparity
    range; beyond the farthest nothing is kept, and the dense map stops there); ``resolution``: radians
    per rectified pixel (None: the coarser camera of each pair); ``min_baseline``: metres a camera must
    have moved for its previous image to be a partner; ``sgbm``: OpenCV's matcher's parameters
    (:class:`~.match.SgbmParameters`);
    ``smooth``: the median window over filled pixels (:func:`~.fill.fill`); ``max_disparities``: the
    most grid pixels of parallax one pair searches (a longer range coarsens its step: :func:`pair_range`);
    ``min_confidence``: the least fused confidence a kept pixel needs (:func:`~.fuse.fuse`; 0: every pixel
    the evidence keeps)."""

    min_distance: float = 0.3
    max_distance: float = 80.0
    resolution: float | None = None
    min_baseline: float = MIN_BASELINE
    sgbm: SgbmParameters = field(default_factory=SgbmParameters)
    smooth: int = 5
    max_disparities: int = 256
    min_confidence: float = 0.0

    def __post_init__(self) -> None:
        for name in ("min_distance", "max_distance", "resolution", "min_baseline", "min_confidence"):
            value = getattr(self, name)
            if not (value is None and name == "resolution") and not is_number(value):
                raise ValueError(f"{name}: {value!r}; a number expected")
        for name in ("smooth", "max_disparities"):
            if not is_whole(getattr(self, name)):
                raise ValueError(f"{name}: {getattr(self, name)!r}; a whole number expected")
        if not isinstance(self.sgbm, SgbmParameters):
            raise ValueError(f"sgbm: {type(self.sgbm).__name__}; an SgbmParameters expected")
        if not 0 < self.min_distance < self.max_distance < math.inf:
            raise ValueError(
                f"--min-distance, --max-distance: {self.min_distance}, {self.max_distance}; need "
                "0 < min-distance < max-distance < inf"
            )
        if self.resolution is not None and not 0 < self.resolution < math.radians(10):
            raise ValueError(f"--resolution: {math.degrees(self.resolution):g} degrees; need 0 < it < 10")
        if not self.min_baseline > 0:
            raise ValueError(f"min_baseline: {self.min_baseline} metres; must be > 0")
        if not 0 <= self.min_confidence < 1:
            raise ValueError(f"--min-confidence: {self.min_confidence}; need 0 <= it < 1")
        if not 16 <= self.max_disparities <= 1024:
            raise ValueError(f"max_disparities: {self.max_disparities}; 16 to 1024")
        if self.smooth not in (0, 3, 5):
            raise ValueError(f"smooth: {self.smooth}; 0, 3 or 5")


# OpenCV's and torch's thread counts are the process's: calls that match pairs side by side (one thread
# of each a pair) set them to 1 while any such call runs, and the last to finish restores them
_THREADS = threading.Lock()
_SIDE_BY_SIDE = {"calls": 0, "saved": (1, 1)}


@contextlib.contextmanager
def one_thread_each():
    """OpenCV and torch on one thread each while inside (for pairs matched side by side on threads of
    our own), restored by the last of any concurrent callers to leave."""
    with _THREADS:
        if _SIDE_BY_SIDE["calls"] == 0:
            _SIDE_BY_SIDE["saved"] = (cv2.getNumThreads(), torch.get_num_threads())
            cv2.setNumThreads(1)
            torch.set_num_threads(1)
        _SIDE_BY_SIDE["calls"] += 1
    try:
        yield
    finally:
        with _THREADS:
            _SIDE_BY_SIDE["calls"] -= 1
            if _SIDE_BY_SIDE["calls"] == 0:
                cv2.setNumThreads(_SIDE_BY_SIDE["saved"][0])
                torch.set_num_threads(_SIDE_BY_SIDE["saved"][1])


class Timer:
    """Seconds spent per stage (:data:`STAGES`), summed over calls; threads add up."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)

    def add(self, stage: str, since: float) -> float:
        now = time.perf_counter()
        self.seconds[stage] += now - since
        return now

    def rounded(self) -> dict[str, float]:
        return {stage: round(self.seconds.get(stage, 0.0), 4) for stage in STAGES}


def grey(image: np.ndarray | torch.Tensor) -> np.ndarray:
    """An ``H x W`` or ``H x W x C`` array (uint8, uint16 or float), or a ``[1, C, H, W]`` tensor, as
    ``H x W`` float32 grey on its own scale (the matcher normalises contrast)."""
    if isinstance(image, torch.Tensor):
        return image.detach().cpu().float().reshape(-1, *image.shape[-2:]).mean(0).numpy()
    image = np.asarray(image)
    if image.ndim == 3:
        image = image.astype(np.float32).mean(2)
    return image.astype(np.float32)


def match_pair(
    image_a: np.ndarray | torch.Tensor,
    image_b: np.ndarray | torch.Tensor,
    rect: Rectification,
    settings: SgbmSettings,
    directions: tuple[bool, bool] = (True, True),
    timer: Timer | None = None,
    masks: tuple[np.ndarray | None, np.ndarray | None] = (None, None),
    residual: float = 0.0,
) -> tuple[PixelMaps | None, PixelMaps | None]:
    """The pair's distance maps at each camera's own pixels (:class:`~.mapback.PixelMaps`), for camera a
    and camera b as ``directions`` asks (None for the other). Images: whatever :func:`grey` takes.
    ``masks``: each camera's usable pixels (``H x W``, nonzero: the scene; zero: its own body, or what
    does not move with the scene), None where all are. ``residual``: radians of the pair's pose its
    images leave unexplained (its epipolar error; 0: a calibrated rig pair), carried into the maps for
    fusion in grid pixels. Both directions are matched whatever is asked (the round trip needs both);
    the maps carry the pair's :class:`~.mapback.Evidence`, and where the images contradict the pair's
    geometry they keep no pixel."""
    if not any(directions):
        raise ValueError("directions: neither camera asked for")
    if not all(rect.directions):
        raise ValueError(
            f"rect: built for {rect.directions}; the round trip matches both ways, so its grid answers both "
            "cameras (directions (True, True))"
        )
    timer = timer or Timer()
    start = time.perf_counter()
    a, b = remap(grey(image_a), rect.a), remap(grey(image_b), rect.b)
    seen = []
    for side, mask in zip((rect.a, rect.b), masks, strict=True):
        usable = side.valid
        if mask is not None:
            usable = usable & (remap((np.asarray(mask) > 0).astype(np.uint8) * 255, side) > 127)
        seen.append(usable)
    start = timer.add("rectify", start)
    d = rect.disparities
    first = rect.first_disparity
    m = settings.sgbm
    pixel = math.sqrt(rect.grid.step * rect.grid.phi_step)  # radians: a grid pixel's side, on the mean
    found = match_both(a, b, seen[0], seen[1], d, pixel, m, directions, first, rect.spans)
    grid = rect.grid
    row_scale = grid.row_scale()  # a row step, in columns
    na, nb = found.normalised
    left, right, disparity = (na, nb, found.a.checked) if directions[0] else (nb, na, found.b.checked)
    if not directions[0]:  # b's matches, mirrored: b the left image
        left, right, disparity, row_scale = (x[..., ::-1] for x in (left, right, disparity, row_scale))
    evidence = judge(
        found.answered, found.returned, row_offsets(left, right, disparity, ROW_WINDOW, row_scale)
    )
    start = timer.add("match", start)
    out: list[PixelMaps | None] = []
    for side, disparity, miss, own, partner, left in (
        ("a", found.a, found.roundtrip_a, seen[0], seen[1], True),
        ("b", found.b, found.roundtrip_b, seen[1], seen[0], False),
    ):
        if disparity is None:
            out.append(None)
            continue
        where = matchable(own, partner, d, partner_left=left, first=first)
        block = m.block
        filled = fill(disparity.checked, where, settings.smooth, block // 2, 4 * block)
        start = timer.add("fill", start)
        maps = to_pixels(disparity.checked, filled, rect, side, miss)
        near, far = settings.min_distance, settings.max_distance  # outside the range searched: no match
        kept = (maps.distance >= near) & (maps.distance <= far)
        filled = (maps.dense >= near) & (maps.dense <= far)
        if evidence.contradicted:
            kept = filled = np.zeros_like(kept)
        maps = PixelMaps(
            np.where(kept, maps.distance, 0).astype(np.float32),
            np.where(filled, maps.dense, 0).astype(np.float32),
            np.where(kept, maps.parallax, 0).astype(np.float32),
            np.where(filled, maps.dense_parallax, 0).astype(np.float32),
            maps.step,
            np.where(kept, maps.roundtrip, 0).astype(np.float32),
            float(residual) / rect.grid.step,
            evidence,
        )
        out.append(maps)
        start = timer.add("map_back", start)
    return out[0], out[1]


# A pair's images contradict its geometry when its matches' best rows lie over a pixel off on the median
# (SGBM needs its epipolar rows to about a pixel; matches of a right pair lie within a fraction of one,
# and images that have nothing to do with the pair put them anywhere in the row check's reach of 4: a
# median of about 2), or when fewer than a third of its answers close the round trip (two independent
# searches that agree by chance: measured in BENCHMARKS.md "Metric distance from geometry").
MAX_ROW_OFFSET = 1.0
MIN_ROUND_TRIP = 1 / 3
MIN_ROW_SAMPLES = 50
ROW_WINDOW = 11  # grid pixels: the row check's window, twice SGBM's so that its choice weighs little


def judge(answered: int, returned: int, rows) -> Evidence:
    """The pair's :class:`~.mapback.Evidence` from its round trip and its row check, and its verdict."""
    why = None
    if answered and returned / answered < MIN_ROUND_TRIP:
        why = (
            f"{returned / answered:.0%} of its matches close the round trip between its two images "
            f"(a pair whose images show one scene from the calibrated poses closes most)"
        )
    elif rows.sampled >= MIN_ROW_SAMPLES and rows.median_px > MAX_ROW_OFFSET:
        why = (
            f"its matches lie {rows.median_px:.2f} px off their epipolar rows on the median "
            f"({rows.off_share:.0%} over a pixel): the images contradict the calibration or the motion"
        )
    return Evidence(answered, returned, rows.sampled, rows.median_px, rows.off_share, why)


# A window matcher compares one surface seen from two directions: beyond a triangulation angle of 30
# degrees its windows differ by a foreshortening of 15 % or more at head-on incidence, and by 70 % at 30
# degrees of incidence: no pair searches a parallax larger than this, whatever its nearest distance.
MAX_TRIANGULATION_DEG = 30.0


def pair_range(
    camera_a: CameraModel, camera_b: CameraModel, baseline: float, settings: SgbmSettings
) -> tuple[float, float]:
    """A pair's nearest distance and grid step from its geometry: the nearest is where its largest
    parallax reaches :data:`MAX_TRIANGULATION_DEG` (or ``settings.min_distance`` where that is farther),
    and the step the coarser camera's angular resolution (or ``settings.resolution``), coarsened where
    that range would need more than ``settings.max_disparities`` grid pixels (a long baseline: a car's
    1.3 m motion pair searches 30 degrees at 4.4 times its camera's step, and still resolves a point at
    40 m with 8 pixels of parallax)."""
    step = pair_step(camera_a, camera_b, settings.resolution)
    widest = math.radians(MAX_TRIANGULATION_DEG)
    nearest = settings.min_distance
    if baseline > 0:
        nearest = max(nearest, baseline / math.sin(widest))
        largest = math.asin(min(1.0, baseline / nearest))
        step = max(step, largest / settings.max_disparities)
    return nearest, step


def rectify_pair(
    camera_a: CameraModel,
    camera_b: CameraModel,
    T_a_to_b: np.ndarray,
    settings: SgbmSettings,
    directions: tuple[bool, bool] = (True, True),
    cache: RectificationCache = RECTIFICATIONS,
) -> Rectification:
    """The pair's :class:`~.rectify.Rectification` for ``settings`` (its range and step from its geometry,
    :func:`pair_range`, and the matcher's end margin), through ``cache``: built once per pair, calibration
    and motion. Its grid answers both cameras whatever ``directions`` asks (the round trip matches both
    ways); its range is what the cameras asked can show."""
    s = settings
    baseline = float(np.linalg.norm(np.asarray(T_a_to_b, dtype=np.float64)[:3, 3]))
    nearest, step = pair_range(camera_a, camera_b, baseline, s)
    return cache.get(camera_a, camera_b, T_a_to_b, nearest, step, (True, True), s.max_distance,
                     s.sgbm.end_margin, tuple(directions))  # fmt: skip


def partner_pair(
    camera_a: CameraModel,
    camera_b: CameraModel,
    T_a_to_b: np.ndarray,
    settings: SgbmSettings,
    directions: tuple[bool, bool] = (True, True),
    cache: RectificationCache = RECTIFICATIONS,
) -> Rectification | str:
    """:func:`rectify_pair` for a pair the rig or the recording offers, or why it is left out: its
    baseline shows under :data:`MIN_PARALLAX` grid pixels of parallax at the nearest distance, or its
    views do not overlap within the range."""
    baseline = float(np.linalg.norm(np.asarray(T_a_to_b)[:3, 3]))
    if baseline < 1e-6:  # a micrometre: what composing two equal extrinsics leaves in float64
        return "T_a_to_b: the two camera centres coincide; a pair without a baseline has no parallax"
    nearest, step = pair_range(camera_a, camera_b, baseline, settings)
    if nearest_parallax(baseline, nearest, step) < MIN_PARALLAX:
        return (
            f"a baseline of {baseline:.3g} m shows under {MIN_PARALLAX} pixels of parallax at the nearest "
            f"distance ({nearest:.3g} m)"
        )
    if nearest >= settings.max_distance:
        return f"a baseline of {baseline:.3g} m triangulates nothing nearer than {nearest:.3g} m"
    try:
        return rectify_pair(camera_a, camera_b, T_a_to_b, settings, directions, cache)
    except ValueError as err:
        return str(err)


def nothing(camera: CameraModel) -> Fused:
    """The fused maps of an image without a partner: every pixel 0."""
    zeros = np.zeros((camera.height, camera.width), np.float32)
    return Fused(zeros, zeros.copy(), zeros.copy(), np.zeros(zeros.shape, np.uint8))
