"""Per-pixel rays, computed once per camera and kept on the compute device.

The paper's caching mechanism: unprojection (iterative for distorted models) runs once per
(camera, resolution, device, dtype); every training step then only multiplies cached unit rays by
the predicted distance. Entries live on the device they are used on: nothing is copied per call.
"""

from __future__ import annotations

import threading
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


# Above this many pixels, a camera without a direct inverse is unprojected by interpolation and
# Newton's polish (:func:`interpolated_rays`), below it pixel by pixel.
INTERPOLATE_FROM_PIXELS = 256 * 256


def compute_rays(camera: CameraModel, device=None, dtype=torch.float32) -> Rays:
    """Unproject every pixel of ``camera``'s image, in float64 (then cast to ``dtype``).

    float64 is used where the device supports it, so float32 rays are correctly rounded rather than the
    result of a float32 iteration. A large image of a model without a direct inverse goes through
    :func:`interpolated_rays` (the same rays, in a tenth of the time).
    """
    device = torch.device("cpu") if device is None else torch.device(device)
    work = device if device.type in ("cpu", "cuda") else torch.device("cpu")
    if not camera.direct_unproject and camera.width * camera.height >= INTERPOLATE_FROM_PIXELS:
        # polished to what the requested precision can hold: float32 rays are 4e-5 px apart at 700 px
        rays, valid = interpolated_rays(camera, work, tolerance_px=1e-9 if dtype == torch.float64 else 1e-6)
    else:
        rays, valid = camera.unproject(pixel_grid(camera.width, camera.height, work, torch.float64))
    return Rays(rays.to(device=device, dtype=dtype).contiguous(), valid.to(device).contiguous())


def angle_vector(rays: Tensor) -> Tensor:
    """``[..., 2]``: ``theta (x, y) / |(x, y)|`` of unit rays, ``theta`` the incidence angle: a chart of
    the sphere that is smooth beyond 90 degrees (everywhere but straight behind the camera)."""
    rho = torch.sqrt(rays[..., :1] ** 2 + rays[..., 1:2] ** 2)
    theta = torch.atan2(rho, rays[..., 2:])
    scale = torch.where(rho > 1e-12, theta / rho.clamp(min=1e-300), 1 / rays[..., 2:].clamp(min=1e-300))
    return rays[..., :2] * scale


def angle_vector_rays(ab: Tensor) -> Tensor:
    """The inverse of :func:`angle_vector`: unit rays ``[..., 3]``."""
    theta = torch.sqrt(ab[..., :1] ** 2 + ab[..., 1:] ** 2)
    sinc = torch.where(theta > 1e-8, torch.sin(theta) / theta.clamp(min=1e-300), 1 - theta**2 / 6)
    return torch.cat((ab * sinc, torch.cos(theta)), dim=-1)


def inverse_jacobian(camera: CameraModel, ab: Tensor, step: float = 1e-6) -> Tensor:
    """``[..., 2, 2]``: ``d(ab) / d(uv)`` at :func:`angle_vector` coordinates ``ab``, the inverse of the
    projection's Jacobian (central differences of ``step`` radians)."""
    columns = []
    for axis in range(2):
        delta = torch.zeros(2, dtype=ab.dtype, device=ab.device)
        delta[axis] = step
        ahead, _ = camera.project(angle_vector_rays(ab + delta))
        behind, _ = camera.project(angle_vector_rays(ab - delta))
        columns.append((ahead - behind) / (2 * step))
    (a, c), (b, d) = (col.unbind(-1) for col in columns)  # d(uv)/d(ab) = [[a, b], [c, d]]
    det = a * d - b * c
    det = torch.where(det.abs() > 1e-300, det, torch.ones_like(det))
    return torch.stack((torch.stack((d, -b), -1), torch.stack((-c, a), -1)), -2) / det[..., None, None]


