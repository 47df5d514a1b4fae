"""Per-pixel rays, computed once per camera and kept on the compute device.

The paper's caching mechanism: unprojection (iterative for distorted models) runs once per
(camera, resolution, device, dtype); every training step then only multiplies cached unit rays by
the predicted distance. Entries live on the device they are used on: nothing is copied per call.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from .base import CameraModel


class Rays(NamedTuple):
    rays: Tensor  # [H, W, 3] unit rays in the camera frame
    valid: Tensor  # [H, W] bool: the pixel has a ray in the model


def pixel_grid(width: int, height: int, device=None, dtype=torch.float32) -> Tensor:
    """``[H, W, 2]`` pixel-centre coordinates ``(u, v) = (column, row)``."""
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype),
        torch.arange(width, device=device, dtype=dtype),
        indexing="ij",
    )
    return torch.stack((u, v), dim=-1)


def compute_rays(camera: CameraModel, device=None, dtype=torch.float32) -> Rays:
    """Unproject every pixel of ``camera``'s image, in float64 (then cast to ``dtype``).

    float64 is used where the device supports it, so float32 rays are correctly rounded rather than the
    result of a float32 iteration.
    """
    device = torch.device("cpu") if device is None else torch.device(device)
    work = device if device.type in ("cpu", "cuda") else torch.device("cpu")
    rays, valid = camera.unproject(pixel_grid(camera.width, camera.height, work, torch.float64))
    return Rays(rays.to(device=device, dtype=dtype).contiguous(), valid.to(device).contiguous())


def _device_key(device) -> torch.device:
    device = torch.device("cpu") if device is None else torch.device(device)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    return device


class RayCache:
    """A bounded LRU cache of :class:`Rays`, keyed by ``(camera, device, dtype)``.

    The camera value includes its resolution, so a resized or flipped camera is its own entry.
    """

    def __init__(self, max_entries: int = 64):
        if max_entries < 1:
            raise ValueError(f"max_entries must be >= 1, got {max_entries}")
        self.max_entries = max_entries
        self._entries: OrderedDict[tuple, Rays] = OrderedDict()
        self.misses = 0

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        self._entries.clear()

    def get(self, camera: CameraModel, device=None, dtype=torch.float32) -> Rays:
        key = (camera, _device_key(device), dtype)
        entry = self._entries.get(key)
        if entry is not None:
            self._entries.move_to_end(key)
            return entry
        self.misses += 1
        entry = compute_rays(camera, key[1], dtype)
        self._entries[key] = entry
        if len(self._entries) > self.max_entries:
            self._entries.popitem(last=False)
        return entry

    def batch(self, cameras: Sequence[CameraModel], device=None, dtype=torch.float32) -> Rays:
        """Stacked ``[B, H, W, 3]`` rays and ``[B, H, W]`` validity for one camera per sample."""
        entries = [self.get(cam, device, dtype) for cam in cameras]
        sizes = {(cam.width, cam.height) for cam in cameras}
        if len(sizes) != 1:
            raise ValueError(f"cameras of one batch must share the image size, got {sorted(sizes)}")
        if all(e is entries[0] for e in entries):
            n = len(entries)
            return Rays(entries[0].rays.expand(n, -1, -1, -1), entries[0].valid.expand(n, -1, -1))
        return Rays(torch.stack([e.rays for e in entries]), torch.stack([e.valid for e in entries]))
