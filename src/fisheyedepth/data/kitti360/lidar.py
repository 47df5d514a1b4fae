"""LiDAR ground truth: Velodyne scans projected into each fisheye camera (for evaluation).

Unlike KITTI-360's official tools, points beyond 90 degrees of incidence are kept (they drop z <= 0),
each pixel keeps its nearest point, and both the Euclidean distance and z are stored. The projection is
cached on disk, one small file per frame, built on first use (nothing is projected when a dataset is
built, nothing is held in memory). An optional occlusion filter, applied when a frame is read, drops
points that lie well behind a nearer point in their neighbourhood (the scanner sees around foreground
edges that the camera cannot); the reference implementation has none.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import zipfile
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ...cameras import CameraModel
from ...files import atomic_write_bytes, file_key
from .files import read_velodyne

log = logging.getLogger(__name__)

OCCLUSION = 0.1  # the project's default: a point 10 % behind the nearest within 3 pixels is hidden
CACHE_VERSION = 2  # bump when the projection changes, so old cache files are never read as new


def occlusion_filter(distance: Tensor, ratio: float, radius: int = 3) -> Tensor:
    """Boolean ``[..., H, W]``: the points (``distance > 0``) farther than ``(1 + ratio)`` times the
    nearest point within ``radius`` pixels, which the scanner saw around an edge the camera cannot."""
    inf = torch.where(distance > 0, distance, torch.full_like(distance, float("inf")))
    flat = inf.reshape(-1, 1, *distance.shape[-2:])
    near = -F.max_pool2d(-flat, 2 * radius + 1, 1, radius).reshape(distance.shape)
    return (distance > 0) & (distance > (1 + ratio) * near)


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
        hidden = occlusion_filter(d_img, occlusion)
        d_img, z_img = d_img.masked_fill(hidden, 0), z_img.masked_fill(hidden, 0)
    return d_img.float().numpy(), z_img.float().numpy()


def _digest(*parts: bytes | str) -> str:
    h = hashlib.sha1()
    for part in parts:
        h.update(part.encode() if isinstance(part, str) else part)
        h.update(b"|")
    return h.hexdigest()[:16]


class LidarGroundTruth:
    """Projected LiDAR per frame, built lazily and cached in ``cache_dir`` one file per frame, keyed by
    the calibration (the camera model at its size and the Velodyne-to-camera transform) and the scan
    (its path, size and modification time): a new calibration or a replaced scan is projected again,
    never served stale (unless a replacement keeps the size and the modification time, as ``cp -p``
    does: delete the cache then). Entries of old calibrations or scans are not pruned.
    ``occlusion``: the filter's ratio applied when reading (None: every point)."""

    def __init__(self, layout, cache_dir: str | os.PathLike, occlusion: float | None = OCCLUSION):
        self.layout, self.cache_dir, self.occlusion = layout, Path(cache_dir), occlusion
        self._calibration: dict[tuple[str, CameraModel], tuple[str, np.ndarray]] = {}
        self._unwritable = False

    @property
    def source(self) -> str:
        """What a sample's ``distance_source`` says of this ground truth: "lidar" (every projected point)
        or "lidar_filtered" (occlusion-filtered), so a protocol can refuse what it must not score."""
        return "lidar" if self.occlusion is None else "lidar_filtered"

    def calibration_key(self, camera_name: str, camera: CameraModel) -> tuple[str, np.ndarray]:
        """``(key, T_velo_to_cam)`` of one camera at one size (one small entry per camera and size)."""
        if (camera_name, camera) not in self._calibration:
            T = self.layout.velo_to_camera(camera_name)
            model = json.dumps(camera.to_dict(), sort_keys=True)
            key = _digest(f"v{CACHE_VERSION}", model, np.ascontiguousarray(T, np.float64).tobytes())
            self._calibration[(camera_name, camera)] = (key, T)
        return self._calibration[(camera_name, camera)]

    def path(self, sequence: str, camera_name: str, camera: CameraModel, scan: Path) -> Path:
        """The cache file of one scan seen by one calibrated camera."""
        calibration, _ = self.calibration_key(camera_name, camera)
        folder = f"{camera_name}_{camera.width}x{camera.height}_{calibration}"
        return self.cache_dir / "lidar" / sequence / folder / f"{scan.stem}_{file_key(scan)}.npz"

    def project(self, camera_name: str, camera: CameraModel, scan: Path) -> tuple[np.ndarray, ...]:
        """``(pixel index, distance, z)`` of the nearest point of each pixel hit, unfiltered."""
        _, T = self.calibration_key(camera_name, camera)
        d, z = project_points(read_velodyne(scan), T, camera, occlusion=None)
        idx = np.flatnonzero(d > 0).astype(np.int32)
        return idx, d.flat[idx], z.flat[idx]

    def _cached(self, path: Path) -> tuple[np.ndarray, ...] | None:
        if not path.is_file():
            return None
        try:
            with np.load(path) as data:
                return data["index"], data["distance"], data["z"]
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
            log.warning("%s: unreadable LiDAR cache (%s); projecting the scan again", path, exc)
            return None

    def _store(self, path: Path, entry: tuple[np.ndarray, ...]) -> None:
        """Write one projection; concurrent workers may both write it, none reads half a file. A cache
        that cannot be written (read-only, full) is reported once and the projection used uncached."""
        if self._unwritable:
            return
        buffer = io.BytesIO()
        np.savez(buffer, index=entry[0], distance=entry[1], z=entry[2])
        try:
            atomic_write_bytes(path, buffer.getvalue())
        except OSError as exc:
            self._unwritable = True
            log.warning(
                "%s: cannot cache LiDAR projections (%s); projecting every scan on each read", path, exc
            )

    def __call__(
        self, sequence: str, camera_name: str, camera: CameraModel, frame
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """``(distance, z)`` images for ``camera`` (any size), or None when the frame has no scan."""
        scan = self.layout.lidar(sequence, frame)
        if not scan.is_file():
            return None
        path = self.path(sequence, camera_name, camera, scan)
        entry = self._cached(path)
        if entry is None:
            entry = self.project(camera_name, camera, scan)
            self._store(path, entry)
        idx, d, z = entry
        d_img = np.zeros(camera.height * camera.width, np.float32)
        z_img = np.zeros_like(d_img)
        d_img[idx], z_img[idx] = d, z
        d_img, z_img = d_img.reshape(camera.height, camera.width), z_img.reshape(camera.height, camera.width)
        if self.occlusion is not None:
            hidden = occlusion_filter(torch.from_numpy(d_img), self.occlusion).numpy()
            d_img[hidden], z_img[hidden] = 0, 0
        return d_img, z_img
