"""An indoor world: a furnished room with doors and windows, and a handheld camera walking through it.

World frame as the street's: x east, y north, z up. The floor is the ray caster's ground plane z = 0;
the room's interior spans ``[0, width] x [0, depth] x [0, height]``. Walls and the ceiling are thin boxes
around it. A door is a recess in its wall with the door leaf at the back; a window is a recess whose back
is a bright "outside" panel (emissive), with a sill and a mullion. Furniture stands against the walls
(shelves with books, cabinets, sofas, beds, desks, floor lamps, plants); a table and a rug may stand in
the middle, and a lamp hangs from the ceiling. Every object is an axis-aligned box, a vertical cylinder
or a sphere, as in the street world, so the ray caster gives the exact distance of every pixel.

The camera walks a smooth loop (a rounded rectangle, ``World.walkway``) between the furniture along the
walls and the middle, with a slow sideways sway, looking around as it goes; the loop keeps
``MIN_CLEARANCE`` metres from every surface, checked numerically (:func:`clearance`). Interior lighting
(``World.style``): ambient, a directional term and a ceiling point light, all randomised per seed.

Everything is drawn from ``numpy.random.default_rng([seed, 101])``: the same seed gives the same room.
"""

from __future__ import annotations

import math

import numpy as np

from . import world as W
from .world import _Builder, _resample, _tint, body_rotation

# The body (the walking camera's reference point) keeps this far from every surface; the cameras sit at
# most RIG_RADIUS from it (indoor rigs are compact), so every camera keeps MIN_CLEARANCE - RIG_RADIUS.
MIN_CLEARANCE = 0.45
RIG_RADIUS = 0.15
SWAY = 0.1  # metres the walk sways to either side of the loop
HEIGHTS = (0.9, 1.6)  # the body's height above the floor: a robot (low) to a hand-held camera (high)
TURN = math.radians(8)  # the walk turns the corners of its loop by at most this much per frame
_GAP = 0.65  # how far the loop keeps from the furniture it passes: MIN_CLEARANCE + SWAY + a margin


def _wall_box(wall: int, s0, s1, d0, d1, z0, z1, room):
    """A box in a wall's frame: ``s`` along the wall, ``d`` from its inner face into the room (negative:
    into the wall), ``z`` up. Walls: 0 south (y = 0), 1 north (y = depth), 2 west (x = 0), 3 east."""
    width, depth = room
    if wall == 0:
        return (s0, d0, z0), (s1, d1, z1)
    if wall == 1:
        return (s0, depth - d1, z0), (s1, depth - d0, z1)
    if wall == 2:
        return (d0, s0, z0), (d1, s1, z1)
    return (width - d1, s0, z0), (width - d0, s1, z1)


def _wall_point(wall: int, s, d, room):
    (x0, y0, _), (x1, y1, _) = _wall_box(wall, s, s, d, d, 0, 0, room)
    return 0.5 * (x0 + x1), 0.5 * (y0 + y1)


def _free(intervals, a, b, gap=0.0) -> bool:
    return all(b + gap <= lo or a - gap >= hi for lo, hi in intervals)


class _Item:
    """One piece of furniture: its primitives (in the builder's row format) and its floor footprint."""

    def __init__(self, wall: int | None, depth: float, footprint: tuple, height: float):
        self.wall, self.depth, self.footprint, self.height = wall, depth, footprint, height
        self.boxes, self.cylinders, self.spheres = [], [], []

    def box(self, lo, hi, material, tint):
        self.boxes.append((lo, hi, material, tint))


