"""Traffic in the street world: cars and pedestrians that move on their own tracks.

Every agent is a few boxes in its own frame (x forward, y left, z up; the origin on the ground under its
centre) and a track: its position and heading at every trajectory frame, linearly interpolated between
frames (motion blur renders between them). The kinds, each a failure case of photometric
self-supervision on real drives:

- ``lead`` / ``follower``: a car ahead of (behind) the ego vehicle in its lane at its speed: it does not
  move relative to the cameras, so a warp explains it best at infinite distance;
- ``oncoming``: cars in the other lane of the ego's route, driving the other way;
- ``crossing``: cars on the streets the route crosses (never on one it drives along); they wait while the
  ego or a car of its route is about to pass;
- ``pedestrian``: people walking along the sidewalks, waiting at a kerb while a car is about to pass.

Parked cars are the world's own (static). ``density`` scales how many agents a drive meets; 0 places
none, and the world and the drive are never touched: the traffic draws from its own random stream. It
is at most :data:`MAX_TRAFFIC`.
An agent is left out of a frame in which it would come within :data:`CLEARANCE` of the ego body's
centre (so no camera ever sits inside one).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..options.kinds import Number
from .world import CAR, CAR_COLOURS, FABRIC, Drive, World, _tint, path_heading, rightward

KINDS = ("lead", "follower", "oncoming", "crossing", "pedestrian")
MOVING = 0.01  # metres per frame: an agent faster than this at a frame is "moving" there
CLEARANCE = 4.0  # metres between the ego body's origin and an agent's centre below which it is left out
# The densest traffic rendered. The agents grow with the density, and the tracks' setup with its square:
# each crossing car and pedestrian waits for every car of the route (its oncoming cars grow with the
# density too). Setting up the 620 trajectory frames of ``frames=600`` took 3 s of one CPU thread at
# density 1, 28 s at 4 and 106 s at 8 (697 agents in the 310 m street world), where 1000 would take weeks;
# rendering 64 px frames took twice as long at 8 as without traffic. 8 is eight busy streets.
MAX_TRAFFIC = 8.0
DENSITY = Number(0.0, MAX_TRAFFIC, note="0: no traffic, 1: a busy street")  # its kind and range
CLOTHES = ([0.2, 0.25, 0.5], [0.5, 0.15, 0.15], [0.3, 0.3, 0.3], [0.75, 0.7, 0.55], [0.15, 0.4, 0.25])


@dataclasses.dataclass
class Traffic:
    """``A`` agents over ``F`` trajectory frames, made of ``P`` boxes."""

    kind: list[str]  # [A] one of KINDS
    track: np.ndarray  # [A, F, 3] x, y (metres) and yaw (radians, unwrapped) per frame
    lo: np.ndarray  # [P, 3] box corners in the agent's frame
    hi: np.ndarray  # [P, 3]
    owner: np.ndarray  # [P] int: the agent of each box
    material: np.ndarray  # [P] int
    tint: np.ndarray  # [P, 3]

    @property
    def n_agents(self) -> int:
        return len(self.kind)

    def at(self, time: float) -> np.ndarray:
        """``[A, 3]`` x, y, yaw at a (fractional) trajectory frame; extrapolated past either end."""
        F = self.track.shape[1]
        if F == 1:
            return self.track[:, 0].copy()
        k = int(np.clip(math.floor(time), 0, F - 2))
        u = time - k
        return (1 - u) * self.track[:, k] + u * self.track[:, k + 1]

    def speed(self, frame: int) -> np.ndarray:
        """``[A]`` metres per frame at an integer frame (central difference; one-sided at the ends)."""
        F = self.track.shape[1]
        a, b = max(frame - 1, 0), min(frame + 1, F - 1)
        if a == b:
            return np.zeros(self.n_agents)
        xy = self.track[:, :, :2]
        return np.linalg.norm(xy[:, b] - xy[:, a], axis=-1) / (b - a)

    def moving(self, frame: int) -> np.ndarray:
        """``[A]`` bool: the agents that move at ``frame`` (faster than :data:`MOVING`)."""
        return self.speed(frame) > MOVING

    def boxes_at(self, time: float, ego_xy: np.ndarray) -> dict[str, np.ndarray]:
        """The boxes at ``time`` in the world: local corners ``lo``/``hi``, their agent's ``x``, ``y``,
        ``yaw``, ``owner``, ``material``, ``tint``; agents within :data:`CLEARANCE` of ``ego_xy`` are
        left out."""
        state = self.at(time)
        keep_agent = np.linalg.norm(state[:, :2] - np.asarray(ego_xy)[None, :2], axis=-1) >= CLEARANCE
        keep = keep_agent[self.owner]
        own = self.owner[keep]
        return {
            "lo": self.lo[keep],
            "hi": self.hi[keep],
            "x": state[own, 0],
            "y": state[own, 1],
            "yaw": state[own, 2],
            "owner": own,
            "material": self.material[keep],
            "tint": self.tint[keep],
        }


def no_traffic(n_frames: int) -> Traffic:
    return Traffic(
        [],
        np.zeros((0, n_frames, 3)),
        np.zeros((0, 3)),
        np.zeros((0, 3)),
        np.zeros(0, dtype=np.int64),
        np.zeros(0, dtype=np.int64),
        np.zeros((0, 3), dtype=np.float32),
    )


# ------------------------------------------------------------------------------------------ shapes
def car_parts(rng, length: float) -> list[tuple[tuple, tuple, float]]:
    """A car as the parked ones are built: a body and a cabin; ``(lo, hi, shade)`` in the car's frame."""
    h = length / 2
    cab = rng.uniform(0.2, 0.6)
    top = rng.uniform(1.4, 1.55)
    return [
        ((-h, -0.9, 0.3), (h, 0.9, 1.05), 1.0),
        ((-h + cab + 0.6, -0.78, 1.05), (h - cab - 0.5, 0.78, top), 0.6),
    ]


