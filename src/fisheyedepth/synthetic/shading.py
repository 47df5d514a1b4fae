"""Materials: world-fixed procedural albedo, Lambertian sun + ambient light, and the sky; indoors, floors
of planks or tiles, painted or papered walls, wood and fabric, lit by ambient, directional and point light,
with emissive windows and lamps.

Lighting depends only on the surface (albedo, normal) and the fixed sun, never on the viewer, so
brightness constancy holds between frames and cameras apart from occlusion and resampling. Textures are
band-limited to the pixel footprint (see :func:`noise.lod_weight`), and thin painted stripes are
box-filtered analytically, so that resampling from another viewpoint does not alias.
"""

from __future__ import annotations

import torch
from torch import Tensor

from . import world as W
from .noise import fbm2, fbm3, hash01, lod_weight
from .raycast import Hit


def _coverage(distance_to_centre: Tensor, half_width: float, footprint: Tensor) -> Tensor:
    """Fraction of a pixel of width ``footprint`` covered by a stripe ``|s| <= half_width`` (box filter)."""
    s, f = distance_to_centre, footprint
    overlap = torch.minimum(s + f / 2, torch.full_like(s, half_width)) - torch.maximum(
        s - f / 2, torch.full_like(s, -half_width)
    )
    return (overlap.clamp_min(0) / f).clamp(max=1.0)


def _ground(world: W.World, p: Tensor, fp: Tensor, seed: int) -> Tensor:
    x, y = p[:, 0], p[:, 1]
    P, hr = world.pitch, world.half_road
    dx = (x - torch.round(x / P) * P).abs()  # distance to the nearest street along y (x = i P)
    dy = (y - torch.round(y / P) * P).abs()  # ... along x (y = j P)
    asphalt = (
        0.3 + 0.35 * (fbm2(x, y, 2.0, 4, seed, fp) - 0.5) + 0.2 * (fbm2(x, y, 0.5, 2, seed + 7, fp) - 0.5)
    )
    grass = 0.7 + 1.2 * (fbm2(x, y, 1.5, 4, seed + 13, fp) - 0.5)
    out = torch.stack((0.25 * grass, 0.42 * grass, 0.16 * grass), -1)
    road = (dx <= hr) | (dy <= hr)
    out[road] = asphalt[road, None] * torch.tensor([1.0, 1.0, 1.05], device=p.device)
    # lane markings outside intersections: a dashed centre line and solid edge lines, box-filtered
    paint = torch.zeros_like(x)
    for along, across, other in ((x, dy, dx), (y, dx, dy)):
        stretch = ((across <= hr) & (other > hr)).to(x.dtype)
        dash = _coverage((torch.remainder(along, 6.0) - 1.5).abs(), 1.5, fp)
        centre = _coverage(across, 0.08, fp) * dash
        edge = _coverage((across - 3.55).abs(), 0.08, fp)
        paint = torch.maximum(paint, stretch * torch.maximum(centre, edge))
    return out * (1 - paint[:, None]) + 0.82 * paint[:, None]


def _blocks(u: Tensor, v: Tensor, width: float, height: float, seed: int, fp: Tensor) -> Tensor:
    """Running-bond blocks with mortar joints, in [0, 1]; fades to its mean below the pixel footprint."""
    row = torch.floor(v / height)
    shifted = u / width + 0.5 * torch.remainder(row, 2)
    col = torch.floor(shifted)
    fu, fv = shifted - col, v / height - row
    value = 0.7 + 0.6 * hash01(col.to(torch.int64), row.to(torch.int64), seed=seed)
    joint = (fu < 0.04) | (fu > 0.96) | (fv < 0.06) | (fv > 0.94)
    pattern = torch.where(joint, torch.full_like(value, 0.6), value)
    mean = 0.6 * 0.19 + 1.0 * 0.81  # joints cover about 19 % of the area
    w = lod_weight(min(width, height), fp)
    return mean + w * (pattern - mean)


def _facade(p: Tensor, n: Tensor, tint: Tensor, fp: Tensor, seed: int) -> Tensor:
    u = torch.where(n[:, 0].abs() > 0.5, p[:, 1], p[:, 0])
    v = p[:, 2]
    roof = n[:, 2].abs() > 0.5
    shade = _blocks(u, v, 0.9, 0.35, seed, fp) + 0.6 * (fbm2(u, v, 2.0, 4, seed + 3, fp) - 0.5)
    out = tint * shade[:, None]
    # windows: floors every 3.2 m from 1.2 m, 1.4 m wide every 3 m (box-filtered edges)
    win = (
        _coverage((torch.remainder(u, 3.0) - 1.5).abs(), 0.7, fp)
        * _coverage((torch.remainder(v - 1.2, 3.2) - 0.8).abs(), 0.8, fp)
        * (v > 1.2).to(u.dtype)
    )
    glass = 0.12 + 0.12 * fbm2(u, v, 0.8, 2, seed + 5, fp)
    out = out * (1 - win[:, None]) + win[:, None] * torch.stack((glass, glass * 1.1, glass * 1.3), -1)
    concrete = 0.55 + 0.5 * (fbm2(p[:, 0], p[:, 1], 2.0, 4, seed + 9, fp) - 0.5)
    out[roof] = concrete[roof, None].expand(-1, 3)
    return out