def _furniture(rng, kind: str, wall: int, s0: float, width: float, room, tints) -> _Item:
    """A piece of furniture of ``kind`` against ``wall``, spanning ``[s0, s0 + width]`` along it."""
    s1, d0 = s0 + width, 0.02

    def box(item, a0, a1, e0, e1, z0, z1, material, tint):
        item.box(*_wall_box(wall, a0, a1, e0, e1, z0, z1, room), material, tint)

    wood = _tint(rng, tints["wood"], 0.05)
    if kind == "shelf":
        depth, height = rng.uniform(0.3, 0.42), rng.uniform(1.6, 2.1)
        item = _Item(wall, d0 + depth, (), height)
        box(item, s0, s1, d0, d0 + 0.02, 0.0, height, W.WOOD, wood)  # back
        for a in (s0, s1 - 0.025):
            box(item, a, a + 0.025, d0, d0 + depth, 0.0, height, W.WOOD, wood)  # sides
        levels = np.arange(0.05, height - 0.1, rng.uniform(0.32, 0.4))
        for z in [*levels, height - 0.025]:
            box(item, s0, s1, d0, d0 + depth, z, z + 0.025, W.WOOD, wood)
        for z, z_next in zip(levels[:-1], levels[1:], strict=True):  # books
            a = s0 + 0.03
            while True:
                w = rng.uniform(0.03, 0.09) if rng.random() < 0.8 else rng.uniform(0.15, 0.3)
                if a + w > s1 - 0.03:
                    break
                if rng.random() < 0.8:
                    h = min(rng.uniform(0.15, 0.3), z_next - z - 0.04)
                    colour = _tint(rng, [0.45, 0.35, 0.3], 0.3)
                    box(
                        item,
                        a,
                        a + w,
                        d0 + 0.03,
                        d0 + rng.uniform(0.16, depth),
                        z + 0.025,
                        z + h,
                        W.FABRIC,
                        colour,
                    )
                a += w + rng.uniform(0.0, 0.02)
    elif kind == "cabinet":
        depth, height = rng.uniform(0.4, 0.55), rng.uniform(0.7, 0.95)
        item = _Item(wall, d0 + depth + 0.02, (), height)
        box(item, s0 + 0.02, s1 - 0.02, d0, d0 + depth, 0.0, height - 0.03, W.WOOD, wood)
        box(item, s0, s1, d0, d0 + depth + 0.02, height - 0.03, height, W.WOOD, wood * 0.8)
    elif kind == "sofa":
        depth, back = rng.uniform(0.8, 0.95), rng.uniform(0.75, 0.85)
        fabric = _tint(rng, tints["fabric"], 0.08)
        item = _Item(wall, d0 + depth, (), back)
        box(item, s0, s1, d0, d0 + depth, 0.0, 0.42, W.FABRIC, fabric)  # seat
        box(item, s0, s1, d0, d0 + 0.22, 0.42, back, W.FABRIC, fabric * 0.9)  # back
        for a in (s0, s1 - 0.18):
            box(item, a, a + 0.18, d0, d0 + depth, 0.42, 0.62, W.FABRIC, fabric * 0.95)  # arms
    elif kind == "bed":
        depth, head = rng.uniform(0.9, 1.5), rng.uniform(0.9, 1.1)
        item = _Item(wall, d0 + depth, (), head)
        end = s0 if rng.random() < 0.5 else s1 - 0.06
        box(item, end, end + 0.06, d0, d0 + depth, 0.0, head, W.WOOD, wood)  # headboard
        b0, b1 = (s0 + 0.06, s1) if end == s0 else (s0, s1 - 0.06)
        box(item, b0, b1, d0, d0 + depth, 0.0, 0.3, W.WOOD, wood * 0.85)
        box(
            item, b0, b1, d0 + 0.02, d0 + depth - 0.02, 0.3, 0.5, W.FABRIC, _tint(rng, [0.85, 0.85, 0.8], 0.1)
        )
        p0 = b0 + 0.05 if end == s0 else b1 - 0.45
        box(
            item,
            p0,
            p0 + 0.4,
            d0 + 0.1,
            d0 + depth - 0.1,
            0.5,
            0.62,
            W.FABRIC,
            _tint(rng, [0.9, 0.9, 0.9], 0.05),
        )
    elif kind == "desk":
        depth, height = rng.uniform(0.55, 0.7), rng.uniform(0.72, 0.76)
        item = _Item(wall, d0 + depth, (), height)
        box(item, s0, s1, d0, d0 + depth, height - 0.035, height, W.WOOD, wood)
        for a in (s0 + 0.03, s1 - 0.08):
            for e in (d0 + 0.03, d0 + depth - 0.08):
                box(item, a, a + 0.05, e, e + 0.05, 0.0, height - 0.035, W.WOOD, wood * 0.8)
    elif kind == "lamp":
        r, height = rng.uniform(0.16, 0.22), rng.uniform(1.45, 1.75)
        item = _Item(wall, d0 + 2 * r, (), height)
        cx, cy = _wall_point(wall, s0 + width / 2, d0 + r, room)
        metal = _tint(rng, [0.3, 0.3, 0.32], 0.05)
        item.cylinders += [
            (cx, cy, 0.14, 0.0, 0.03, W.POLE, metal),
            (cx, cy, 0.015, 0.03, height - 0.3, W.POLE, metal),
            (cx, cy, r, height - 0.3, height, W.LAMP, np.array([1.0, 0.93, 0.78])),
        ]
    else:  # plant
        pot, leaves = rng.uniform(0.14, 0.22), rng.uniform(0.3, 0.42)
        z_pot = rng.uniform(0.3, 0.45)
        item = _Item(wall, d0 + 2 * leaves, (), z_pot + 0.2 + 2 * leaves)
        cx, cy = _wall_point(wall, s0 + width / 2, d0 + leaves, room)
        item.cylinders.append((cx, cy, pot, 0.0, z_pot, W.CONCRETE, _tint(rng, [0.65, 0.4, 0.3], 0.08)))
        item.spheres.append(
            ((cx, cy, z_pot + 0.2 + leaves), leaves, W.FOLIAGE, _tint(rng, [0.22, 0.45, 0.15], 0.06))
        )
    lo, hi = _wall_box(wall, s0, s1, d0, item.depth, 0.0, item.height, room)
    item.footprint = (lo[0], lo[1], hi[0], hi[1])
    return item


