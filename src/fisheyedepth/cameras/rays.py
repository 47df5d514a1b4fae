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
import torch.nn.functional as F
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


def erode_field_of_view(valid: Tensor, margin: int) -> Tensor:
    """``valid`` ``[B, H, W]`` (pixels with a ray: the image circle) without the pixels within ``margin``
    pixels of one that has none: the rim, where a pixel's footprint mixes in the black outside the circle.
    The image's rectangular border does not count as outside (the warp checks it)."""
    if margin < 0:
        raise ValueError(f"rim margin: {margin} pixels is negative")
    if margin == 0:
        return valid
    inside = valid.to(torch.float32)[:, None]
    return (-F.max_pool2d(-inside, 2 * margin + 1, stride=1, padding=margin))[:, 0] > 0.5


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
        self._inside: OrderedDict[tuple, Tensor] = OrderedDict()  # eroded validity, by camera and margin
        self.misses = 0

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        self._entries.clear()
        self._inside.clear()

    def get(self, camera: CameraModel, device=None, dtype=torch.float32) -> Rays:
        key = (camera, _device_key(device), dtype)
        if key not in self._entries:
            self.misses += 1
        return self._lookup(self._entries, key, lambda: compute_rays(camera, key[1], dtype))

    def _lookup(self, store: OrderedDict, key: tuple, compute):
        """``store[key]``, computed on a miss; the least recently used entry leaves past ``max_entries``."""
        entry = store.get(key)
        if entry is None:
            entry = store[key] = compute()
            if len(store) > self.max_entries:
                store.popitem(last=False)
        else:
            store.move_to_end(key)
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

    def inside(self, cameras: Sequence[CameraModel], margin: int, device=None) -> Tensor:
        """``[B, H, W]`` bool: each sample's pixels with a ray, less the rim of ``margin`` pixels
        (:func:`erode_field_of_view`), eroded once per camera and margin and kept like the rays."""
        device = _device_key(device)
        return torch.stack(
            [
                self._lookup(
                    self._inside,
                    (cam, device, margin),
                    lambda cam=cam: erode_field_of_view(self.get(cam, device).valid[None], margin)[0],
                )
                for cam in cameras
            ]
        )
