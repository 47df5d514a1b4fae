"""Vectorised ray casting against the world's boxes, vertical cylinders, spheres and ground plane.

Rays come in tiles (``[T, K, 3]``: T tiles of K neighbouring rays). Each tile gets a bounding cone;
each object a bounding sphere; only (tile, object) pairs whose cone and sphere overlap are intersected,
all pairs of one primitive kind in one batch of tensor operations. The nearest hit per ray is resolved
with a scatter-min.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import torch
from torch import Tensor

from .world import GROUND, SKY, World

_EPS = 1e-4  # hits closer than this (metres) are ignored


@dataclasses.dataclass
class SceneTensors:
    box_lo: Tensor
    box_hi: Tensor
    box_material: Tensor
    box_tint: Tensor
    cylinders: Tensor
    cylinder_material: Tensor
    cylinder_tint: Tensor
    spheres: Tensor
    sphere_material: Tensor
    sphere_tint: Tensor
    # kind -> (bounding-sphere centre [N, 3], its radius [N], top height [N], footprint radius [N] around
    # the centre's (x, y))
    bounds: dict[str, tuple[Tensor, Tensor, Tensor, Tensor]]
    # True: bound the elevation of an object's top below the origin from its nearest point, as the street
    # datasets were rendered; that bound is too low, so rays meeting such a top beyond its nearest point
    # (a far part of a sidewalk's or a car's top) pass through it. False: the exact bound.
    legacy_culling: bool = False


def scene_tensors(world: World, device="cpu", legacy_culling: bool = False) -> SceneTensors:
    """The world's objects as tensors for :func:`cast`; ``legacy_culling`` reproduces the street
    datasets' ground truth byte for byte (see :class:`SceneTensors`)."""
    f = dict(dtype=torch.float32, device=device)
    lo, hi = torch.as_tensor(world.boxes[:, :3], **f), torch.as_tensor(world.boxes[:, 3:], **f)
    cyl = torch.as_tensor(world.cylinders, **f).reshape(-1, 5)
    sph = torch.as_tensor(world.spheres, **f).reshape(-1, 4)
    cyl_centre = torch.stack((cyl[:, 0], cyl[:, 1], 0.5 * (cyl[:, 3] + cyl[:, 4])), -1)
    cyl_radius = torch.sqrt(cyl[:, 2] ** 2 + (0.5 * (cyl[:, 4] - cyl[:, 3])) ** 2)
    return SceneTensors(
        lo,
        hi,
        torch.as_tensor(world.box_material, device=device),
        torch.as_tensor(world.box_tint, **f),
        cyl,
        torch.as_tensor(world.cylinder_material, device=device),
        torch.as_tensor(world.cylinder_tint, **f),
        sph,
        torch.as_tensor(world.sphere_material, device=device),
        torch.as_tensor(world.sphere_tint, **f),
        bounds={
            "box": (
                0.5 * (lo + hi),
                0.5 * (hi - lo).norm(dim=-1),
                hi[:, 2],
                0.5 * (hi - lo)[:, :2].norm(dim=-1),
            ),
            "cylinder": (cyl_centre, cyl_radius, cyl[:, 4], cyl[:, 2]),
            "sphere": (sph[:, :3], sph[:, 3], sph[:, 2] + sph[:, 3], sph[:, 3]),
        },
        legacy_culling=legacy_culling,
    )


class Hit(NamedTuple):
    t: Tensor  # [R] distance along the unit ray; inf where nothing was hit
    material: Tensor  # [R] int64
    normal: Tensor  # [R, 3] world-frame unit normal
    tint: Tensor  # [R, 3]
    # with movers only: where the texture is looked up minus the hit point ([R, 3]; 0 on the static
    # world, so a mover's texture travels with it), and the mover hit ([R] int64; -1 none)
    offset: Tensor | None = None
    agent: Tensor | None = None