# kind: (weight, width along the wall (for a lamp or a plant: its footprint), tall: blocks a window)
_KINDS = {
    "shelf": (3, (0.8, 1.6), True),
    "cabinet": (2, (0.6, 1.2), False),
    "sofa": (2, (1.6, 2.2), False),
    "bed": (1, (1.9, 2.1), False),
    "desk": (2, (1.0, 1.5), False),
    "lamp": (1, (0.44, 0.44), True),
    "plant": (1, (0.84, 0.84), True),
}


def make_indoor_world(seed: int) -> W.World:
    """A furnished room (see the module docstring); the same seed gives the same room."""
    rng = np.random.default_rng([seed, 101])
    width, depth, height = rng.uniform(4.5, 6.5), rng.uniform(4.5, 6.5), rng.uniform(2.5, 2.95)
    t = rng.uniform(0.12, 0.2)  # wall thickness: the depth of door and window recesses
    room = (width, depth)
    lengths = (width, width, depth, depth)
    tints = {
        "wall": _tint(rng, [[0.85, 0.83, 0.78], [0.75, 0.8, 0.82], [0.85, 0.78, 0.7]][rng.integers(3)], 0.05),
        "wood": [[0.55, 0.38, 0.22], [0.72, 0.58, 0.4], [0.35, 0.24, 0.16]][rng.integers(3)],
        "fabric": [[0.35, 0.4, 0.55], [0.55, 0.3, 0.25], [0.45, 0.45, 0.4]][rng.integers(3)],
    }

    # doors and windows: openings (s0, s1, z0, z1) per wall
    openings: dict[int, list[tuple[float, float, float, float, str]]] = {w: [] for w in range(4)}
    sill = rng.uniform(0.85, 1.0)
    wanted = ["door"] * (1 + int(rng.random() < 0.35)) + ["window"] * int(rng.integers(1, 4))
    for kind in wanted:
        size = rng.uniform(0.8, 0.9) if kind == "door" else rng.uniform(0.8, 1.6)
        for _ in range(50):
            wall = int(rng.integers(4))
            s0 = rng.uniform(0.3, lengths[wall] - 0.3 - size)
            if _free([(a, b) for a, b, *_ in openings[wall]], s0, s0 + size, 0.4):
                z0, z1 = (
                    (0.0, rng.uniform(2.0, 2.1)) if kind == "door" else (sill, min(height - 0.25, sill + 1.2))
                )
                openings[wall].append((s0, s0 + size, z0, z1, kind))
                break

    # furniture against the walls
    placed: list[_Item] = []
    for _ in range(int(rng.integers(5, 10))):
        names = list(_KINDS)
        weights = np.array([_KINDS[k][0] for k in names], dtype=np.float64)
        kind = names[rng.choice(len(names), p=weights / weights.sum())]
        (lo_w, hi_w), tall = _KINDS[kind][1], _KINDS[kind][2]
        size = rng.uniform(lo_w, hi_w)
        for _ in range(30):
            wall = int(rng.integers(4))
            if size > lengths[wall] - 0.1:
                continue
            s0 = rng.uniform(0.05, lengths[wall] - 0.05 - size)
            blocked = [(a - 0.3, b + 0.3) for a, b, *_, k in openings[wall] if k == "door"]
            item = _furniture(rng, kind, wall, s0, size, room, tints)
            if tall or item.height > sill - 0.02:
                blocked += [(a, b) for a, b, *_, k in openings[wall] if k == "window"]
            x0, y0, x1, y1 = item.footprint
            if _free(blocked, s0, s0 + size) and all(
                x1 + 0.05 <= o[0] or x0 - 0.05 >= o[2] or y1 + 0.05 <= o[1] or y0 - 0.05 >= o[3]
                for o in (p.footprint for p in placed)
            ):
                placed.append(item)
                break

    # the walkway: a loop at least _GAP beyond the furniture along each wall and 1 m from the walls
    while True:
        inset = [max([1.0] + [p.depth + _GAP for p in placed if p.wall == w]) for w in range(4)]
        loop = (inset[2], inset[0], width - inset[3], depth - inset[1])
        short = [(0, 1) if loop[2] - loop[0] < 1.2 else None, (2, 3) if loop[3] - loop[1] < 1.2 else None]
        short = [pair for pair in short if pair]
        if not short:
            break
        # drop the deepest piece on the walls that squeeze the loop
        walls = {2, 3} if short[0] == (0, 1) else {0, 1}
        deepest = max((p for p in placed if p.wall in walls), key=lambda p: p.depth)
        placed.remove(deepest)
    corner = min(0.6, 0.45 * min(loop[2] - loop[0], loop[3] - loop[1]))

    # the middle: a table (if there is room) and a rug; a lamp hangs from the ceiling
    island = (loop[0] + _GAP + 0.3, loop[1] + _GAP + 0.3, loop[2] - _GAP - 0.3, loop[3] - _GAP - 0.3)
    middle = _Item(None, 0.0, (), 0.0)
    wood = _tint(rng, tints["wood"], 0.05)
    if island[2] - island[0] > 0.5 and island[3] - island[1] > 0.5:
        tw = min(rng.uniform(0.6, 1.6), island[2] - island[0])
        td = min(rng.uniform(0.6, 1.0), island[3] - island[1])
        tx, ty = rng.uniform(island[0], island[2] - tw), rng.uniform(island[1], island[3] - td)
        th = rng.uniform(0.4, 0.76)
        middle.box((tx, ty, th - 0.04), (tx + tw, ty + td, th), W.WOOD, wood)
        for lx in (tx + 0.03, tx + tw - 0.08):
            for ly in (ty + 0.03, ty + td - 0.08):
                middle.box((lx, ly, 0.0), (lx + 0.05, ly + 0.05, th - 0.04), W.WOOD, wood * 0.8)
    if rng.random() < 0.7:
        cx, cy = rng.uniform(0.35, 0.65) * width, rng.uniform(0.35, 0.65) * depth
        rw, rd = rng.uniform(1.2, 2.4), rng.uniform(1.0, 1.8)
        rug = _tint(rng, [[0.6, 0.25, 0.2], [0.3, 0.35, 0.5], [0.7, 0.65, 0.55]][rng.integers(3)], 0.06)
        middle.box((cx - rw / 2, cy - rd / 2, 0.0), (cx + rw / 2, cy + rd / 2, 0.012), W.FABRIC, rug)
    light = np.array([rng.uniform(0.35, 0.65) * width, rng.uniform(0.35, 0.65) * depth, height - 0.3])
    middle.cylinders += [
        (light[0], light[1], 0.008, height - 0.2, height, W.POLE, np.array([0.2, 0.2, 0.2])),
        (
            light[0],
            light[1],
            rng.uniform(0.15, 0.25),
            height - 0.38,
            height - 0.2,
            W.LAMP,
            np.array([1.0, 0.95, 0.82]),
        ),
    ]

    b = _Builder()
    wall_tint = tints["wall"]
    for wall in range(4):
        lo_s, hi_s = (-t, lengths[wall] + t) if wall < 2 else (0.0, lengths[wall])
        cuts = sorted({lo_s, hi_s, *(e for a, c, *_ in openings[wall] for e in (a, c))})
        for a, c in zip(cuts[:-1], cuts[1:], strict=True):
            holes = sorted((z0, z1) for s0, s1, z0, z1, _ in openings[wall] if s0 <= a and s1 >= c)
            z = 0.0
            for z0, z1 in [*holes, (height, height)]:
                if z0 > z:
                    b.box(*_wall_box(wall, a, c, -t, 0.0, z, z0, room), W.WALL, wall_tint)
                z = max(z, z1)
        for s0, s1, z0, z1, kind in openings[wall]:
            if kind == "door":
                leaf = _tint(rng, tints["wood"], 0.08)
                b.box(*_wall_box(wall, s0, s1, -t, -t + 0.04, z0, z1, room), W.DOOR, leaf)
            else:
                b.box(*_wall_box(wall, s0, s1, -t - 0.02, -t, z0, z1, room), W.WINDOW, np.ones(3))
                frame = np.array([0.9, 0.9, 0.88])
                b.box(*_wall_box(wall, s0 - 0.05, s1 + 0.05, -t, 0.05, z0 - 0.04, z0, room), W.WOOD, frame)
                m = 0.5 * (s0 + s1)
                b.box(
                    *_wall_box(wall, m - 0.025, m + 0.025, -t + 0.02, -t + 0.07, z0, z1, room), W.WOOD, frame
                )
    b.box(
        (-t, -t, height),
        (width + t, depth + t, height + 0.1),
        W.CEILING,
        _tint(rng, [0.93, 0.93, 0.92], 0.02),
    )
    for item in [*placed, middle]:
        for lo, hi, material, tint in item.boxes:
            b.box(lo, hi, material, tint)
        for cx, cy, r, z0, z1, material, tint in item.cylinders:
            b.cylinder(cx, cy, r, z0, z1, material, tint)
        for c, r, material, tint in item.spheres:
            b.sphere(c, r, material, tint)

    boxes, box_m, box_t = _Builder._split(b.boxes, 6)
    cyl, cyl_m, cyl_t = _Builder._split(b.cyl, 5)
    sph, sph_m, sph_t = _Builder._split(b.sph, 4)
    azimuth, elevation = rng.uniform(0, 2 * math.pi), math.radians(rng.uniform(20, 70))
    style = {
        "floor": "planks" if rng.random() < 0.6 else "tiles",
        "floor_tint": _tint(
            rng, [[0.62, 0.45, 0.3], [0.75, 0.68, 0.55], [0.55, 0.55, 0.55]][rng.integers(3)], 0.05
        ),
        "plank": [float(rng.uniform(1.0, 2.0)), float(rng.uniform(0.12, 0.2))],  # length, width (m)
        "tile": float(rng.uniform(0.3, 0.6)),
        "floor_axis": int(rng.integers(2)),
        "wallpaper": float(rng.uniform(0.05, 0.15)) if rng.random() < 0.35 else 0.0,  # stripe width; 0: paint
        "ambient": float(rng.uniform(0.45, 0.65)),
        "directional": float(rng.uniform(0.15, 0.35)),
        "point": float(rng.uniform(0.3, 0.6)),
        "light_tint": _tint(rng, [1.0, 0.97, 0.92], 0.04),
        "light": light,
    }
    toward = np.array(
        [
            math.cos(elevation) * math.cos(azimuth),
            math.cos(elevation) * math.sin(azimuth),
            math.sin(elevation),
        ]
    )
    world = W.World(
        seed, 0.0, 0.0, 0.0, 0, boxes, box_m, box_t, cyl, cyl_m, cyl_t, sph, sph_m, sph_t, toward,
        scene="indoor",
        room=np.array([0.0, 0.0, 0.0, width, depth, height]),
        walkway=np.array([*loop, corner]),
        style=style,
    )  # fmt: skip
    path, _ = _loop(world)
    for sway in (-SWAY, 0.0, SWAY):
        for z in np.linspace(*HEIGHTS, 8):
            points = np.concatenate([_offset(path, sway), np.full((len(path), 1), z)], 1)
            if clearance(world, points).min() < MIN_CLEARANCE:
                raise RuntimeError(f"indoor world {seed}: the walkway passes too close to an object")
    return world