def pedestrian_parts(rng) -> list[tuple[tuple, tuple, int]]:
    """Legs, torso and head; ``(lo, hi, part)`` with part 0 trousers, 1 coat, 2 head."""
    height = rng.uniform(1.55, 1.9)
    hip, shoulder = 0.5 * height, 0.84 * height
    return [
        ((-0.12, -0.18, 0.0), (0.12, 0.18, hip), 0),
        ((-0.14, -0.24, hip), (0.14, 0.24, shoulder), 1),
        ((-0.1, -0.09, shoulder + 0.02), (0.1, 0.09, height), 2),
    ]


# ------------------------------------------------------------------------------------------ tracks
def _along(path: np.ndarray, s_path: np.ndarray, heading: np.ndarray, s: np.ndarray) -> np.ndarray:
    """``[F, 3]`` x, y, yaw at arc lengths ``s`` along a polyline, extended straight past its ends."""
    s = np.asarray(s, dtype=np.float64)
    x, y = np.interp(s, s_path, path[:, 0]), np.interp(s, s_path, path[:, 1])
    yaw = np.interp(s, s_path, heading)
    for end, beyond in ((0, s < s_path[0]), (-1, s > s_path[-1])):
        over = s[beyond] - s_path[end]
        x[beyond] += over * math.cos(heading[end])
        y[beyond] += over * math.sin(heading[end])
    return np.stack((x, y, yaw), -1)


