"""Which images a multi-view run matches with which: each image's partners among the rig's other cameras
at its instant (``rig``) and its own camera's images that moved far enough (``time``), and every image
left out, with why."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from ..data.layouts import Frame, RigLayout

SOURCES = ("rig", "time")
MIN_BASELINE = 0.05  # metres a camera must have moved for its earlier or later image to be a partner
SAME_INSTANT_NS = 1_000_000  # two cameras' images this close in time are one instant of the rig


@dataclass(frozen=True)
class Partner:
    camera: str
    frame: Frame


@dataclass(frozen=True)
class Pairing:
    sequence: str
    camera: str
    frame: Frame
    partners: tuple[Partner, ...]

    @property
    def name(self) -> str:
        return f"{self.sequence}/{self.camera}/{self.frame.key}"


def check_sources(sources: tuple[str, ...]) -> tuple[str, ...]:
    if not sources or set(sources) - set(SOURCES):
        raise ValueError(f"--sources: {','.join(sources)!r}; choose from {','.join(SOURCES)}")
    return sources


def pair_pose(
    layout: RigLayout,
    camera_a: str,
    frame_a: Frame,
    camera_b: str,
    frame_b: Frame,
    same_instant_ns: int = SAME_INSTANT_NS,
) -> np.ndarray:
    """``T_a_to_b`` of two images: each camera's extrinsics and each instant's body pose. Two cameras of
    one instant (within ``same_instant_ns``) are a rig pair: their extrinsics alone, so that its
    rectification is built once (the body moves 0.4 mm in a millisecond at 0.4 m/s)."""
    if camera_a != camera_b and abs(frame_a.key - frame_b.key) <= same_instant_ns:
        return np.linalg.inv(layout.cameras[camera_b].cam_to_body) @ layout.cameras[camera_a].cam_to_body
    world_a = frame_a.pose @ layout.cameras[camera_a].cam_to_body
    world_b = frame_b.pose @ layout.cameras[camera_b].cam_to_body
    return np.linalg.inv(world_b) @ world_a


def _centre(layout: RigLayout, camera: str, frame: Frame) -> np.ndarray:
    return (frame.pose @ layout.cameras[camera].cam_to_body)[:3, 3]


def pairings(
    layout: RigLayout,
    sources: tuple[str, ...] = SOURCES,
    same_instant_ns: int = SAME_INSTANT_NS,
    min_baseline: float = MIN_BASELINE,
    max_frames_apart: int = 5,
) -> list[Pairing]:
    """Every image of the recording with its partners: each other camera's image within
    ``same_instant_ns`` (``rig``); and of its own camera the nearest earlier and the nearest later image,
    within ``max_frames_apart``, whose centre is ``min_baseline`` metres or more from its own (``time``)."""
    check_sources(sources)
    out = []
    for sequence in layout.sequences():
        frames = {camera: layout.frames(sequence, camera) for camera in layout.cameras}
        for camera, own in frames.items():
            for i, frame in enumerate(own):
                partners: list[Partner] = []
                if "rig" in sources:
                    for other, theirs in frames.items():
                        if other == camera or not theirs:
                            continue
                        nearest = min(theirs, key=lambda f: abs(f.key - frame.key))
                        if abs(nearest.key - frame.key) <= same_instant_ns:
                            partners.append(Partner(other, nearest))
                if "time" in sources:
                    here = _centre(layout, camera, frame)
                    earlier = own[max(0, i - max_frames_apart) : i][::-1]
                    later = own[i + 1 : i + 1 + max_frames_apart]
                    for side in (earlier, later):
                        moved = (
                            f
                            for f in side
                            if np.linalg.norm(_centre(layout, camera, f) - here) >= min_baseline
                        )
                        found = next(moved, None)
                        if found is not None:
                            partners.append(Partner(camera, found))
                out.append(Pairing(sequence, camera, frame, tuple(partners)))
    return out


NO_PARTNER = "no partner at its instant or among its camera's neighbours"


def images_left_out(layout: RigLayout, planned: list[Pairing]) -> dict[str, str]:
    """Every image of the recording the run does not match, by name, with why: no partner, outside the
    poses' time range, in a gap of the poses, or a file name that is not a timestamp."""
    out = {p.name: NO_PARTNER for p in planned if not p.partners}
    for (sequence, camera), stamps in layout.outside.items():
        out.update({f"{sequence}/{camera}/{t}": "outside the poses' time range" for t in stamps})
    for (sequence, camera), stamps in layout.in_gaps.items():
        out.update({f"{sequence}/{camera}/{t}": "in a gap of the poses (max_pose_gap)" for t in stamps})
    for (sequence, camera), names in layout.not_understood.items():
        out.update({f"{sequence}/{camera}/{n}": "name not understood (<timestamp_ns>.png)" for n in names})
    return out


def nothing_to_match(layout: RigLayout, sources: tuple[str, ...], left_out: dict[str, str]) -> str:
    """Why a recording gives the run no image to match, in one line."""
    reasons: dict[str, int] = defaultdict(int)
    for why in left_out.values():
        reasons[why] += 1
    said = "; ".join(f"{n} {why}" for why, n in reasons.items()) or "no images"
    if sources == ("rig",) and len(layout.cameras) < 2:
        said += " (--sources rig pairs the rig's cameras, and it has one)"
    return said