@dataclasses.dataclass
class Movers:
    """Boxes turned about the vertical, at one instant (the traffic's): ``lo``/``hi [P, 3]`` corners in
    each box's own frame, placed at ``(x, y)`` with heading ``yaw`` (``cos``/``sin [P]``); ``owner [P]``
    the agent of each box."""

    lo: Tensor
    hi: Tensor
    xy: Tensor
    cos: Tensor
    sin: Tensor
    owner: Tensor
    material: Tensor
    tint: Tensor
    bounds: tuple[Tensor, Tensor, Tensor, Tensor]

    @classmethod
    def from_boxes(cls, boxes: dict, device="cpu") -> Movers:
        """From :meth:`fisheyedepth.synthetic.traffic.Traffic.boxes_at`'s arrays."""
        f = dict(dtype=torch.float32, device=device)
        lo, hi = torch.as_tensor(boxes["lo"], **f), torch.as_tensor(boxes["hi"], **f)
        xy = torch.stack((torch.as_tensor(boxes["x"], **f), torch.as_tensor(boxes["y"], **f)), -1)
        yaw = torch.as_tensor(boxes["yaw"], dtype=torch.float64, device=device)
        cos, sin = torch.cos(yaw).float(), torch.sin(yaw).float()
        mid = 0.5 * (lo + hi)
        centre = torch.stack(
            (
                xy[:, 0] + cos * mid[:, 0] - sin * mid[:, 1],
                xy[:, 1] + sin * mid[:, 0] + cos * mid[:, 1],
                mid[:, 2],
            ),
            -1,
        )
        half = 0.5 * (hi - lo)
        bounds = (centre, half.norm(dim=-1), hi[:, 2], half[:, :2].norm(dim=-1))
        return cls(
            lo,
            hi,
            xy,
            cos,
            sin,
            torch.as_tensor(boxes["owner"], dtype=torch.int64, device=device),
            torch.as_tensor(boxes["material"], dtype=torch.int64, device=device),
            torch.as_tensor(boxes["tint"], **f),
            bounds,
        )

    def to_local(self, points: Tensor, index: Tensor, direction: bool = False) -> Tensor:
        """World points (or directions) ``[N, 3]`` in the frames of the boxes ``index [N]``."""
        c, s = self.cos[index], self.sin[index]
        x, y, z = points.unbind(-1)
        if not direction:
            x, y = x - self.xy[index, 0], y - self.xy[index, 1]
        return torch.stack((c * x + s * y, -s * x + c * y, z), -1)

    def to_world(self, vectors: Tensor, index: Tensor) -> Tensor:
        """Directions ``[N, 3]`` in the boxes' frames turned into the world's."""
        c, s = self.cos[index], self.sin[index]
        x, y, z = vectors.unbind(-1)
        return torch.stack((c * x - s * y, s * x + c * y, z), -1)