# ------------------------------------------------------------------------------------------ geometry
def clearance(world: W.World, points: np.ndarray) -> np.ndarray:
    """``[N]`` distance (metres) from each point ``[N, 3]`` to the nearest surface of the world: the floor
    plane, every box, cylinder and sphere (0 inside one)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    best = np.abs(p[:, 2])
    if len(world.boxes):
        lo, hi = world.boxes[None, :, :3], world.boxes[None, :, 3:]
        outside = np.maximum(np.maximum(lo - p[:, None], p[:, None] - hi), 0.0)
        best = np.minimum(best, np.linalg.norm(outside, axis=-1).min(1))
    if len(world.cylinders):
        c = world.cylinders[None]
        radial = np.maximum(np.hypot(p[:, None, 0] - c[..., 0], p[:, None, 1] - c[..., 1]) - c[..., 2], 0.0)
        vertical = np.maximum(np.maximum(c[..., 3] - p[:, None, 2], p[:, None, 2] - c[..., 4]), 0.0)
        best = np.minimum(best, np.hypot(radial, vertical).min(1))
    if len(world.spheres):
        s = world.spheres[None]
        d = np.linalg.norm(p[:, None] - s[..., :3], axis=-1) - s[..., 3]
        best = np.minimum(best, np.maximum(d, 0.0).min(1))
    return best


def _loop(world: W.World, step: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """The walkway's rounded rectangle, counter-clockwise: points ``[N, 2]`` every ``step`` metres and
    their left (inward) unit normals."""
    x0, y0, x1, y1, r = world.walkway
    corners = ((x1 - r, y0 + r, -0.5), (x1 - r, y1 - r, 0.0), (x0 + r, y1 - r, 0.5), (x0 + r, y0 + r, 1.0))
    pts = []
    for cx, cy, start in corners:
        a = np.linspace(start * math.pi, (start + 0.5) * math.pi, 25)
        pts.append(np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], 1))
    poly = np.concatenate([*pts, pts[0][:1]])
    path, _ = _resample(poly, step)
    tangent = np.gradient(np.concatenate([path[-1:], path, path[:1]]), axis=0)[1:-1]
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    return path, np.stack([-tangent[:, 1], tangent[:, 0]], 1)


def _offset(path: np.ndarray, sway: float) -> np.ndarray:
    """Points ``sway`` metres to the left of a closed counter-clockwise path (:func:`_loop`'s normals)."""
    tangent = np.gradient(np.concatenate([path[-1:], path, path[:1]]), axis=0)[1:-1]
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    return path + sway * np.stack([-tangent[:, 1], tangent[:, 0]], 1)


def make_indoor_trajectory(world: W.World, n_frames: int, seed: int) -> np.ndarray:
    """``[n_frames, 4, 4]`` body-to-world poses (body x forward, y right, z down, as the street's) of a
    camera carried around the room's walkway: 0.07-0.17 m per frame (slower in the corners, which it
    turns by at most ``TURN`` per frame), swaying up to ``SWAY`` metres to
    either side, at a height in ``HEIGHTS`` with a slight bob, looking up to 25 degrees to either side of
    the way it walks, with a few degrees of pitch and roll. Every pose keeps ``MIN_CLEARANCE`` metres
    from every surface (checked; a RuntimeError otherwise)."""
    rng = np.random.default_rng([seed, 107])
    path, _ = _loop(world)
    if rng.random() < 0.5:  # clockwise
        path = path[::-1].copy()
    seg = np.linalg.norm(np.diff(np.concatenate([path, path[:1]]), axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    perimeter = arc[-1]
    closed = np.concatenate([path, path[:1]])
    phases = rng.uniform(0, 2 * math.pi, 7)
    k = np.arange(n_frames)
    speed = W.wobbling_speed(n_frames, 0.12, (0.035, 50), (0.015, 17), phases)
    # in the corners it slows down to turn at most TURN radians per frame
    chord = np.roll(path, -1, axis=0) - np.roll(path, 1, axis=0)  # central differences round the loop
    heading_along = np.arctan2(chord[:, 1], chord[:, 0])
    turn = np.angle(np.exp(1j * (np.roll(heading_along, -1) - np.roll(heading_along, 1))))
    curvature = np.abs(turn) / np.maximum(np.linalg.norm(chord, axis=1), 1e-9)
    curvature = np.append(curvature, curvature[0])  # at arc[-1], the loop's start again
    s = np.empty(n_frames)
    s[0] = rng.uniform(0, perimeter)
    for i in range(1, n_frames):
        ahead = np.mod(s[i - 1] + np.linspace(0.0, float(speed[i]), 6), perimeter)
        bend = float(np.interp(ahead, arc, curvature).max())  # the tightest bend of the step
        bend /= max(1.0 - SWAY * bend, 0.2)  # swayed inwards, the corner is tighter
        s[i] = s[i - 1] + min(float(speed[i]), TURN / max(bend, 1e-9))
    wavelength = rng.uniform(3.0, 6.0)

    def position(arc_length):
        a = np.mod(arc_length, perimeter)
        p = np.stack([np.interp(a, arc, closed[:, 0]), np.interp(a, arc, closed[:, 1])], -1)
        ahead = np.mod(arc_length + 0.05, perimeter)
        q = np.stack([np.interp(ahead, arc, closed[:, 0]), np.interp(ahead, arc, closed[:, 1])], -1)
        tangent = (q - p) / np.linalg.norm(q - p, axis=-1, keepdims=True)
        left = np.stack([-tangent[..., 1], tangent[..., 0]], -1)
        sway = SWAY * np.sin(2 * math.pi * arc_length / wavelength + phases[2])
        return p + sway[..., None] * left

    xy = position(s)
    heading = position(s + 0.1) - position(s - 0.1)
    yaw = np.unwrap(np.arctan2(heading[:, 1], heading[:, 0]))
    look = math.radians(25) * np.sin(2 * math.pi * k / 90 + phases[3])
    base = rng.uniform(*HEIGHTS)
    bob = 0.015 * np.sin(2 * math.pi * k / 12 + phases[4])
    z = np.clip(base + bob, *HEIGHTS)
    poses = np.zeros((n_frames, 4, 4))
    for i in range(n_frames):
        pitch = math.radians(4) * math.sin(0.09 * i + phases[5])
        roll = math.radians(2) * math.sin(0.13 * i + phases[6])
        poses[i, :3, :3] = body_rotation(yaw[i] + look[i], pitch, roll)
        poses[i, :3, 3] = (xy[i, 0], xy[i, 1], z[i])
        poses[i, 3, 3] = 1.0
    if clearance(world, poses[:, :3, 3]).min() < MIN_CLEARANCE - 1e-9:
        raise RuntimeError(f"indoor trajectory {seed}: a pose comes within {MIN_CLEARANCE} m of an object")
    return poses
