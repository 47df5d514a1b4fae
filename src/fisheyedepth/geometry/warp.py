"""The photometric warp: target pixels -> 3-D points (cached rays x distance) -> source pixels.

For each target pixel p with unit ray r(p) (cached) and predicted Euclidean distance L(p):
    X_t = L(p) r(p),   X_s = T_{t->s} X_t,   p_s = F_s(X_s)
where F_s is the source camera's projection (any model, possibly another camera of the rig).

Sampling convention: ``grid_sample(..., align_corners=False)`` (``ALIGN_CORNERS``). With pixel centres at
integer (u, v), the normalised coordinate is ``x = (2 u + 1) / W - 1``: -1 and +1 are the outer edges of
the first and last pixel. (Monodepth2 normalises for ``align_corners=True`` but samples with False,
a half-pixel shift; this module uses one convention on both sides.)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from ..cameras.base import CameraModel
from .se3 import transform_points

ALIGN_CORNERS = False
_OUTSIDE = -2.0  # grid value given to invalid pixels: outside [-1, 1], so zero-padded samples are 0
_SLACK_PX = 1e-3  # a border pixel that maps onto itself up to rounding is still inside the image


class Warp(NamedTuple):
    grid: Tensor  # [B, H, W, 2] normalised source coordinates for grid_sample(align_corners=False)
    valid: Tensor  # [B, H, W] bool: the warped sample is meaningful
    uv: Tensor  # [B, H, W, 2] source pixel coordinates (pixel-centre convention)


def pixels_to_grid(uv: Tensor, width: int, height: int) -> Tensor:
    """Pixel-centre coordinates to ``grid_sample`` coordinates for ``align_corners=False``."""
    scale = uv.new_tensor((2.0 / width, 2.0 / height))
    return (uv + 0.5) * scale - 1.0


def grid_to_pixels(grid: Tensor, width: int, height: int) -> Tensor:
    scale = grid.new_tensor((width / 2.0, height / 2.0))
    return (grid + 1.0) * scale - 0.5


def project_cameras(cameras: CameraModel | Sequence[CameraModel], points: Tensor) -> tuple[Tensor, Tensor]:
    """Project ``points [B, ..., 3]`` with one camera, or one camera per sample (any mix of models).

    Samples that share a camera are projected together. Returns ``uv [B, ..., 2]`` and
    ``valid [B, ...]`` (in the model's domain).
    """
    if isinstance(cameras, CameraModel):
        return cameras.project(points)
    if len(cameras) != points.shape[0]:
        raise ValueError(f"{len(cameras)} cameras for a batch of {points.shape[0]} samples")
    groups: dict[CameraModel, list[int]] = {}
    for i, cam in enumerate(cameras):
        groups.setdefault(cam, []).append(i)
    if len(groups) == 1:
        return cameras[0].project(points)
    uv = points.new_zeros(*points.shape[:-1], 2)
    valid = torch.zeros(points.shape[:-1], dtype=torch.bool, device=points.device)
    for cam, idx in groups.items():
        index = torch.as_tensor(idx, device=points.device)
        uv_g, valid_g = cam.project(points.index_select(0, index))
        uv = uv.index_copy(0, index, uv_g)
        valid = valid.index_copy(0, index, valid_g)
    return uv, valid


def _per_sample(cameras: CameraModel | Sequence[CameraModel], batch: int, attr: str, ref: Tensor) -> Tensor:
    if isinstance(cameras, CameraModel):
        return ref.new_tensor(float(getattr(cameras, attr)))
    return ref.new_tensor([float(getattr(c, attr)) for c in cameras]).reshape(batch, *([1] * (ref.dim() - 1)))


def warp_to_source(
    rays: Tensor,
    rays_valid: Tensor,
    distance: Tensor,
    T_target_to_source: Tensor,
    source_cameras: CameraModel | Sequence[CameraModel],
    source_mask: Tensor | None = None,
) -> Warp:
    """Where each target pixel lands in the source image.

    Args:
        rays: ``[B, H, W, 3]`` unit rays of the target camera (from :class:`~fisheyedepth.cameras.RayCache`).
        rays_valid: ``[B, H, W]`` pixels that have a ray.
        distance: ``[B, 1, H, W]`` or ``[B, H, W]`` Euclidean distance along each ray (not z).
        T_target_to_source: ``[B, 4, 4]`` target camera to source camera.
        source_cameras: the source camera, or one per sample.
        source_mask: optional ``[B, 1, Hs, Ws]`` (or ``[B, Hs, Ws]``) source body mask, 1/True = usable.

    ``valid`` is False where the pixel has no ray, the distance is not positive and finite, the point
    is outside the source model's domain (behind the camera), it falls outside the source image (all
    four bilinear neighbours must be inside, up to 1e-3 px of rounding), or its bilinear footprint
    touches the source's body mask.
    """
    if distance.dim() == 4:
        distance = distance[:, 0]
    finite = torch.isfinite(distance) & (distance > 0)
    usable = torch.where(finite, distance, torch.ones_like(distance))  # any value: masked out below
    points = transform_points(T_target_to_source, rays * usable[..., None])
    uv, valid = project_cameras(source_cameras, points)

    batch = rays.shape[0]
    width = _per_sample(source_cameras, batch, "width", uv[..., 0])
    height = _per_sample(source_cameras, batch, "height", uv[..., 0])
    u, v = uv[..., 0], uv[..., 1]
    inside = (
        (u >= -_SLACK_PX) & (u <= width - 1 + _SLACK_PX) & (v >= -_SLACK_PX) & (v <= height - 1 + _SLACK_PX)
    )
    valid = valid & inside & rays_valid & finite
    grid = torch.stack(((2 * u + 1) / width - 1, (2 * v + 1) / height - 1), dim=-1)
    grid = torch.where(valid[..., None], grid, torch.full_like(grid, _OUTSIDE))

    if source_mask is not None:
        if source_mask.dim() == 3:
            source_mask = source_mask[:, None]
        with torch.no_grad():
            usable = F.grid_sample(
                source_mask.to(grid.dtype),
                grid.detach(),
                mode="bilinear",
                padding_mode="zeros",
                align_corners=ALIGN_CORNERS,
            )[:, 0]
        valid = valid & (usable >= 1 - 1e-3)
    return Warp(grid, valid, uv)


def sample(image: Tensor, grid: Tensor, padding_mode: str = "border") -> Tensor:
    """Bilinear sample of ``image [B, C, Hs, Ws]`` at ``grid [B, H, W, 2]`` (the module's convention)."""
    return F.grid_sample(
        image, grid.to(image.dtype), mode="bilinear", padding_mode=padding_mode, align_corners=ALIGN_CORNERS
    )


def distance_to_depth(distance: Tensor, rays: Tensor) -> Tensor:
    """z-depth from Euclidean distance along unit rays: ``z = L * ray_z`` (``[B, 1, H, W]`` and
    ``[B, H, W, 3]``). Negative for points behind the image plane, which fisheye pixels beyond 90 degrees
    see; distance stays the quantity the network predicts."""
    return distance * rays[..., 2].unsqueeze(1).to(distance)