def _polyline(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A path's arc length and unwrapped heading at each of its points."""
    step = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate(([0.0], np.cumsum(step)))
    return points, s, path_heading(points)


def _legs(route: np.ndarray, pitch: float) -> set[tuple[int, int]]:
    """The street lines the route drives along: (axis, index), axis 0 for y = index * pitch."""
    lines = set()
    for a, b in zip(route[:-1], route[1:], strict=True):
        if abs(a[1] - b[1]) < 1e-6:  # along x
            lines.add((0, round(a[1] / pitch)))
        else:
            lines.add((1, round(a[0] / pitch)))
    return lines


def _wait_for(obstacles: np.ndarray, start: np.ndarray, step: np.ndarray, n: int, reach: float, ahead: int):
    """``[n, 2]`` positions of an agent that moves ``step`` per frame from ``start`` but holds while its
    next position lies within ``reach`` of an obstacle's position (``obstacles [O, F, 2]``) in the next
    ``ahead`` frames; it never holds where it already is within reach (it clears the way instead)."""
    out = np.empty((n, 2))
    pos = np.asarray(start, dtype=np.float64).copy()
    for k in range(n):
        out[k] = pos
        nxt = pos + step
        window = obstacles[:, k + 1 : k + 1 + ahead].reshape(-1, 2)
        if window.size:
            near_next = np.linalg.norm(window - nxt, axis=1).min() < reach
            near_now = np.linalg.norm(window - pos, axis=1).min() < reach
            if near_next and not near_now:
                continue
        pos = nxt
    return out


def make_traffic(world: World, drive: Drive, density: float, seed: int) -> Traffic:
    """The agents a drive meets at ``density`` (0: none; 1: a busy city street). Deterministic per seed."""
    n_frames = len(drive.s)
    DENSITY.check("traffic density", density)
    if density == 0:
        return no_traffic(n_frames)
    rng = np.random.default_rng([seed, 45])
    kinds, tracks, parts = [], [], []

    def add(kind: str, track: np.ndarray, shapes) -> None:
        kinds.append(kind)
        tracks.append(track)
        parts.append(shapes)

    def car(colour_rng) -> tuple[float, list]:
        length = colour_rng.uniform(3.8, 4.8)
        tint = _tint(colour_rng, CAR_COLOURS[colour_rng.integers(len(CAR_COLOURS))], 0.08)
        return length, [(lo, hi, CAR, tint * shade) for lo, hi, shade in car_parts(colour_rng, length)]

    # with the ego, in its lane
    if rng.random() < min(1.0, density):
        length, shapes = car(rng)
        gap = rng.uniform(7.0, 16.0) + length / 2  # the ego's front is 1.65 m ahead of its origin
        add("lead", _along(drive.lane, drive.s_lane, drive.heading, drive.s + gap), shapes)
    if rng.random() < min(1.0, 0.6 * density):
        length, shapes = car(rng)
        gap = rng.uniform(6.0, 12.0) + length / 2 + 3.4  # its back is 3.4 m behind
        add("follower", _along(drive.lane, drive.s_lane, drive.heading, drive.s - gap), shapes)
    # oncoming, in the route's other lane
    other, s_other, heading_other = _polyline(drive.centre - drive.lane_offset * rightward(drive.centre))
    length_route = float(s_other[-1])
    for _ in range(int(rng.poisson(density * length_route / 25.0))):
        length, shapes = car(rng)
        s0, v = rng.uniform(0.0, length_route + 60.0), rng.uniform(0.5, 1.3)
        track = _along(other, s_other, heading_other, s0 - v * np.arange(n_frames))
        track[:, 2] += math.pi
        add("oncoming", track, shapes)
    # the route's cars are obstacles for those that cross it
    ego_xy = drive.poses[:, :2, 3]
    obstacles = np.stack([ego_xy, *(t[:, :2] for t in tracks)])
    driven = _legs(drive.route, world.pitch)
    extent = world.extent
    for axis in (0, 1):
        for index in range(world.n_blocks + 1):
            line = index * world.pitch
            for _ in range(int(rng.poisson(density * 3.0)) if (axis, index) not in driven else 0):
                length, shapes = car(rng)
                direction = 1.0 if rng.random() < 0.5 else -1.0
                v = rng.uniform(0.4, 1.3)
                along, lateral = rng.uniform(0.0, extent), -direction * 1.75  # keep right
                track = _straight(axis, line, along, lateral, direction, v, n_frames, obstacles, 9.0, 15)
                add("crossing", track, shapes)
    for axis in (0, 1):
        for index in range(world.n_blocks + 1):
            line = index * world.pitch
            for _ in range(int(rng.poisson(density * 2.0))):
                person = pedestrian_parts(rng)
                colours = (
                    _tint(rng, CLOTHES[rng.integers(len(CLOTHES))], 0.05),
                    _tint(rng, CLOTHES[rng.integers(len(CLOTHES))], 0.05),
                    _tint(rng, [0.72, 0.55, 0.45], 0.1),
                )
                shapes = [(lo, hi, FABRIC, colours[part]) for lo, hi, part in person]
                direction = 1.0 if rng.random() < 0.5 else -1.0
                side = 1.0 if rng.random() < 0.5 else -1.0
                lateral = side * (world.half_road + rng.uniform(2.2, 2.6))  # clear of poles and trunks
                along, v = rng.uniform(0.0, extent), rng.uniform(0.08, 0.16)
                track = _straight(axis, line, along, lateral, direction, v, n_frames, obstacles, 6.0, 40)
                add("pedestrian", track, shapes)
    if not kinds:
        return no_traffic(n_frames)
    lo, hi, owner, material, tint = [], [], [], [], []
    for a, shapes in enumerate(parts):
        for p_lo, p_hi, mat, colour in shapes:
            lo.append(p_lo)
            hi.append(p_hi)
            owner.append(a)
            material.append(mat)
            tint.append(colour)
    return Traffic(
        kinds,
        np.stack(tracks),
        np.asarray(lo, dtype=np.float64),
        np.asarray(hi, dtype=np.float64),
        np.asarray(owner, dtype=np.int64),
        np.asarray(material, dtype=np.int64),
        np.clip(np.asarray(tint, dtype=np.float32), 0.0, 1.0),
    )


def _straight(axis, line, along, lateral, direction, v, n_frames, obstacles, reach, ahead) -> np.ndarray:
    """``[F, 3]`` track along a street line (axis 0: y = line, driving along x), ``lateral`` metres
    to the side of its centreline, waiting for the obstacles (see :func:`_wait_for`)."""
    if axis == 0:
        start, step, yaw = (along, line + lateral), (direction * v, 0.0), 0.0 if direction > 0 else math.pi
    else:
        start, step = (line - lateral, along), (0.0, direction * v)
        yaw = math.pi / 2 if direction > 0 else -math.pi / 2
    xy = _wait_for(obstacles, np.array(start), np.array(step), n_frames, reach, ahead)
    return np.concatenate((xy, np.full((n_frames, 1), yaw)), 1)
