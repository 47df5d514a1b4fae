"""Rendering one camera (supersampled colour, exact per-pixel distance, body mask) or one LiDAR scan."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..cameras import CameraModel, compute_rays
from . import world as W
from .raycast import Hit, Movers, SceneTensors, box_intersect, cast, tile_grid, untile_grid
from .rig import EGO_BODY
from .shading import shade

MAX_RANGE = 120.0


def _tile_size(h: int, w: int, preferred: int = 8) -> int:
    t = preferred
    while t > 1 and (h % t or w % t):
        t //= 2
    return t


class _Rays:
    """Rays of one sensor in its own frame, tiled, with the ego body's hits precomputed (it never moves;
    ``ego=False``: a rig without a vehicle body, the indoor scene's)."""

    def __init__(
        self, grid: Tensor, valid: Tensor, sensor_to_pose: np.ndarray, tile: tuple[int, int], ego: bool = True
    ):
        self.H, self.W = grid.shape[:2]
        self.th, self.tw = tile
        self.rays = tile_grid(grid, *tile)  # [T, K, 3] sensor frame
        self.valid = tile_grid(valid[..., None], *tile).reshape(-1)
        self.sensor_to_pose = torch.as_tensor(sensor_to_pose, dtype=torch.float32)
        R, t = self.sensor_to_pose[:3, :3], self.sensor_to_pose[:3, 3]
        d_body = self.rays.reshape(-1, 3) @ R.T
        self.t_ego = torch.full((d_body.shape[0],), float("inf"))
        self.n_ego_body = torch.zeros_like(d_body)
        rows = torch.arange(d_body.shape[0])
        for lo, hi in EGO_BODY if ego else ():
            t_box, axis = box_intersect(
                t, d_body, torch.as_tensor(lo, dtype=torch.float32), torch.as_tensor(hi, dtype=torch.float32)
            )
            nearer = t_box < self.t_ego
            n = torch.zeros_like(d_body)
            n[rows, axis] = -torch.sign(d_body[rows, axis])
            self.t_ego = torch.where(nearer, t_box, self.t_ego)
            self.n_ego_body = torch.where(nearer[:, None], n, self.n_ego_body)

    def untile(self, values: Tensor) -> Tensor:
        return untile_grid(values, self.H, self.W, self.th, self.tw)

    def cast(
        self, scene: SceneTensors, pose: np.ndarray, movers: Movers | None = None
    ) -> tuple[Tensor, Tensor, Hit]:
        """World-frame origin, ray directions [R, 3] and nearest hits (ego body included) at ``pose``,
        with the traffic's ``movers`` of that instant."""
        T = torch.as_tensor(pose, dtype=torch.float32) @ self.sensor_to_pose
        origin = T[:3, 3]
        dirs = self.rays @ T[:3, :3].T
        hit = cast(scene, origin, dirs, MAX_RANGE, movers)
        ego = self.t_ego < hit.t
        R_body = torch.as_tensor(pose[:3, :3], dtype=torch.float32)
        agent = (
            hit.agent if hit.agent is None else torch.where(ego, torch.full_like(hit.agent, -1), hit.agent)
        )
        hit = Hit(
            torch.where(ego, self.t_ego, hit.t),
            torch.where(ego, torch.full_like(hit.material, W.EGO), hit.material),
            torch.where(ego[:, None], self.n_ego_body @ R_body.T, hit.normal),
            hit.tint,
            hit.offset,
            agent,
        )
        return origin, dirs.reshape(-1, 3), hit


class CameraFrame(NamedTuple):
    image: np.ndarray  # [H, W, 3] uint8 RGB
    distance: np.ndarray  # [H, W] float32 metres along the ray; 0 = sky or no ray
    moving: np.ndarray | None = None  # [H, W] bool: a moving agent (with traffic only)


