"""A textured room with exact ground truth for the sweep-stereo tests: a box of walls with a random
texture over its volume, rendered by any camera model from any pose."""

from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F

from fisheyedepth.cameras.rays import compute_rays
from fisheyedepth.geometry.se3 import axis_angle_to_matrix, invert_pose, make_pose
from fisheyedepth.stereo import View

ROOM = torch.tensor([[-4.0, -1.5, -3.0], [4.0, 1.5, 5.0]], dtype=torch.float64)  # metres, x right, y down


@functools.cache
def texture_volume(seed: int = 0, cell: float = 0.04) -> torch.Tensor:
    """A random texture over the room's volume (fine noise over coarse blotches), sampled where rays hit."""
    g = torch.Generator().manual_seed(seed)
    size = [int(n) for n in ((ROOM[1] - ROOM[0]) / cell).long().flip(0) + 2]
    fine = torch.rand(1, 1, *size, generator=g)
    coarse = torch.rand(1, 1, *[n // 4 + 2 for n in size], generator=g)
    return 0.6 * fine + 0.4 * F.interpolate(coarse, size=size, mode="trilinear", align_corners=True)


def render(camera, T_cam_to_world: torch.Tensor, volume: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``[1, 1, H, W]`` image and ``[1, H, W]`` exact distance (0 without a ray) of ``camera`` inside the
    room: each ray's first hit of the box's walls."""
    rays, valid = compute_rays(camera, dtype=torch.float64)
    R, t = T_cam_to_world[:3, :3], T_cam_to_world[:3, 3]
    d = rays @ R.T
    hits = []
    for axis in range(3):
        component = torch.where(
            d[..., axis].abs() > 1e-12, d[..., axis], torch.full_like(d[..., axis], 1e-12)
        )
        for bound in ROOM[:, axis]:
            s = (bound - t[axis]) / component
            hits.append(torch.where(s > 0, s, torch.full_like(s, math.inf)))
    distance = torch.stack(hits).amin(0)
    where = ((t + d * distance[..., None]) - ROOM[0]) / (ROOM[1] - ROOM[0]) * 2 - 1
    value = F.grid_sample(volume, where[None, None].float(), mode="bilinear", align_corners=True)[0, 0, 0]
    image = torch.where(valid, value, torch.zeros_like(value))
    return image[None, None].float(), torch.where(valid, distance, torch.zeros_like(distance))[None].float()


def pose(yaw_deg: float = 0.0, t=(0.0, 0.0, 0.0)) -> torch.Tensor:
    R = axis_angle_to_matrix(torch.tensor([0.0, math.radians(yaw_deg), 0.0], dtype=torch.float64))
    return make_pose(R, torch.tensor(t, dtype=torch.float64))


def scores(
    distance: torch.Tensor, truth: torch.Tensor, among: torch.Tensor | None = None
) -> dict[str, float]:
    among = (truth > 0) if among is None else among & (truth > 0)
    kept = among & (distance > 0)
    ratio = distance[kept] / truth[kept]
    return {
        "abs_rel": float((ratio - 1).abs().mean()),
        "a1": float((torch.maximum(ratio, 1 / ratio) < 1.25).float().mean()),
        "coverage": float(kept.sum() / among.sum()),
    }


def pair(camera_a, camera_b, T_a, T_b, seed: int = 0):
    volume = texture_volume(seed)
    image_a, truth_a = render(camera_a, T_a, volume)
    image_b, _ = render(camera_b, T_b, volume)
    T_ab = (invert_pose(T_b) @ T_a).float()
    return View(image_a, camera_a, torch.eye(4)), View(image_b, camera_b, T_ab), truth_a