def _floor(style: dict, p: Tensor, fp: Tensor, seed: int) -> Tensor:
    """Planks (running bond, with grain along them) or square tiles, in the room's floor tint."""
    u, v = (p[:, 0], p[:, 1]) if style["floor_axis"] == 0 else (p[:, 1], p[:, 0])
    tint = torch.as_tensor(style["floor_tint"], dtype=p.dtype, device=p.device)
    if style["floor"] == "planks":
        length, width = style["plank"]
        boards = _blocks(u, v, length, width, seed, fp)
        grain = fbm2(u * 0.25, v * 4.0, 0.25, 4, seed + 1, fp * 4.0)
        shade = boards * (0.75 + 0.5 * grain)
    else:
        side = style["tile"]
        shade = _blocks(u, v, side, side, seed + 2, fp) * (0.85 + 0.3 * fbm2(u, v, 0.4, 4, seed + 3, fp))
    return tint * shade[:, None]


def _wall(style: dict, p: Tensor, n: Tensor, tint: Tensor, fp: Tensor, seed: int) -> Tensor:
    """Paint with a soft mottle (or striped wallpaper) above a white skirting board."""
    x, y, z = p.unbind(-1)
    u = torch.where(n[:, 0].abs() > 0.5, y, x)
    shade = 0.9 + 0.35 * (fbm3(x, y, z, 0.6, 5, seed, fp) - 0.5)
    if style["wallpaper"] > 0:
        w = style["wallpaper"]
        stripe = _coverage((torch.remainder(u, 2 * w) - w / 2).abs(), w / 4, fp)
        shade = shade * (1 - 0.15 * stripe)
    out = tint * shade[:, None]
    skirting = _coverage((z - 0.05).abs(), 0.05, fp)
    return out * (1 - skirting[:, None]) + 0.9 * skirting[:, None]


def _wood(p: Tensor, tint: Tensor, fp: Tensor, seed: int) -> Tensor:
    x, y, z = p.unbind(-1)
    grain = fbm3(x * 3.0, y * 3.0, z * 0.5, 0.3, 4, seed, fp * 3.0)
    return tint * (0.6 + 0.8 * grain)[:, None]


def _outside(p: Tensor, fp: Tensor, seed: int) -> Tensor:
    """The bright view through a window: a pale sky with soft clouds, unlit."""
    x, y, z = p.unbind(-1)
    cloud = fbm3(x, y, z, 0.5, 3, seed, fp)
    base = torch.tensor([0.82, 0.88, 0.96], dtype=p.dtype, device=p.device)
    return base + 0.18 * cloud[:, None]


