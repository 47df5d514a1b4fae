"""The rectified matcher behind the :class:`~.matchers.Matcher` interface: every pair rectified on the
sphere and matched by OpenCV's semi-global matcher (:func:`.pipeline.rectify_pair`,
:func:`.pipeline.match_pair`, with :class:`.pipeline.SgbmSettings`), each image's pairs fused
(:func:`.fuse.fuse`); over a recording, each camera's body mask and the pixels that do not move with the
scene left out of its matches, and every pair judged by its evidence."""

from __future__ import annotations

import math
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch

from ..cameras.base import CameraModel
from ..data.layouts import Frame, RigLayout
from ..options.memory import check_memory
from .features import Features, features
from .fuse import fuse
from .mapback import PixelMaps
from .matchers import ImageMaps
from .motion import MOTION_FEATURES, check_motion
from .pairing import Pairing, pair_pose
from .pipeline import SgbmSettings, Timer, grey, match_pair, pair_step, partner_pair, rectify_pair
from .rectify import Rectification, RectificationCache
from .static import StaticFinder, usable

# Peak memory of matching one pair: a fixed part and a part per pixel of its larger image at the cameras'
# own resolution (the rays, the rectification's tables, both rectified images, SGBM's buffers and the
# maps back). Measured 44 MiB at 256 px, 148-172 MiB at 512, 509-518 at 1024 and about 1.9 GiB at 2048
# (scripts/bench/bench_stereo_memory.py; tests/test_multiview.py checks a 512 px pair against it): each
# 0.9 of this bound or less.
MEMORY_BASE = 64 * 2**20
MEMORY_PER_PIXEL = 512


def pair_memory(pixels: float) -> float:
    """Bytes one pair of images of ``pixels`` pixels needs at its peak (:data:`MEMORY_PER_PIXEL`)."""
    return MEMORY_BASE + MEMORY_PER_PIXEL * pixels


@dataclass(frozen=True)
class SgbmMatcher:
    """The rectified SGBM pipeline with its :class:`~.pipeline.SgbmSettings` (module docstring), one
    :class:`~.matchers.Matcher`."""

    settings: SgbmSettings = field(default_factory=SgbmSettings)
    name: ClassVar[str] = "sgbm"

    def __post_init__(self) -> None:
        if not isinstance(self.settings, SgbmSettings):
            raise ValueError(f"settings: {type(self.settings).__name__}; an SgbmSettings expected")

    @property
    def min_baseline(self) -> float:
        return self.settings.min_baseline

    def maps(
        self, image, partner_image, camera, partner_camera, T_ref_to_partner
    ) -> tuple[np.ndarray, np.ndarray]:
        T = T_ref_to_partner.numpy() if isinstance(T_ref_to_partner, torch.Tensor) else T_ref_to_partner
        rect = rectify_pair(camera, partner_camera, np.asarray(T), self.settings, (True, False))
        found, _ = match_pair(image, partner_image, rect, self.settings, (True, False))
        return found.distance, found.dense

    def recording(self, layout: RigLayout, pairings: list[Pairing], timer: Timer) -> SgbmRecording:
        return SgbmRecording(layout, self.settings, timer, pairings)

    def _scale(self, camera: CameraModel) -> float:
        """The pair's pixels over the camera's: above 1 where ``resolution`` is finer than its own."""
        if self.settings.resolution is None:
            return 1.0
        return max(1.0, (pair_step(camera, camera, None) / self.settings.resolution) ** 2)

    def memory(self, camera: CameraModel) -> float:
        return pair_memory(camera.width * camera.height * self._scale(camera))

    def check_memory(self, name: str, camera: CameraModel, where: str) -> None:
        scale = self._scale(camera)
        what = f"{MEMORY_BASE // 2**20} MiB + {MEMORY_PER_PIXEL} bytes a pixel of a pair"
        if scale > 1:
            what += f", x {scale:.3g} at --resolution {math.degrees(self.settings.resolution):g} degrees"
        check_memory(where, f"{camera.width}x{camera.height}", self.memory(camera), what)

    def record(self) -> dict[str, Any]:
        s = self.settings
        ranges = ("min_distance", "max_distance", "resolution", "min_baseline", "smooth", "max_disparities",
                  "min_confidence")  # fmt: skip
        return {"matcher": self.name, **{k: getattr(s, k) for k in ranges}, **vars(s.sgbm)}


