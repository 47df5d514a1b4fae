"""The live API a robot calls once per instant (:class:`RigStereo`): the rig's images, and optionally the
previous instant's with the odometry between them; every camera gets its rig partners (the other cameras
whose view overlaps its own) and its own previous image (once it moved far enough), each pair through
:func:`.pipeline.match_pair`, fused (:mod:`.fuse`). Metric throughout: the calibration's baselines and the
odometry's motion carry the scale.
"""

from __future__ import annotations

import contextlib
import time
from collections import defaultdict
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np
import torch

from ..cameras.base import CameraModel
from ..geometry import MAX_MOTION, rig_extent_problem, rigid_transform
from ..utils import check_threads
from .features import Features, features
from .fuse import Fused, fuse
from .mapback import PixelMaps
from .motion import MOTION_FEATURES, check_motion
from .pipeline import SgbmSettings, Timer, grey, match_pair, nothing, one_thread_each, partner_pair
from .rectify import Rectification, RectificationCache
from .static import StaticFinder, usable


def _relative(
    cam_to_body_a: np.ndarray, cam_to_body_b: np.ndarray, b_body_from_a_body: np.ndarray | None = None
):
    """``T_a_to_b`` of two cameras (their ``cam_to_body``), optionally on two instants of the body
    (``b_body_from_a_body``: a's body frame to b's)."""
    motion = np.eye(4) if b_body_from_a_body is None else b_body_from_a_body
    return np.linalg.inv(cam_to_body_b) @ motion @ cam_to_body_a


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
    against its images first (:func:`~.motion.check_motion`: refined, or left out where its images
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
        settings: SgbmSettings | None = None,
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
        if settings is not None and not isinstance(settings, SgbmSettings):
            raise ValueError(f"settings: {type(settings).__name__}; a SgbmSettings expected")
        self.settings = settings or SgbmSettings()
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