def albedo(world: W.World, hit: Hit, points: Tensor, footprint: Tensor) -> Tensor:
    """``[R, 3]`` albedo in [0, 1] at each hit point (sky rays are left at 0)."""
    out = torch.zeros_like(points)
    mat, seed = hit.material, world.seed * 1000
    for m in range(len(W.MATERIAL_NAMES)):
        sel = (mat == m).nonzero().squeeze(1)
        if sel.numel() == 0 or m == W.SKY:
            continue
        p, n, tint, fp = points[sel], hit.normal[sel], hit.tint[sel], footprint[sel]
        x, y, z = p.unbind(-1)
        if m == W.GROUND and world.scene == "indoor":
            a = _floor(world.style, p, fp, seed + 100)
        elif m == W.GROUND:
            a = _ground(world, p, fp, seed)
        elif m == W.SIDEWALK:
            top = n[:, 2] > 0.5
            tiles = _blocks(torch.where(top, x, x + y), torch.where(top, y, z * 4), 0.5, 0.5, seed + 21, fp)
            a = tint * (tiles * (0.7 + 0.6 * fbm2(x + z, y, 1.0, 4, seed + 22, fp)))[:, None]
        elif m == W.FACADE:
            a = _facade(p, n, tint, fp, seed + 30)
        elif m == W.CAR:
            a = tint * (0.7 + 0.6 * fbm3(x, y, z, 0.8, 3, seed + 40, fp))[:, None]
        elif m == W.CONCRETE:
            a = tint * (0.5 + 0.9 * fbm3(x, y, z, 1.0, 4, seed + 50, fp))[:, None]
        elif m == W.POLE:
            a = tint * (0.75 + 0.5 * fbm3(x, y, z, 0.6, 3, seed + 60, fp))[:, None]
        elif m == W.BARK:
            a = tint * (0.5 + 1.0 * fbm3(x * 2, y * 2, z * 0.5, 0.4, 3, seed + 70, fp))[:, None]
        elif m == W.FOLIAGE and world.scene == "indoor":  # a house plant: leaves of a hand's size
            a = tint * (0.4 + 1.2 * fbm3(x, y, z, 0.15, 4, seed + 80, fp))[:, None]
        elif m == W.FOLIAGE:
            a = tint * (0.4 + 1.2 * fbm3(x, y, z, 0.8, 4, seed + 80, fp))[:, None]
        elif m == W.WALL:
            a = _wall(world.style, p, n, tint, fp, seed + 110)
        elif m == W.CEILING:
            a = tint * (0.92 + 0.16 * (fbm2(x, y, 0.8, 4, seed + 120, fp) - 0.5))[:, None]
        elif m in (W.WOOD, W.DOOR):
            a = _wood(p, tint, fp, seed + 130 + (m == W.DOOR))
        elif m == W.FABRIC:
            a = tint * (0.7 + 0.6 * fbm3(x, y, z, 0.12, 4, seed + 140, fp))[:, None]
        elif m == W.WINDOW:
            a = _outside(p, fp, seed + 150)
        elif m == W.LAMP:
            a = tint * (0.92 + 0.16 * fbm3(x, y, z, 0.1, 2, seed + 160, fp))[:, None]
        else:  # the ego vehicle: dark and untextured
            a = torch.full_like(p, 0.06)
        out[sel] = a.clamp(0, 1)
    return out


def sky(dirs: Tensor) -> Tensor:
    """Sky colour from the world-frame ray elevation: pale at the horizon, blue at the zenith."""
    up = dirs[:, 2].clamp(-0.2, 1.0)[:, None]
    horizon = torch.tensor([0.85, 0.88, 0.92], device=dirs.device)
    zenith = torch.tensor([0.35, 0.55, 0.85], device=dirs.device)
    return horizon + (zenith - horizon) * up.clamp_min(0).sqrt()


def shade(world: W.World, hit: Hit, origin: Tensor, dirs: Tensor, pixel_angle: float) -> Tensor:
    """``[R, 3]`` linear colour for the rays ``dirs [R, 3]`` with their nearest hits.

    ``pixel_angle``: the angle one output pixel subtends (radians), for texture filtering.
    """
    finite = torch.isfinite(hit.t)
    t = torch.where(finite, hit.t, torch.zeros_like(hit.t))
    points = origin + dirs * t[:, None]
    slant = (hit.normal * dirs).sum(-1).abs().clamp_min(0.15)
    footprint = (t * pixel_angle / slant).clamp_min(1e-4)
    sun = torch.as_tensor(world.sun, dtype=dirs.dtype, device=dirs.device)
    texture = points if hit.offset is None else points + hit.offset  # a mover's texture moves with it
    if world.scene == "indoor":
        return _indoor(world, hit, points, albedo(world, hit, texture, footprint), sun)
    light = 0.45 + 0.55 * (hit.normal @ sun).clamp_min(0)
    colour = albedo(world, hit, texture, footprint) * light[:, None]
    return torch.where((hit.material == W.SKY)[:, None], sky(dirs), colour)


def _indoor(world: W.World, hit: Hit, points: Tensor, albedo_: Tensor, toward: Tensor) -> Tensor:
    """Interior light, viewer-independent like the sun's: ambient, a directional term (``world.sun``: the
    direction the light comes from) and a point light with a soft falloff; windows and lamps glow."""
    style = world.style
    lamp = torch.as_tensor(style["light"], dtype=points.dtype, device=points.device)
    to_lamp = lamp - points
    dist = to_lamp.norm(dim=-1).clamp_min(1e-3)
    point = (hit.normal * to_lamp).sum(-1).clamp_min(0) / dist / (1 + (dist / 2.5) ** 2)
    light = (
        style["ambient"] + style["directional"] * (hit.normal @ toward).clamp_min(0) + style["point"] * point
    )
    tint = torch.as_tensor(style["light_tint"], dtype=points.dtype, device=points.device)
    colour = albedo_ * light[:, None] * tint
    emissive = (hit.material == W.WINDOW) | (hit.material == W.LAMP)
    colour = torch.where(emissive[:, None], albedo_, colour)
    return torch.where((hit.material == W.SKY)[:, None], torch.zeros_like(colour), colour)
