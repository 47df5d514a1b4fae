"""A procedural street world in metres, and a vehicle trajectory through it.

World frame: x east, y north, z up; the ground is the plane z = 0. Streets form a Manhattan grid:
centrelines at x = i * pitch and y = j * pitch. Each street has a two-lane carriageway (half width
``half_road``) with parking strips at its edges, raised sidewalks (kerbs 0.12 m), poles and trees;
blocks hold buildings or parks with low walls and trees; cars are parked along the kerbs.

Every object is an axis-aligned box, a vertical cylinder or a sphere, with a material and a tint.
Everything is drawn from ``numpy.random.default_rng(seed)``: the same seed gives the same world.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

# materials (the street's ten, then the indoor scene's; GROUND is the indoor floor too)
SKY, GROUND, SIDEWALK, FACADE, CAR, CONCRETE, POLE, BARK, FOLIAGE, EGO = range(10)
WALL, CEILING, WOOD, FABRIC, WINDOW, DOOR, LAMP = range(10, 17)
MATERIAL_NAMES = (
    "sky",
    "ground",
    "sidewalk",
    "facade",
    "car",
    "concrete",
    "pole",
    "bark",
    "foliage",
    "ego",
    "wall",
    "ceiling",
    "wood",
    "fabric",
    "window",
    "door",
    "lamp",
)
EMISSIVE = (WINDOW, LAMP)  # their colour is their albedo, unlit (the outside seen through a window, a lamp)
SCENES = ("street", "indoor")

CAR_COLOURS = ([0.7, 0.1, 0.1], [0.15, 0.2, 0.6], [0.85, 0.85, 0.85], [0.2, 0.2, 0.22], [0.6, 0.6, 0.1])
BODY_HEIGHT = 0.73  # the pose (IMU) frame origin above the ground; KITTI-360's cameras sit ~1.8 m high


@dataclasses.dataclass
class World:
    seed: int
    pitch: float
    half_road: float
    sidewalk: float
    n_blocks: int
    boxes: np.ndarray  # [N, 6] lo xyz, hi xyz
    box_material: np.ndarray  # [N] int
    box_tint: np.ndarray  # [N, 3]
    cylinders: np.ndarray  # [N, 5] cx, cy, radius, z0, z1
    cylinder_material: np.ndarray
    cylinder_tint: np.ndarray
    spheres: np.ndarray  # [N, 4] cx, cy, cz, radius
    sphere_material: np.ndarray
    sphere_tint: np.ndarray
    sun: np.ndarray  # [3] unit vector towards the sun
    # the indoor scene (fisheyedepth.synthetic.indoor); a street world keeps these defaults
    scene: str = "street"
    room: np.ndarray | None = None  # [6] the room's interior: lo xyz, hi xyz (the floor is z = 0)
    walkway: np.ndarray | None = None  # [5] x0, y0, x1, y1, corner radius of the loop the camera walks
    style: dict | None = None  # floor, wall paint and interior lighting parameters (see indoor.py)

    @property
    def extent(self) -> float:
        return self.n_blocks * self.pitch


class _Builder:
    def __init__(self):
        self.boxes, self.cyl, self.sph = [], [], []

    def box(self, lo, hi, material, tint):
        self.boxes.append((*lo, *hi, material, *tint))

    def cylinder(self, cx, cy, r, z0, z1, material, tint):
        self.cyl.append((cx, cy, r, z0, z1, material, *tint))

    def sphere(self, c, r, material, tint):
        self.sph.append((*c, r, material, *tint))

    @staticmethod
    def _split(rows, n_geom):
        a = np.asarray(rows, dtype=np.float64).reshape(-1, n_geom + 4)
        return a[:, :n_geom].copy(), a[:, n_geom].astype(np.int64), a[:, n_geom + 1 :].astype(np.float32)


def _tint(rng, base, spread):
    return np.clip(np.asarray(base) + rng.uniform(-spread, spread, 3), 0.05, 1.0)


def make_world(seed: int, n_blocks: int = 7) -> World:
    """A city of ``n_blocks x n_blocks`` blocks between ``n_blocks + 1`` streets in each direction."""
    rng = np.random.default_rng(seed)
    pitch = float(rng.uniform(38.0, 48.0))
    hr, sw, kerb = 5.5, 3.0, 0.12
    b = _Builder()
    facade_colours = (
        [0.55, 0.32, 0.25],
        [0.75, 0.7, 0.6],
        [0.6, 0.55, 0.5],
        [0.45, 0.4, 0.38],
        [0.7, 0.5, 0.35],
    )

    for i in range(n_blocks + 1):
        for j in range(n_blocks):
            for axis in (0, 1):  # street along x (axis 0) at y = i * pitch, or along y at x = i * pitch
                # the street segment between two intersections
                c = i * pitch
                s0, s1 = j * pitch + hr + sw, (j + 1) * pitch - hr - sw
                for side in (-1, 1):
                    # sidewalk slab: kerb face + walking surface
                    # (in pieces of at most 8 m, so that bounding spheres stay tight for the ray caster)
                    lat0, lat1 = sorted((c + side * hr, c + side * (hr + sw)))
                    tint = _tint(rng, [0.62, 0.6, 0.57], 0.04)
                    cuts = np.linspace(s0 - sw, s1 + sw, int(np.ceil((s1 - s0 + 2 * sw) / 8.0)) + 1)
                    for a0, a1 in zip(cuts[:-1], cuts[1:], strict=True):
                        lo, hi = _oriented(axis, a0, a1, lat0, lat1, 0.0, kerb)
                        b.box(lo, hi, SIDEWALK, tint)
                    # parked cars in the parking strip
                    s = s0 + rng.uniform(0.5, 4.0)
                    while s + 4.4 < s1:
                        length = rng.uniform(3.8, 4.8)
                        if rng.random() < 0.55:
                            mid = c + side * rng.uniform(4.3, 4.6)
                            tint = _tint(rng, CAR_COLOURS[rng.integers(len(CAR_COLOURS))], 0.08)
                            lo, hi = _oriented(axis, s, s + length, mid - 0.9, mid + 0.9, 0.3, 1.05)
                            b.box(lo, hi, CAR, tint)
                            cab = rng.uniform(0.2, 0.6)
                            lo, hi = _oriented(
                                axis,
                                s + cab + 0.5,
                                s + length - cab - 0.6,
                                mid - 0.78,
                                mid + 0.78,
                                1.05,
                                rng.uniform(1.4, 1.55),
                            )
                            b.box(lo, hi, CAR, tint * 0.6)
                        s += length + rng.uniform(1.0, 5.0)
                    # poles and trees on the sidewalk
                    s = s0 + rng.uniform(1.0, 8.0)
                    while s < s1:
                        lat = c + side * (hr + 0.6)
                        x, y = (s, lat) if axis == 0 else (lat, s)
                        if rng.random() < 0.5:
                            b.cylinder(
                                x,
                                y,
                                rng.uniform(0.08, 0.14),
                                kerb,
                                rng.uniform(4.5, 7.5),
                                POLE,
                                _tint(rng, [0.5, 0.52, 0.55], 0.05),
                            )
                        else:
                            lat = c + side * (hr + 1.6)
                            x, y = (s, lat) if axis == 0 else (lat, s)
                            _tree(b, rng, x, y, kerb)
                        s += rng.uniform(7.0, 14.0)

    for i in range(n_blocks):
        for j in range(n_blocks):
            x0, x1 = i * pitch + hr + sw, (i + 1) * pitch - hr - sw
            y0, y1 = j * pitch + hr + sw, (j + 1) * pitch - hr - sw
            if rng.random() < 0.78:
                _buildings(b, rng, x0, x1, y0, y1, facade_colours)
            else:
                _park(b, rng, x0, x1, y0, y1)

    boxes, box_m, box_t = _Builder._split(b.boxes, 6)
    cyl, cyl_m, cyl_t = _Builder._split(b.cyl, 5)
    sph, sph_m, sph_t = _Builder._split(b.sph, 4)
    elevation, azimuth = math.radians(rng.uniform(35, 60)), rng.uniform(0, 2 * math.pi)
    sun = np.array(
        [
            math.cos(elevation) * math.cos(azimuth),
            math.cos(elevation) * math.sin(azimuth),
            math.sin(elevation),
        ]
    )
    return World(
        seed, pitch, hr, sw, n_blocks, boxes, box_m, box_t, cyl, cyl_m, cyl_t, sph, sph_m, sph_t, sun
    )


def _oriented(axis, s0, s1, l0, l1, z0, z1):
    """Box bounds for a street-aligned box: along-street [s0, s1], across [l0, l1], height [z0, z1]."""
    if axis == 0:
        return (s0, l0, z0), (s1, l1, z1)
    return (l0, s0, z0), (l1, s1, z1)


def _tree(b, rng, x, y, z0):
    trunk = rng.uniform(2.0, 3.2)
    b.cylinder(
        x, y, rng.uniform(0.15, 0.25), z0, z0 + trunk + 0.5, BARK, _tint(rng, [0.35, 0.25, 0.17], 0.04)
    )
    r = rng.uniform(1.3, 2.4)
    b.sphere((x, y, z0 + trunk + r * 0.8), r, FOLIAGE, _tint(rng, [0.22, 0.45, 0.15], 0.06))


def _buildings(b, rng, x0, x1, y0, y1, colours):
    nx, ny = int(rng.integers(1, 4)), int(rng.integers(1, 4))
    xs, ys = np.linspace(x0, x1, nx + 1), np.linspace(y0, y1, ny + 1)
    for a in range(nx):
        for c in range(ny):
            if rng.random() < 0.1:
                continue
            lo = (xs[a] + rng.uniform(0.0, 2.0), ys[c] + rng.uniform(0.0, 2.0), 0.0)
            hi = (
                xs[a + 1] - rng.uniform(0.0, 2.0),
                ys[c + 1] - rng.uniform(0.0, 2.0),
                rng.uniform(6.0, 24.0),
            )
            b.box(lo, hi, FACADE, _tint(rng, colours[rng.integers(len(colours))], 0.06))


def _park(b, rng, x0, x1, y0, y1):
    h, t = rng.uniform(0.8, 1.3), 0.3
    tint = _tint(rng, [0.6, 0.58, 0.55], 0.05)
    for lo, hi in (
        ((x0, y0, 0), (x1, y0 + t, h)),
        ((x0, y1 - t, 0), (x1, y1, h)),
        ((x0, y0, 0), (x0 + t, y1, h)),
        ((x1 - t, y0, 0), (x1, y1, h)),
    ):
        b.box(lo, hi, CONCRETE, tint)
    for _ in range(int(rng.integers(5, 12))):
        _tree(b, rng, rng.uniform(x0 + 2, x1 - 2), rng.uniform(y0 + 2, y1 - 2), 0.0)


# ------------------------------------------------------------------------------------------ trajectory
def _route(world: World, rng, length: float) -> np.ndarray:
    """Grid nodes of a random drive (no U-turns, inside the city), long enough for ``length`` metres."""
    n = world.n_blocks
    node = np.array([1, int(rng.integers(1, n))])
    heading = np.array([1, 0])
    nodes = [node.copy()]
    travelled = 0.0
    while travelled < length + 2 * world.pitch:
        options = []
        for d in (heading, np.array([-heading[1], heading[0]]), np.array([heading[1], -heading[0]])):
            nxt = node + d
            if 1 <= nxt[0] <= n - 1 and 1 <= nxt[1] <= n - 1:
                options.append(d)
        weights = np.array([3.0 if np.array_equal(d, heading) else 1.0 for d in options])
        heading = options[rng.choice(len(options), p=weights / weights.sum())]
        node = node + heading
        nodes.append(node.copy())
        travelled += world.pitch
    return np.array(nodes, dtype=np.float64) * world.pitch


def _fillet_path(points: np.ndarray, radius: float, step: float = 0.05) -> np.ndarray:
    """A smooth polyline through ``points``: straight legs joined by circular arcs of ``radius``."""
    out = [points[0]]
    for k in range(1, len(points) - 1):
        a, p, c = points[k - 1], points[k], points[k + 1]
        d_in, d_out = (p - a) / np.linalg.norm(p - a), (c - p) / np.linalg.norm(c - p)
        cross = d_in[0] * d_out[1] - d_in[1] * d_out[0]
        if abs(cross) < 1e-9:
            out.append(p)
            continue
        t0, t1 = p - d_in * radius, p + d_out * radius
        centre = t0 + radius * np.sign(cross) * np.array([-d_in[1], d_in[0]])
        a0 = math.atan2(t0[1] - centre[1], t0[0] - centre[0])
        a1 = math.atan2(t1[1] - centre[1], t1[0] - centre[0])
        sweep = (a1 - a0 + math.pi) % (2 * math.pi) - math.pi
        for u in np.linspace(0, 1, max(3, int(abs(sweep) * radius / step))):
            ang = a0 + u * sweep
            out.append(centre + radius * np.array([math.cos(ang), math.sin(ang)]))
    out.append(points[-1])
    return np.array(out)


def _resample(poly: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    keep = np.concatenate(([True], seg > 1e-9))
    poly = poly[keep]
    s = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))))
    grid = np.arange(0.0, s[-1], step)
    return np.stack([np.interp(grid, s, poly[:, 0]), np.interp(grid, s, poly[:, 1])], 1), grid


def rightward(path: np.ndarray) -> np.ndarray:
    """``[N, 2]`` unit vectors to the right of a polyline's direction at each of its points."""
    tangent = np.gradient(path, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    return np.stack([tangent[:, 1], -tangent[:, 0]], 1)


def path_heading(path: np.ndarray) -> np.ndarray:
    """``[N]`` the unwrapped yaw (radians) of a polyline's direction at each of its points."""
    return np.unwrap(np.arctan2(*np.gradient(path, axis=0).T[::-1]))


def body_rotation(yaw: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """Body (x forward, y right, z down, as KITTI-360's pose frame) to world (z up)."""
    cy, sy = math.cos(yaw), math.sin(yaw)
    R = np.array([[cy, sy, 0.0], [sy, -cy, 0.0], [0.0, 0.0, -1.0]])  # columns: body x, y, z in the world
    cp, sp, cr, sr = math.cos(pitch), math.sin(pitch), math.cos(roll), math.sin(roll)
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return R @ Ry @ Rx


def wobbling_speed(n_frames: int, mean: float, slow, fast, phases) -> np.ndarray:
    """Metres per frame ``mean + a1 sin(2 pi k / T1 + phases[0]) + a2 sin(2 pi k / T2 + phases[1])``
    for frames ``k``, with ``slow = (a1, T1)`` and ``fast = (a2, T2)``: a speed that varies smoothly."""
    k = np.arange(n_frames)
    return (
        mean
        + slow[0] * np.sin(2 * math.pi * k / slow[1] + phases[0])
        + fast[0] * np.sin(2 * math.pi * k / fast[1] + phases[1])
    )


@dataclasses.dataclass
class Drive:
    """A drive through the street world: the body poses and the paths they follow (what traffic needs)."""

    poses: np.ndarray  # [F, 4, 4] body-to-world
    s: np.ndarray  # [F] arc length along ``lane`` of each frame (metres)
    route: np.ndarray  # [N, 2] the grid nodes driven through (metres)
    centre: np.ndarray  # [M, 2] the street centreline, filleted, every 5 cm
    lane: np.ndarray  # [L, 2] the driven lane, every 5 cm
    s_lane: np.ndarray  # [L] arc length of each lane point
    heading: np.ndarray  # [L] unwrapped yaw of the lane (radians)
    lane_offset: float  # metres right of the centreline


def make_trajectory(world: World, n_frames: int, seed: int, lane_offset: float = 1.75) -> np.ndarray:
    """``[n_frames, 4, 4]`` body-to-world poses of a car driving ``lane_offset`` metres to the right of
    the street's centreline (1.75: the right lane; negative: the left lane), with turns.

    Speeds vary smoothly between 0.3 and 1.5 m per frame and drop in turns; pitch and roll wobble by a
    few tenths of a degree.
    """
    return make_drive(world, n_frames, seed, lane_offset).poses


def make_drive(world: World, n_frames: int, seed: int, lane_offset: float = 1.75) -> Drive:
    """:func:`make_trajectory`'s poses with the paths behind them."""
    rng = np.random.default_rng([seed, 7])
    phases = rng.uniform(0, 2 * math.pi, 4)
    speed = wobbling_speed(n_frames, 0.9, (0.35, 90), (0.15, 31), phases)
    route = _route(world, rng, float(speed.sum()) * 1.2 + 20.0)
    centre = _fillet_path(route, radius=8.0)
    centre, _ = _resample(centre, 0.05)
    lane, s_lane = _resample(centre + lane_offset * rightward(centre), 0.05)
    heading = path_heading(lane)
    curvature = np.abs(np.gradient(heading)) / 0.05
    s = np.empty(n_frames)
    s[0] = 10.0
    for i in range(1, n_frames):
        bend = np.interp(s[i - 1], s_lane, curvature)
        s[i] = s[i - 1] + float(np.clip(speed[i] * (1.0 - min(0.5, 4.0 * bend)), 0.3, 1.5))
    if s[-1] > s_lane[-1]:
        raise RuntimeError(
            "the route is too short for the requested frames"
        )  # cannot happen: route has slack
    x, y = np.interp(s, s_lane, lane[:, 0]), np.interp(s, s_lane, lane[:, 1])
    yaw = np.interp(s, s_lane, heading)
    poses = np.zeros((n_frames, 4, 4))
    for i in range(n_frames):
        pitch = math.radians(0.3) * math.sin(0.21 * i + phases[2])
        roll = math.radians(0.3) * math.sin(0.17 * i + phases[3])
        poses[i, :3, :3] = body_rotation(yaw[i], pitch, roll)
        poses[i, :3, 3] = (x[i], y[i], BODY_HEIGHT)
        poses[i, 3, 3] = 1.0
    return Drive(poses, s, route, centre, lane, s_lane, heading, lane_offset)