def static_masks(layout: RigLayout, max_distance: float, pairs: int = 12) -> dict[str, np.ndarray]:
    """Each camera's pixels that do not move with the scene (:class:`.static.StaticFinder`), from up to
    ``pairs`` pairs of its consecutive images spread over the recording (every sequence)."""
    out = {}
    for name, spec in layout.cameras.items():
        finder = StaticFinder(spec.camera, max_distance)
        found = []
        for sequence in layout.sequences():
            frames = layout.frames(sequence, name)
            found += [(sequence, a, b) for a, b in zip(frames, frames[1:], strict=False)]
        for sequence, a, b in found[:: max(1, len(found) // pairs)][:pairs]:
            images = [layout.read_image(sequence, name, frame) for frame in (a, b)]
            finder.add(grey(images[0]), grey(images[1]), pair_pose(layout, name, a, name, b))
        out[name] = finder.mask
    return out


class SgbmRecording:
    """:class:`SgbmMatcher`'s run over a recording (:class:`~.matchers.RecordingMatches`): each pair of
    images matched once, for the images of the pair that ask for it (``pairings``: one, or both), and
    kept until they have taken their maps; each image's maps against its partners fused."""

    def __init__(self, layout: RigLayout, settings: SgbmSettings, timer: Timer, pairings: list[Pairing]):
        self.layout, self.settings, self.timer = layout, settings, timer
        start = time.perf_counter()
        self.static = static_masks(layout, settings.max_distance)
        self.masks = {name: usable(layout.read_mask(name), self.static[name]) for name in layout.cameras}
        timer.add("motion", start)
        self.rectifications = RectificationCache(max_entries=64)
        self.wanted: dict[tuple, set[tuple[str, int]]] = defaultdict(set)  # pair -> the images asking
        for pairing in pairings:
            for partner in pairing.partners:
                key, _, _ = self._key(
                    pairing.sequence, (pairing.camera, pairing.frame), (partner.camera, partner.frame)
                )
                self.wanted[key].add((pairing.camera, pairing.frame.key))
        self.maps: dict[tuple, dict[tuple, PixelMaps | None]] = {}
        self.unmatched: dict[str, str] = {}  # pair name -> why no map (no overlap, too short a baseline,
        # a motion its images do not explain, images that contradict the pair's geometry)
        # pair name -> its evidence (round trip, rows, a motion's residuals)
        self.checks: dict[str, dict] = {}
        self.described: dict[tuple, Features] = {}

    @staticmethod
    def _key(sequence: str, one: tuple[str, Frame], other: tuple[str, Frame]) -> tuple:
        a, b = sorted((one, other), key=lambda x: (x[1].key, x[0]))  # the earlier image is camera a
        return (sequence, a[0], a[1].key, b[0], b[1].key), a, b

    def get(self, sequence: str, own: tuple[str, Frame], other: tuple[str, Frame]) -> PixelMaps | None:
        """``own``'s maps against ``other`` (None where the pair is left out)."""
        key, a, b = self._key(sequence, own, other)
        if key not in self.maps:
            self.maps[key] = self._match(sequence, a, b, self.wanted.pop(key, {(own[0], own[1].key)}))
        entry = self.maps[key]
        found = entry.pop((own[0], own[1].key), None)
        if not entry:
            del self.maps[key]
        return found

    def _match(self, sequence: str, a: tuple[str, Frame], b: tuple[str, Frame], wanted: set) -> dict:
        layout, s = self.layout, self.settings
        sides = (a[0], a[1].key), (b[0], b[1].key)
        directions = tuple(side in wanted for side in sides)
        name = f"{sequence}: {a[0]}/{a[1].key} ~ {b[0]}/{b[1].key}"
        nothing_here = {side: None for side, want in zip(sides, directions, strict=True) if want}
        start = time.perf_counter()
        T = pair_pose(layout, a[0], a[1], b[0], b[1])
        cameras = layout.cameras[a[0]].camera, layout.cameras[b[0]].camera
        residual, record, images = 0.0, {}, None
        if a[0] == b[0]:  # one camera at two instants: its motion checked against its images first
            images = [layout.read_image(sequence, cam, frame) for cam, frame in (a, b)]
            found = [
                self._features(sequence, cam, frame, image)
                for (cam, frame), image in zip((a, b), images, strict=True)
            ]
            verdict = check_motion(found[0], cameras[0], found[1], cameras[1], T)
            record = verdict.record()
            start = self.timer.add("motion", start)
            if verdict.left_out is not None:
                self.checks[name] = record
                self.unmatched[name] = verdict.left_out
                return nothing_here
            T, residual = verdict.T_a_to_b, verdict.residual
        rect = partner_pair(*cameras, T, s, directions, self.rectifications)
        if not isinstance(rect, Rectification):  # left out, and why
            self.unmatched[name] = rect
            return nothing_here
        self.timer.add("rectify", start)
        images = images or [layout.read_image(sequence, cam, frame) for cam, frame in (a, b)]
        pair_masks = (self.masks[a[0]], self.masks[b[0]])
        maps = match_pair(images[0], images[1], rect, s, directions, self.timer, pair_masks, residual)
        evidence = next(m.evidence for m in maps if m is not None)
        self.checks[name] = {**record, **evidence.record()}
        if evidence.contradicted:
            self.unmatched[name] = evidence.contradicted
            return nothing_here
        return {side: m for side, m, want in zip(sides, maps, directions, strict=True) if want}

    def image(self, pairing: Pairing, image: np.ndarray) -> ImageMaps:
        """``pairing``'s maps against each of its partners, fused; a partner whose distances disagree with
        the others' is named, not fused."""
        own = (pairing.camera, pairing.frame)
        found = [(p, self.get(pairing.sequence, own, (p.camera, p.frame))) for p in pairing.partners]
        used = [(p, m) for p, m in found if m is not None]
        start = time.perf_counter()
        fused = fuse([m for _, m in used], self.settings.min_confidence) if used else None
        self.timer.add("fuse", start)
        disagree: dict[str, str] = {}
        if fused is not None:
            disagree = {
                f"{used[k][0].camera}/{used[k][0].frame.key}": why for k, why in fused.left_out.items()
            }
            used = [pm for k, pm in enumerate(used) if k not in fused.left_out]
        return ImageMaps(fused, [p for p, _ in used], disagree)

    def record(self) -> dict[str, Any]:
        return {
            "static": {n: round(float(m.mean()), 4) for n, m in self.static.items()},
            "pairs": self.checks,
            "pairs_left_out": self.unmatched,
        }

    def _features(self, sequence: str, camera: str, frame: Frame, image: np.ndarray) -> Features:
        """An image's SIFT features, kept for the next pair it is in (the time pairs on its two sides)."""
        key = (sequence, camera, frame.key)
        if key not in self.described:
            self.described[key] = features(grey(image), MOTION_FEATURES)
            while len(self.described) > 4 * len(self.layout.cameras):
                self.described.pop(next(iter(self.described)))
        return self.described[key]