def interpolated_rays(
    camera: CameraModel, device=None, stride: int = 8, tolerance_px: float = 1e-6, iterations: int = 6
) -> Rays:
    """Every pixel's unit ray, float64, without the model's iterative inverse at every pixel: the model
    unprojects the pixels of a grid ``stride`` apart; each pixel's ray starts from its cell's corners in
    :func:`angle_vector` coordinates and their inverse Jacobians ``d(angles) / d(uv)`` (exact to the third
    order), then Newton steps with the interpolated inverse Jacobian bring its projection within
    ``tolerance_px`` of the pixel. Cells with a corner, or a corner's neighbour, without
    a ray (the image circle's rim), and pixels the polish does not bring within the tolerance, are
    unprojected by the model itself: the result is the model's inverse, not an approximation of it."""
    device = torch.device("cpu") if device is None else torch.device(device)
    width, height = camera.width, camera.height
    # nodes past the last pixel: every pixel lies inside a cell
    nodes_u = stride * torch.arange((width - 1) // stride + 2, device=device, dtype=torch.float64)
    nodes_v = stride * torch.arange((height - 1) // stride + 2, device=device, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(nodes_u, nodes_v, indexing="xy"), dim=-1)  # [h, w, 2]
    node_rays, node_valid = camera.unproject(grid)
    node_ab = angle_vector(node_rays)  # [h, w, 2]
    jacobian = inverse_jacobian(camera, node_ab)  # [h, w, 2 (a, b), 2 (u, v)]
    # a cell is interpolated where its corners and their neighbours all have a ray
    usable = -F.max_pool2d(-node_valid[None, None].double(), 3, stride=1, padding=1)[0, 0] > 0.5
    usable = -F.max_pool2d(-usable[None, None].double(), 2, stride=1)[0, 0] > 0.5  # [h - 1, w - 1] cells
    # bilinear interpolation, and the corners' first-order predictions blended with the same weights:
    # their errors are equal and opposite for a quadratic, so their mean is exact to the third order
    node_grid = (jacobian @ grid[..., None])[..., 0]
    fields = torch.cat((node_ab, jacobian.reshape(*node_ab.shape[:2], 4), node_grid), -1).permute(2, 0, 1)
    size = ((len(nodes_v) - 1) * stride + 1, (len(nodes_u) - 1) * stride + 1)
    fine = F.interpolate(fields[None], size=size, mode="bilinear", align_corners=True)[0, :, :height, :width]
    fine = fine.permute(1, 2, 0).reshape(height * width, 8)
    J = fine[:, 2:6].reshape(-1, 2, 2)
    uv = pixel_grid(width, height, device, torch.float64).reshape(-1, 2)
    ab = fine[:, :2] + 0.5 * (J[..., 0] * uv[:, :1] + J[..., 1] * uv[:, 1:] - fine[:, 6:])
    cells = usable.repeat_interleave(stride, 0).repeat_interleave(stride, 1)[:height, :width].reshape(-1)
    # the first step over every pixel at once, then only over those it left unfinished
    projected, projects = camera.project(angle_vector_rays(ab))
    error = uv - projected
    valid = cells & projects & (error[:, 0] ** 2 + error[:, 1] ** 2 <= tolerance_px**2)
    active = (cells & ~valid).nonzero()[:, 0]
    error = error[active]
    for _ in range(iterations):
        if active.numel() == 0:
            break
        J_active = J[active]
        ab[active] += J_active[..., 0] * error[:, :1] + J_active[..., 1] * error[:, 1:]
        projected, projects = camera.project(angle_vector_rays(ab[active]))
        error = uv[active] - projected
        done = projects & (error[:, 0] ** 2 + error[:, 1] ** 2 <= tolerance_px**2)
        valid[active[done]] = True
        active, error = active[~done], error[~done]
    rays = angle_vector_rays(ab)
    exact = ~valid  # the rim and whatever the polish left: the model's own inverse
    if bool(exact.any()):
        rays[exact], valid[exact] = camera.unproject(uv[exact])
    axis = torch.zeros_like(rays)
    axis[:, 2] = 1
    rays = torch.where(valid[:, None], rays, axis)
    return Rays(rays.reshape(height, width, 3), valid.reshape(height, width))


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
        self._lock = threading.RLock()  # callers on several threads (the stereo pipeline's pairs)
        self.misses = 0

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        self._entries.clear()
        self._inside.clear()

    def get(self, camera: CameraModel, device=None, dtype=torch.float32) -> Rays:
        key = (camera, _device_key(device), dtype)
        with self._lock:
            if key not in self._entries:
                self.misses += 1
            return self._lookup(self._entries, key, lambda: compute_rays(camera, key[1], dtype))

    def _lookup(self, store: OrderedDict, key: tuple, compute):
        """``store[key]``, computed on a miss; the least recently used entry leaves past ``max_entries``.
        Under the lock: one thread computes an entry, the others wait for it."""
        with self._lock:
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
