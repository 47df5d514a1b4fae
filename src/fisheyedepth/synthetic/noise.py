"""Procedural textures: hashed value noise on an integer lattice, evaluated in world coordinates.

Everything is a pure function of the world position and an integer seed, so a surface looks the same
from every camera and every frame (brightness constancy holds up to resampling and occlusion).
"""

from __future__ import annotations

import torch
from torch import Tensor

_PRIMES = (73856093, 19349663, 83492791)


def hash01(*coords: Tensor, seed: int = 0) -> Tensor:
    """A pseudo-random number in [0, 1) for each integer lattice point (int64 tensors of one shape)."""
    h = torch.full_like(coords[0], (seed * 2654435761 + 97) & 0x7FFFFFFF)
    for c, p in zip(coords, _PRIMES, strict=False):
        h = h ^ (c * p)
        h = (h ^ (h >> 13)) * 1274126177
        h = h ^ (h >> 16)
    return (h & 0xFFFFFF).to(torch.float32) / float(0x1000000)


def _smooth(t: Tensor) -> Tensor:
    return t * t * (3 - 2 * t)


def value_noise2(x: Tensor, y: Tensor, seed: int = 0) -> Tensor:
    """Smooth 2-D value noise in [0, 1] with unit lattice spacing."""
    xf, yf = torch.floor(x), torch.floor(y)
    xi, yi = xf.to(torch.int64), yf.to(torch.int64)
    tx, ty = _smooth(x - xf), _smooth(y - yf)
    a = hash01(xi, yi, seed=seed)
    b = hash01(xi + 1, yi, seed=seed)
    c = hash01(xi, yi + 1, seed=seed)
    d = hash01(xi + 1, yi + 1, seed=seed)
    return torch.lerp(torch.lerp(a, b, tx), torch.lerp(c, d, tx), ty)


def value_noise3(x: Tensor, y: Tensor, z: Tensor, seed: int = 0) -> Tensor:
    """Smooth 3-D value noise in [0, 1] with unit lattice spacing."""
    xf, yf, zf = torch.floor(x), torch.floor(y), torch.floor(z)
    xi, yi, zi = xf.to(torch.int64), yf.to(torch.int64), zf.to(torch.int64)
    tx, ty, tz = _smooth(x - xf), _smooth(y - yf), _smooth(z - zf)
    out = []
    for dz in (0, 1):
        a = hash01(xi, yi, zi + dz, seed=seed)
        b = hash01(xi + 1, yi, zi + dz, seed=seed)
        c = hash01(xi, yi + 1, zi + dz, seed=seed)
        d = hash01(xi + 1, yi + 1, zi + dz, seed=seed)
        out.append(torch.lerp(torch.lerp(a, b, tx), torch.lerp(c, d, tx), ty))
    return torch.lerp(out[0], out[1], tz)


def lod_weight(wavelength: float | Tensor, footprint: Tensor | None) -> Tensor | float:
    """How much of a feature of ``wavelength`` metres to keep when one pixel covers ``footprint`` metres.

    Features at least 4 pixels long are kept whole, those under 2 pixels are replaced by their mean (a
    mip-map in closed form): the rendered texture stays band-limited, so a surface looks the same after
    resampling from another viewpoint, which brightness constancy between frames needs.
    """
    if footprint is None:
        return 1.0
    return (wavelength / (2.0 * footprint) - 1.0).clamp(0.0, 1.0)


def fbm2(
    x: Tensor, y: Tensor, scale: float, octaves: int = 3, seed: int = 0, footprint: Tensor | None = None
) -> Tensor:
    """Fractal sum of 2-D value noise; ``scale`` is the coarsest feature size in metres. Range [0, 1].
    Octaves finer than the pixel ``footprint`` (metres) fade to their mean."""
    total, amp, norm, f = torch.zeros_like(x), 1.0, 0.0, 1.0 / scale
    for o in range(octaves):
        w = lod_weight(1.0 / f, footprint)
        total = total + amp * (0.5 + w * (value_noise2(x * f, y * f, seed=seed + 101 * o) - 0.5))
        norm += amp
        amp *= 0.5
        f *= 2.0
    return total / norm


def fbm3(
    x: Tensor,
    y: Tensor,
    z: Tensor,
    scale: float,
    octaves: int = 3,
    seed: int = 0,
    footprint: Tensor | None = None,
) -> Tensor:
    total, amp, norm, f = torch.zeros_like(x), 1.0, 0.0, 1.0 / scale
    for o in range(octaves):
        w = lod_weight(1.0 / f, footprint)
        total = total + amp * (0.5 + w * (value_noise3(x * f, y * f, z * f, seed=seed + 101 * o) - 0.5))
        norm += amp
        amp *= 0.5
        f *= 2.0
    return total / norm