def tile_grid(grid: Tensor, th: int, tw: int) -> Tensor:
    """``[H, W, C]`` -> ``[T, th * tw, C]`` tiles (H, W multiples of th, tw)."""
    H, W, C = grid.shape
    return grid.reshape(H // th, th, W // tw, tw, C).permute(0, 2, 1, 3, 4).reshape(-1, th * tw, C)


def untile_grid(values: Tensor, H: int, W: int, th: int, tw: int) -> Tensor:
    """Inverse of :func:`tile_grid`: ``[T * th * tw, ...]`` values in tiled ray order -> ``[H, W, ...]``."""
    rest = tuple(values.shape[1:])
    x = values.reshape(H // th, W // tw, th, tw, *rest)
    return x.permute(0, 2, 1, 3, *range(4, 4 + len(rest))).reshape(H, W, *rest)


def box_intersect(origin: Tensor, dirs: Tensor, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """Slab test. ``origin`` [..., 3] or [3], ``dirs`` [..., 3], ``lo``/``hi`` broadcastable.

    Returns the entry distance (inf on a miss or when the origin is inside) and the entry axis.
    """
    safe = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    inv = 1.0 / safe
    t1, t2 = (lo - origin) * inv, (hi - origin) * inv
    near, axis = torch.minimum(t1, t2).max(dim=-1)
    far = torch.maximum(t1, t2).amin(dim=-1)
    hit = (far >= near) & (near > _EPS)
    return torch.where(hit, near, torch.full_like(near, float("inf"))), axis


def box_normal(point: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """The outward unit normal ``[N, 3]`` of the face of each box (``lo``/``hi [N, 3]``) that ``point``
    lies on (the axis along which it is farthest out, relative to the box's half size)."""
    rel = (point - 0.5 * (lo + hi)) / (0.5 * (hi - lo)).clamp_min(1e-6)
    axis = rel.abs().argmax(-1)
    rows = torch.arange(len(axis))
    n = torch.zeros_like(point)
    n[rows, axis] = torch.sign(rel[rows, axis])
    return n


def _cylinder_intersect(origin: Tensor, dirs: Tensor, cyl: Tensor) -> Tensor:
    """Vertical cylinders ``cyl [..., 5]`` (cx, cy, radius, z0, z1), one per ray ``dirs [..., 3]``."""
    dx, dy, dz = dirs.unbind(-1)
    cx, cy, r, z0, z1 = cyl.unbind(-1)
    fx, fy = origin[0] - cx, origin[1] - cy
    a = (dx * dx + dy * dy).clamp_min(1e-12)
    b = 2 * (fx * dx + fy * dy)
    c = fx * fx + fy * fy - r * r
    disc = b * b - 4 * a * c
    t = (-b - torch.sqrt(disc.clamp_min(0))) / (2 * a)
    z = origin[2] + t * dz
    hit = (disc >= 0) & (t > _EPS) & (z >= z0) & (z <= z1)
    return torch.where(hit, t, torch.full_like(t, float("inf")))


def _sphere_intersect(origin: Tensor, dirs: Tensor, sph: Tensor) -> Tensor:
    """Spheres ``sph [..., 4]`` (centre, radius), one per ray ``dirs [..., 3]``."""
    L = sph[..., :3] - origin
    tca = (L * dirs).sum(-1)
    d2 = (L * L).sum(-1) - tca * tca
    r2 = sph[..., 3] ** 2
    t = tca - torch.sqrt((r2 - d2).clamp_min(0))
    hit = (d2 <= r2) & (t > _EPS)
    return torch.where(hit, t, torch.full_like(t, float("inf")))


def _overlapping_pairs(origin, cone_dir, cone_cos_sin, tile_min_dz, bounds, max_range, legacy=False):
    """(tile, object, nearest possible distance, sine of the object's highest elevation) for every tile
    cone that meets an object's bounding sphere and whose lowest ray is not above the object's top."""
    centre, radius, top, footprint = bounds
    v = centre - origin
    dist = v.norm(dim=-1).clamp_min(1e-6)
    near = dist - radius < max_range
    idx = near.nonzero().squeeze(1)
    if idx.numel() == 0:
        empty = torch.zeros(0, device=centre.device)
        return idx, idx, empty, empty
    v, dist, radius = v[idx], dist[idx], radius[idx]
    rise = top[idx] - origin[2]
    # the top is seen highest from its nearest point when above the origin, from its farthest when below
    across = v[:, :2].norm(dim=-1)
    nearest = (across - footprint[idx]).clamp_min(0)
    flat = nearest if legacy else torch.where(rise >= 0, nearest, across + footprint[idx])
    sin_top = rise / torch.sqrt(rise * rise + flat * flat).clamp_min(1e-9)  # sine of the highest elevation
    sin_b = (radius / dist).clamp(max=1.0)
    cos_b = torch.sqrt(1 - sin_b * sin_b)
    cos_a, sin_a = cone_cos_sin
    # angle(tile axis, object) <= alpha + beta  <=>  cos(angle) >= cos(alpha + beta) (when alpha + beta < pi)
    cos_ab = cos_a[:, None] * cos_b[None, :] - sin_a[:, None] * sin_b[None, :]
    wide = (torch.acos(cos_a.clamp(-1, 1))[:, None] + torch.asin(sin_b)[None, :]) >= torch.pi
    overlap = (cone_dir @ (v / dist[:, None]).T >= cos_ab) | wide | (dist <= radius)[None, :]
    overlap &= tile_min_dz[:, None] <= sin_top[None, :] + 1e-6
    tiles, objs = overlap.nonzero(as_tuple=True)
    return tiles, idx[objs], (dist - radius).clamp_min(0)[objs], sin_top[objs]


# Objects are intersected nearest first, in bands of their nearest possible distance; before each band,
# a tile whose rays all hit something nearer than an object skips that object (occlusion culling).
_BANDS = (0.0, 6.0, 15.0, 30.0, 60.0, float("inf"))


def first_per_ray(rays: Tensor, objs: Tensor) -> tuple[Tensor, Tensor]:
    """One hit per ray: where a ray meets two objects at the same distance (a face they share), the
    lower object id. Indexed writes with a repeated index leave the winner undefined, so two renders of
    one seed could differ on those rays."""
    if rays.numel() < 2:
        return rays, objs
    span = int(objs.max()) + 1
    key = torch.sort(rays * span + objs).values
    ray, obj = key // span, key % span
    first = torch.ones_like(ray, dtype=torch.bool)
    first[1:] = ray[1:] != ray[:-1]
    return ray[first], obj[first]


def cast(
    scene: SceneTensors, origin: Tensor, dirs: Tensor, max_range: float = 120.0, movers: Movers | None = None
) -> Hit:
    """Nearest hit for tiled unit rays ``dirs [T, K, 3]`` from ``origin [3]`` (world frame); ``movers``:
    the traffic's boxes at this instant (the hit then says which agent it met and where its texture is)."""
    T, K, _ = dirs.shape
    flat = dirs.reshape(-1, 3)
    n_rays = flat.shape[0]
    inf = float("inf")
    # ground plane z = 0
    down = flat[:, 2] < -1e-9
    t_ground = -origin[2] / torch.where(down, flat[:, 2], torch.full_like(flat[:, 2], -1e-9))
    t_ground = torch.where(down & (t_ground <= max_range), t_ground, torch.full_like(t_ground, inf))

    cone_dir = torch.nn.functional.normalize(dirs.mean(1), dim=-1)
    cos_a = (dirs * cone_dir[:, None]).sum(-1).amin(1).clamp(-1, 1)
    sin_a = torch.sqrt((1 - cos_a * cos_a).clamp_min(0))
    ray_ids = torch.arange(n_rays, device=dirs.device).reshape(T, K)
    tile_min_dz = dirs[..., 2].amin(1)
    pairs = {
        kind: _overlapping_pairs(
            origin, cone_dir, (cos_a, sin_a), tile_min_dz, scene.bounds[kind], max_range, scene.legacy_culling
        )
        for kind in ("box", "cylinder", "sphere")
        if scene.bounds[kind][0].shape[0]
    }
    if movers is not None and movers.lo.shape[0]:
        pairs["mover"] = _overlapping_pairs(
            origin, cone_dir, (cos_a, sin_a), tile_min_dz, movers.bounds, max_range
        )

    t_best = t_ground.clone()
    candidates = []  # (kind, ray ids [N], object ids [N], t [N])
    for lo_band, hi_band in zip(_BANDS[:-1], _BANDS[1:], strict=True):
        tile_far = t_best.reshape(T, K).amax(1)  # every ray of the tile hits something at most this far
        for kind, (tiles, objs, near, sin_top) in pairs.items():
            sel = ((near >= lo_band) & (near < hi_band) & (near < tile_far[tiles])).nonzero().squeeze(1)
            if sel.numel() == 0:
                continue
            # only rays that have hit nothing nearer than the object and are not above its top can hit it
            rid = ray_ids[tiles[sel]]
            maybe = (t_best[rid] > near[sel, None]) & (flat[rid, 2] <= sin_top[sel, None] + 1e-6)
            pair, k = maybe.nonzero(as_tuple=True)
            rays, ob = ray_ids[tiles[sel[pair]], k], objs[sel[pair]]
            d = flat[rays]
            if kind == "box":
                t, _ = box_intersect(origin, d, scene.box_lo[ob], scene.box_hi[ob])
            elif kind == "cylinder":
                t = _cylinder_intersect(origin, d, scene.cylinders[ob])
            elif kind == "mover":
                o_local = movers.to_local(origin.expand(len(ob), 3), ob)
                t, _ = box_intersect(o_local, movers.to_local(d, ob, True), movers.lo[ob], movers.hi[ob])
            else:
                t = _sphere_intersect(origin, d, scene.spheres[ob])
            t = torch.where(t <= max_range, t, torch.full_like(t, inf))
            t_best = t_best.scatter_reduce(0, rays, t, reduce="amin")
            candidates.append((kind, rays, ob, t))

    material = torch.full((n_rays,), SKY, dtype=torch.int64, device=dirs.device)
    normal = torch.zeros(n_rays, 3, device=dirs.device)
    tint = torch.ones(n_rays, 3, device=dirs.device)
    offset = agent = None
    if movers is not None:
        offset = torch.zeros(n_rays, 3, device=dirs.device)
        agent = torch.full((n_rays,), -1, dtype=torch.int64, device=dirs.device)
    ground = torch.isfinite(t_ground) & (t_ground == t_best)
    material[ground] = GROUND
    normal[ground] = torch.tensor([0.0, 0.0, 1.0], device=dirs.device)
    for kind, rays, objs, t in candidates:
        win = torch.isfinite(t) & (t == t_best[rays])
        if not bool(win.any()):
            continue
        rays, obj = first_per_ray(rays[win], objs[win])
        point = origin + flat[rays] * t_best[rays, None]
        if kind == "box":
            n = box_normal(point, scene.box_lo[obj], scene.box_hi[obj])
            mat, tn = scene.box_material[obj], scene.box_tint[obj]
        elif kind == "cylinder":
            cyl = scene.cylinders[obj]
            n = torch.stack(
                (point[:, 0] - cyl[:, 0], point[:, 1] - cyl[:, 1], torch.zeros_like(cyl[:, 0])), -1
            )
            n = torch.nn.functional.normalize(n, dim=-1)
            mat, tn = scene.cylinder_material[obj], scene.cylinder_tint[obj]
        elif kind == "mover":
            local = movers.to_local(point, obj)
            n = movers.to_world(box_normal(local, movers.lo[obj], movers.hi[obj]), obj)
            mat, tn = movers.material[obj], movers.tint[obj]
            owner = movers.owner[obj]
            # each agent's texture is its own, fixed to its body: looked up in its frame, moved apart
            apart = torch.stack((owner * 37.0, owner * 23.0, torch.zeros_like(owner)), -1).to(local)
            offset[rays] = local + apart - point
            agent[rays] = owner
        else:
            n = torch.nn.functional.normalize(point - scene.spheres[obj, :3], dim=-1)
            mat, tn = scene.sphere_material[obj], scene.sphere_tint[obj]
        material[rays], normal[rays], tint[rays] = mat, n, tn
    return Hit(t_best, material, normal, tint, offset, agent)
