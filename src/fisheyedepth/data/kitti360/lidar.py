"""LiDAR ground truth: Velodyne scans projected into each fisheye camera (for evaluation).

Unlike KITTI-360's official tools, points beyond 90 degrees of incidence are kept (they drop z <= 0),
each pixel keeps its nearest point, and both the Euclidean distance and z are stored. An optional
occlusion filter drops points that lie well behind a nearer point in their neighbourhood (the scanner
sees around foreground edges that the camera cannot). Results are cached on disk once per
(sequence, camera, image size).
"""

from __future__ import annotations

import io
import logging
import os
import zipfile
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ...cameras import CameraModel
from ...utils import atomic_write_bytes
from .files import read_velodyne

log = logging.getLogger(__name__)


def project_points(
    points: np.ndarray, T_velo_to_cam: np.ndarray, camera: CameraModel, occlusion: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Sparse ``(distance, z)`` images ``[H, W]`` (0 = no point) from Velodyne points ``[N, >=3]``.

    ``occlusion``: drop a point whose distance exceeds ``(1 + occlusion)`` times the nearest distance
    within 3 pixels (None: no filtering).
    """
    X = points[:, :3].astype(np.float64) @ T_velo_to_cam[:3, :3].T + T_velo_to_cam[:3, 3]
    uv, ok = camera.project(torch.from_numpy(X))
    px = torch.round(uv).long()
    inside = ok & (px[:, 0] >= 0) & (px[:, 0] < camera.width) & (px[:, 1] >= 0) & (px[:, 1] < camera.height)
    dist = torch.from_numpy(np.linalg.norm(X, axis=1))[inside]
    z = torch.from_numpy(X[:, 2])[inside]
    index = px[inside, 1] * camera.width + px[inside, 0]
    best = torch.full((camera.height * camera.width,), float("inf"), dtype=torch.float64)
    best = best.scatter_reduce(0, index, dist, reduce="amin")
    winner = dist == best[index]  # the nearest point of each pixel
    z_img = torch.zeros_like(best)
    z_img[index[winner]] = z[winner]
    d_img = torch.where(torch.isfinite(best), best, torch.zeros_like(best)).reshape(
        camera.height, camera.width
    )
    z_img = z_img.reshape(camera.height, camera.width)
    if occlusion is not None:
        inf = torch.where(d_img > 0, d_img, torch.full_like(d_img, float("inf")))
        near = -F.max_pool2d(-inf[None, None], 7, 1, 3)[0, 0]
        hidden = (d_img > 0) & (d_img > (1 + occlusion) * near)
        d_img, z_img = d_img.masked_fill(hidden, 0), z_img.masked_fill(hidden, 0)
    return d_img.float().numpy(), z_img.float().numpy()


class LidarGroundTruth:
    """Projected LiDAR per frame, computed for a whole sequence on first use and cached to ``cache_dir``."""

    def __init__(self, layout, cache_dir: str | os.PathLike, occlusion: float | None = 0.1):
        self.layout, self.cache_dir, self.occlusion = layout, Path(cache_dir), occlusion
        self._loaded: dict[tuple, dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}

    def _path(self, sequence: str, camera_name: str, camera: CameraModel) -> Path:
        occ = "none" if self.occlusion is None else f"{self.occlusion:g}"
        return (
            self.cache_dir / "lidar" / sequence / f"{camera_name}_{camera.width}x{camera.height}_occ{occ}.npz"
        )

    def _build(self, sequence: str, camera_name: str, camera: CameraModel, path: Path) -> None:
        T = self.layout.velo_to_camera(camera_name)
        arrays = {}
        for frame in self.layout.frames(sequence, camera_name):
            scan = self.layout.lidar(sequence, frame)
            if not scan.is_file():
                continue
            d, z = project_points(read_velodyne(scan), T, camera, self.occlusion)
            idx = np.flatnonzero(d > 0).astype(np.int32)
            arrays[f"i{frame.key}"], arrays[f"d{frame.key}"], arrays[f"z{frame.key}"] = (
                idx,
                d.flat[idx],
                z.flat[idx],
            )
        buffer = io.BytesIO()
        np.savez_compressed(buffer, **arrays)
        atomic_write_bytes(path, buffer.getvalue())  # concurrent workers may both build, none sees half
        log.info("LiDAR ground truth for %s/%s cached in %s", sequence, camera_name, path)

    def __call__(
        self, sequence: str, camera_name: str, camera: CameraModel, frame
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """``(distance, z)`` images for ``camera`` (any size), or None when the frame has no scan."""
        key = (sequence, camera_name, camera)
        if key not in self._loaded:
            path = self._path(sequence, camera_name, camera)
            if not path.is_file():
                self._build(sequence, camera_name, camera, path)
            try:
                with np.load(path) as data:
                    keys = {int(k[1:]) for k in data.files if k.startswith("i")}
                    self._loaded[key] = {k: (data[f"i{k}"], data[f"d{k}"], data[f"z{k}"]) for k in keys}
            except (OSError, ValueError, zipfile.BadZipFile) as exc:
                raise ValueError(f"{path}: corrupt LiDAR cache ({exc}); delete it to rebuild") from None
        entry = self._loaded[key].get(frame.key)
        if entry is None:
            return None
        idx, d, z = entry
        d_img = np.zeros(camera.height * camera.width, np.float32)
        z_img = np.zeros_like(d_img)
        d_img[idx], z_img[idx] = d, z
        return d_img.reshape(camera.height, camera.width), z_img.reshape(camera.height, camera.width)