def quantise(colour: Tensor) -> np.ndarray:
    """``[H, W, 3]`` colour in [0, 1] as 8-bit RGB."""
    return (colour.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()


class CameraRenderer:
    """Renders ``camera`` mounted at ``cam_to_pose`` with ``supersample`` x ``supersample`` antialiasing
    (``ego``: the ego vehicle's body is in view)."""

    def __init__(self, camera: CameraModel, cam_to_pose: np.ndarray, supersample: int = 2, ego: bool = True):
        self.camera, self.ss = camera, supersample
        fine = camera.resize(camera.width * supersample, camera.height * supersample)
        self.fine = self._rays(fine, cam_to_pose, ego)
        self.centre = self._rays(camera, cam_to_pose, ego)
        self.pixel_angle = 1.0 / min(
            camera.paraxial_focal()
        )  # radians per output pixel, for texture filtering
        ego = self.centre.untile(torch.isfinite(self.centre.t_ego))
        self.body_mask = (~ego).numpy()  # True = usable (not the ego body; pixels without a ray included)

    @staticmethod
    def _rays(camera: CameraModel, cam_to_pose, ego: bool = True) -> _Rays:
        rays, valid = compute_rays(camera, dtype=torch.float32)
        tile = _tile_size(camera.height, camera.width)
        return _Rays(rays, valid, cam_to_pose, (tile, tile), ego)

    def colour(
        self, scene: SceneTensors, world: W.World, pose: np.ndarray, movers: Movers | None = None
    ) -> Tensor:
        """``[H, W, 3]`` colour (the supersamples' mean, not yet clamped) at ``pose``."""
        origin, dirs, hit = self.fine.cast(scene, pose, movers)
        colour = shade(world, hit, origin, dirs, self.pixel_angle)
        colour = torch.where(self.fine.valid[:, None], colour, torch.zeros_like(colour))
        img = self.fine.untile(colour)  # [sH, sW, 3]
        s = self.ss
        return img.reshape(self.camera.height, s, self.camera.width, s, 3).mean(dim=(1, 3))

    def truth(
        self,
        scene: SceneTensors,
        pose: np.ndarray,
        movers: Movers | None = None,
        moving: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The exact distance ``[H, W]`` at ``pose`` (0: sky, no ray) and, with ``movers``, the pixels
        that see an agent whose entry of ``moving [A]`` (bool) is set."""
        _, _, centre = self.centre.cast(scene, pose, movers)
        keep = self.centre.valid & torch.isfinite(centre.t) & (centre.material != W.SKY)
        distance = self.centre.untile(torch.where(keep, centre.t, torch.zeros_like(centre.t)))
        mask = None
        if centre.agent is not None:
            flags = torch.as_tensor(np.asarray(moving, dtype=bool)) if moving is not None else None
            hit = centre.agent >= 0
            if flags is not None and flags.numel():
                hit = hit & flags[centre.agent.clamp_min(0)]
            mask = self.centre.untile((hit & keep)[:, None])[..., 0].numpy()
        return distance.numpy().astype(np.float32), mask

    def render(
        self,
        scene: SceneTensors,
        world: W.World,
        pose: np.ndarray,
        movers: Movers | None = None,
        moving: np.ndarray | None = None,
    ) -> CameraFrame:
        image = quantise(self.colour(scene, world, pose, movers))
        return CameraFrame(image, *self.truth(scene, pose, movers, moving))


def hdl64_directions(columns: int = 900) -> tuple[Tensor, Tensor]:
    """Unit rays ``[64, columns, 3]`` of a 64-beam spinning LiDAR in the Velodyne frame (x forward, y left,
    z up): elevations from +2 to -24.9 degrees (HDL-64E), azimuths over the full turn."""
    elevation = torch.deg2rad(torch.linspace(2.0, -24.9, 64))
    azimuth = torch.linspace(0, 2 * math.pi, columns + 1)[:-1]
    e, a = torch.meshgrid(elevation, azimuth, indexing="ij")
    grid = torch.stack((torch.cos(e) * torch.cos(a), torch.cos(e) * torch.sin(a), torch.sin(e)), -1)
    return grid, torch.ones(grid.shape[:2], dtype=torch.bool)


class LidarRenderer:
    def __init__(self, velo_to_pose: np.ndarray, columns: int = 900, ego: bool = True):
        grid, valid = hdl64_directions(columns)
        tw = 30 if columns % 30 == 0 else _tile_size(1, columns, 32)
        self.rays = _Rays(grid, valid, velo_to_pose, (8, tw), ego)
        self.pixel_angle = 2 * math.pi / columns

    def render(
        self, scene: SceneTensors, world: W.World, pose: np.ndarray, movers: Movers | None = None
    ) -> np.ndarray:
        """``[N, 4]`` float32 points (x, y, z in the Velodyne frame, reflectance in [0, 1])."""
        origin, dirs, hit = self.rays.cast(scene, pose, movers)
        keep = torch.isfinite(hit.t) & (hit.material != W.EGO) & (hit.material != W.SKY)
        local = self.rays.rays.reshape(-1, 3)[keep] * hit.t[keep, None]
        kept = Hit(*(x if x is None else x[keep] for x in hit))
        colour = shade(world, kept, origin, dirs[keep], self.pixel_angle)
        reflectance = colour.mean(-1, keepdim=True)
        return torch.cat((local, reflectance), -1).numpy().astype(np.float32)
