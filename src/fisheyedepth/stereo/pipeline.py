"""Distance for every camera of a rig from geometry: rectify, match, fill, map back, fuse.

:func:`match_pair` runs one pair of images (a rig pair at one instant, or one camera at two instants)
through :mod:`.rectify`, :mod:`.match`, :mod:`.fill` and :mod:`.mapback`, for either image or both.
:class:`RigStereo` is the live API a robot calls once per instant: the rig's images, and optionally the
previous instant's with the odometry between them; every camera gets its rig partners (the other cameras
whose view overlaps its own) and its own previous image (once it moved far enough), fused (:mod:`.fuse`).
Metric throughout: the calibration's baselines and the odometry's motion carry the scale.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections import defaultdict
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import NamedTuple

import cv2
import numpy as np
import torch

from ..cameras.base import CameraModel
from ..geometry import MAX_MOTION, rig_extent_problem, rigid_transform
from ..utils import check_threads, is_number, is_whole
from .fill import fill, matchable
from .fuse import Fused, fuse
from .mapback import Evidence, PixelMaps, to_pixels
from .match import MatcherSettings, match_both, row_offsets
from .rectify import (
    RECTIFICATIONS,
    Rectification,
    RectificationCache,
    nearest_parallax,
    pair_step,
    remap,
)
from .refine import MOTION_FEATURES, Features, check_motion, features
from .static import StaticFinder, usable

STAGES = ("motion", "rectify", "match", "fill", "map_back", "fuse")  # "motion": a time pair's check
# A rig pair whose parallax at the nearest distance is under this many grid pixels is left out: one pixel
# of disparity error is already 6 % of the nearest distance there, and 25 % at four times it.
MIN_PARALLAX = 16


@dataclass(frozen=True)
class StereoSettings:
    """``min_distance``, ``max_distance``: metres, the range searched (the nearest sets the disparity
    range; beyond the farthest nothing is kept, and the dense map stops there); ``resolution``: radians
    per rectified pixel (None: the coarser camera of each pair); ``min_baseline``: metres a camera must
    have moved for its previous image to be a partner; ``matcher``: :class:`~.match.MatcherSettings`;
    ``smooth``: the median window over filled pixels (:func:`~.fill.fill`); ``max_disparities``: the
    most grid pixels of parallax one pair searches (a longer range coarsens its step: :func:`pair_range`);
    ``min_confidence``: the least fused confidence a kept pixel needs (:func:`~.fuse.fuse`; 0: every pixel
    the evidence keeps)."""

    min_distance: float = 0.3
    max_distance: float = 80.0
    resolution: float | None = None
    min_baseline: float = 0.05
    matcher: MatcherSettings = field(default_factory=MatcherSettings)
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
        if not isinstance(self.matcher, MatcherSettings):
            raise ValueError(f"matcher: {type(self.matcher).__name__}; a MatcherSettings expected")
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
    settings: StereoSettings,
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
    m = settings.matcher
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
    camera_a: CameraModel, camera_b: CameraModel, baseline: float, settings: StereoSettings
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
    settings: StereoSettings,
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
                     s.matcher.end_margin, tuple(directions))  # fmt: skip


def partner_pair(
    camera_a: CameraModel,
    camera_b: CameraModel,
    T_a_to_b: np.ndarray,
    settings: StereoSettings,
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


def _relative(
    cam_to_body_a: np.ndarray, cam_to_body_b: np.ndarray, b_body_from_a_body: np.ndarray | None = None
):
    """``T_a_to_b`` of two cameras (their ``cam_to_body``), optionally on two instants of the body
    (``b_body_from_a_body``: a's body frame to b's)."""
    motion = np.eye(4) if b_body_from_a_body is None else b_body_from_a_body
    return np.linalg.inv(cam_to_body_b) @ motion @ cam_to_body_a


def nothing(camera: CameraModel) -> Fused:
    """The fused maps of an image without a partner: every pixel 0."""
    zeros = np.zeros((camera.height, camera.width), np.float32)
    return Fused(zeros, zeros.copy(), zeros.copy(), np.zeros(zeros.shape, np.uint8))


class CameraResult(NamedTuple):
    fused: Fused
    partners: tuple[str, ...]  # "<camera>" for a rig partner, "<camera>@previous" for its own motion: fused
    left_out: dict[str, str] = {}  # partner -> why its maps were not fused (contradicted, disagreeing)
    checks: dict[str, dict] = {}  # partner -> its evidence (round trip, row check; a motion's residuals)


class RigStereo:
    """Distance for every camera of a calibrated rig, one call per instant.

    ``cameras``: name -> :class:`~fisheyedepth.cameras.base.CameraModel`; ``cam_to_body``: name -> 4x4
    (camera to body, metres); ``masks``: name -> ``H x W`` usable pixels (nonzero; zero where the camera
    sees the robot itself), optional. Rig pairs are every two cameras whose views overlap within the
    disparity range (the others are listed in ``unpaired``); their rectification is built once, here.
    ``threads``: pairs matched at once. Each camera's own motion since the previous instant is checked
    against its images first (:func:`~.refine.check_motion`: refined, or left out where its images
    leave over a pixel of epipolar error); every pair's images are checked against its geometry
    (:class:`~.mapback.Evidence`); a partner left out is named in its camera's result with why. As the
    rig moves, each camera's pixels that do not move with the scene (a border, an overlay, the robot's
    body: :class:`~.static.StaticFinder`, ``static[name].mask``) are found and left out of its matches.

    Refused with a ValueError naming the argument (docs/faults.md): extrinsics or a motion that are not
    rigid transforms (:func:`~fisheyedepth.geometry.rigid_transform`), cameras over
    :data:`~fisheyedepth.geometry.MAX_RIG_BASELINE` apart, images or masks that are not a mapping by camera
    or hold values that are not finite, ``threads`` beyond the machine's cores. A motion over
    :data:`~fisheyedepth.geometry.MAX_MOTION` is not matched, and named in each camera's ``left_out``."""

    def __init__(
        self,
        cameras: Mapping[str, CameraModel],
        cam_to_body: Mapping[str, np.ndarray],
        settings: StereoSettings | None = None,
        threads: int = 1,
        masks: Mapping[str, np.ndarray] | None = None,
    ):
        for what, given in (("cameras", cameras), ("cam_to_body", cam_to_body), ("masks", masks or {})):
            if not isinstance(given, Mapping):
                raise ValueError(
                    f"{what}: a mapping of camera name -> value expected, got {type(given).__name__}"
                )
        if set(cameras) != set(cam_to_body):
            raise ValueError(
                f"cameras, cam_to_body: name different cameras ({sorted(cameras)}, {sorted(cam_to_body)})"
            )
        for name, camera in cameras.items():
            if not isinstance(camera, CameraModel):
                raise ValueError(f"cameras[{name!r}]: {type(camera).__name__}; a camera model expected")
        self.cameras = dict(cameras)
        self.cam_to_body = {n: rigid_transform(T, f"cam_to_body[{n!r}]") for n, T in cam_to_body.items()}
        spread = rig_extent_problem(self.cam_to_body)
        if spread is not None:
            raise ValueError(f"cam_to_body: {spread}")
        if settings is not None and not isinstance(settings, StereoSettings):
            raise ValueError(f"settings: {type(settings).__name__}; a StereoSettings expected")
        self.settings = settings or StereoSettings()
        self.threads = check_threads(threads, "threads")
        self.masks = dict(masks or {})
        self._check("masks", self.masks, every=False)
        for name, mask in self.masks.items():
            if not np.asarray(mask).any():  # every pixel body: nothing of the camera could be matched
                raise ValueError(f"masks[{name!r}]: no pixel is usable (all zero); leave the camera out")
        self.timer = Timer()
        self._motion_cache = RectificationCache(max_entries=2 * len(self.cameras))
        self._features: dict[str, tuple[np.ndarray, Features]] = {}  # the last images' SIFT, by camera
        # each camera's pixels that do not move with the scene, found as the rig moves (:mod:`.static`)
        self.static = {n: StaticFinder(c, self.settings.max_distance) for n, c in self.cameras.items()}
        self.pairs: dict[tuple[str, str], Rectification] = {}
        self.unpaired: dict[tuple[str, str], str] = {}
        names = list(self.cameras)
        s = self.settings
        for i, a in enumerate(names):
            for b in names[i + 1 :]:
                found = partner_pair(
                    self.cameras[a], self.cameras[b], _relative(*(self.cam_to_body[n] for n in (a, b))), s
                )
                if isinstance(found, Rectification):
                    self.pairs[a, b] = found
                else:
                    self.unpaired[a, b] = found

    def _check(self, what: str, arrays: Mapping[str, np.ndarray], every: bool = True) -> None:
        """Each image (or mask) at its camera's calibrated size; with ``every``, one for every camera."""
        if not isinstance(arrays, Mapping):
            raise ValueError(
                f"{what}: a mapping of camera name -> image expected, got {type(arrays).__name__}"
            )
        missing = sorted(set(self.cameras) - set(arrays)) if every else []
        if missing:
            raise ValueError(f"{what}: no image of camera {', '.join(missing)}")
        for name, array in arrays.items():
            if name not in self.cameras:
                raise ValueError(f"{what}: {name!r} is not a camera of the rig ({', '.join(self.cameras)})")
            camera, shape = self.cameras[name], np.shape(array)
            if len(shape) not in (2, 3) or (shape[1], shape[0]) != (camera.width, camera.height):
                raise ValueError(
                    f"{what}[{name!r}]: shape {shape}, but camera {name!r} is {camera.width}x{camera.height}"
                )
            values = array.detach().cpu().numpy() if isinstance(array, torch.Tensor) else np.asarray(array)
            if values.dtype.kind not in "biuf":
                raise ValueError(f"{what}[{name!r}]: {values.dtype} values; numbers expected")
            if values.dtype.kind == "f" and not np.isfinite(values).all():
                bad = int((~np.isfinite(values)).sum())
                raise ValueError(
                    f"{what}[{name!r}]: {bad} values are not finite (NaN or inf); give finite pixels, and "
                    "leave out what the camera does not see with a mask"
                )

    def usable(self, name: str) -> np.ndarray | None:
        """Camera ``name``'s pixels to match: its mask's, less those found static; None where all are."""
        return usable(self.masks.get(name), self.static[name].mask)

    def _described(self, name: str, image: np.ndarray) -> Features:
        """The SIFT features of camera ``name``'s ``image``: the last call's where it is the same image."""
        last = self._features.get(name)
        return last[1] if last is not None and last[0] is image else features(grey(image), MOTION_FEATURES)

    def __call__(
        self,
        images: Mapping[str, np.ndarray],
        previous: Mapping[str, np.ndarray] | None = None,
        motion: np.ndarray | None = None,
    ) -> dict[str, CameraResult]:
        """Every camera's fused distance at this instant (all zeros, no partners, for a camera with none).
        ``images``: name -> ``H x W`` or ``H x W x 3`` image (every camera of the rig); ``previous``,
        ``motion``: the previous instant's images and the transform of the body frame now to the body
        frame then (``inv(pose_then) @ pose_now``, from the odometry). Calls on one object are made one at
        a time (the threads it matches on set OpenCV's and torch's thread counts for the process)."""
        self._check("images", images)
        if (previous is None) != (motion is None):
            raise ValueError(
                "previous, motion: give both (the previous images and the motion since) or neither"
            )
        s = self.settings
        jobs = []  # (a's label, b's label, a image, b image, rectification or its pose, camera names)
        for (a, b), rect in self.pairs.items():
            jobs.append(((a, b), (b, a), images[a], images[b], rect, (a, b)))
        left_out: dict[str, dict[str, str]] = defaultdict(dict)
        checks: dict[str, dict[str, dict]] = defaultdict(dict)
        described: dict[str, tuple[np.ndarray, Features]] = {}
        if previous is not None:
            self._check("previous", previous, every=False)
            motion = rigid_transform(motion, "motion")
            travelled = float(np.linalg.norm(motion[:3, 3]))
            if travelled > MAX_MOTION:  # not matched, and named for every camera
                why = (
                    f"the body moved {travelled:.4g} m since the previous instant, over {MAX_MOTION:g} m: "
                    "odometry in metres expected (another unit?)"
                )
                left_out.update({name: {f"{name}@previous": why} for name in self.cameras})
                previous = {}
            for name in self.cameras:
                E = self.cam_to_body[name]
                T_now_to_then = _relative(E, E, motion)
                if name in previous and np.linalg.norm(T_now_to_then[:3, 3]) >= s.min_baseline:
                    label = (name, f"{name}@previous")
                    jobs.append((label, None, images[name], previous[name], T_now_to_then, (name, name)))

        # the pixels to match, as the instants before this one found them (this one's motion adds to them
        # for the next): every pair of one call sees the same masks
        usable = {name: self.usable(name) for name in self.cameras}

        def run(job):
            timer = Timer()
            first, second, a, b, rect, cameras = job
            residual, record = 0.0, None
            if not isinstance(rect, Rectification):  # a motion pair: checked and built here, once per motion
                start = time.perf_counter()
                camera = self.cameras[cameras[0]]
                name = cameras[0]  # its motion checked against its images, and its static pixels
                now, then = self._described(name, a), self._described(name, b)
                described[name] = (a, now)  # the next call's previous image
                verdict = check_motion(now, camera, then, camera, rect)
                self.static[name].add(b, a, np.linalg.inv(rect))
                start = timer.add("motion", start)
                record = verdict.record()
                if verdict.left_out is not None:
                    return first, second, (None, None), timer, record, verdict.left_out
                rect = partner_pair(camera, camera, verdict.T_a_to_b, s, (True, False), self._motion_cache)
                residual = verdict.residual
                timer.add("rectify", start)
                if not isinstance(rect, Rectification):  # left out: no partner
                    return first, second, (None, None), timer, record, rect
            masks = tuple(usable[name] for name in cameras)
            maps = match_pair(a, b, rect, s, (True, second is not None), timer, masks, residual)
            return first, second, maps, timer, record, None

        # the motion pairs first (their rectification is built in the job): the longest jobs start first
        order = sorted(range(len(jobs)), key=lambda i: isinstance(jobs[i][4], Rectification))
        per_camera: dict[str, list[tuple[str, PixelMaps]]] = defaultdict(list)

        def collect(done) -> None:  # each partner's maps to its camera, in the rig's order, then the motion
            for first, second, (maps_a, maps_b), timer, record, why in done:
                for stage, seconds in timer.seconds.items():
                    self.timer.seconds[stage] += seconds
                for label, maps in ((first, maps_a), (second, maps_b)):
                    if label is None:
                        continue
                    own, partner = label
                    evidence = next((m.evidence for m in (maps_a, maps_b) if m is not None), None)
                    checks[own][partner] = {**(record or {}), **(evidence.record() if evidence else {})}
                    reason = why or (evidence.contradicted if evidence is not None else None)
                    if reason is not None:
                        left_out[own][partner] = reason
                    elif maps is not None:
                        per_camera[own].append((partner, maps))

        def fused(name: str) -> CameraResult:
            found, why, evidence = per_camera.get(name), dict(left_out.get(name, {})), checks.get(name, {})
            if not found:
                return CameraResult(nothing(self.cameras[name]), (), why, dict(evidence))
            out = fuse([m for _, m in found], s.min_confidence)
            why.update({found[k][0]: reason for k, reason in out.left_out.items()})
            partners = tuple(p for k, (p, _) in enumerate(found) if k not in out.left_out)
            return CameraResult(out, partners, why, dict(evidence))

        names = list(self.cameras)
        with contextlib.ExitStack() as stack:
            mapped = map
            if (
                self.threads > 1
            ):  # pairs side by side, each on one thread of OpenCV's and torch's; then images
                stack.enter_context(one_thread_each())
                mapped = stack.enter_context(ThreadPoolExecutor(self.threads)).map
            results = dict(zip(order, mapped(run, [jobs[i] for i in order]), strict=True))
            collect(results[i] for i in range(len(jobs)))
            start = time.perf_counter()
            out = dict(zip(names, mapped(fused, names), strict=True))
        if previous is not None:
            self._features = described  # this instant's features: the next call's previous ones
        self.timer.add("fuse", start)
        return out
