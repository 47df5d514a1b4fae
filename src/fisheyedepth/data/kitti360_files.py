"""Readers for KITTI-360's text and binary files (poses, extrinsics, Velodyne scans).

Every malformed line raises a ``ValueError`` naming the file and the line.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def _numbers(path: Path, lineno: int, fields: list[str], count: int) -> np.ndarray:
    try:
        values = np.array([float(x) for x in fields], dtype=np.float64)
    except ValueError:
        raise ValueError(f"{path}:{lineno}: expected {count} numbers, got {' '.join(fields)!r}") from None
    if values.size != count or not np.isfinite(values).all():
        raise ValueError(f"{path}:{lineno}: expected {count} finite numbers, got {values.size}")
    return values


def _pose(values: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3] = values.reshape(3, 4)
    return T


def read_poses(path: str | os.PathLike) -> dict[int, np.ndarray]:
    """``data_poses/<seq>/poses.txt``: ``frame_index`` + 12 numbers (pose frame -> world) per line."""
    path = Path(path)
    poses: dict[int, np.ndarray] = {}
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        values = _numbers(path, lineno, fields, 13)
        if values[0] != int(values[0]) or values[0] < 0:
            raise ValueError(
                f"{path}:{lineno}: frame index must be a non-negative integer, got {fields[0]!r}"
            )
        poses[int(values[0])] = _pose(values[1:])
    return poses


def read_cam_to_pose(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """``calibration/calib_cam_to_pose.txt``: ``image_0X: 12 numbers`` (camera -> pose frame)."""
    path = Path(path)
    out = {}
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        name, sep, rest = line.partition(":")
        if not sep:
            raise ValueError(f"{path}:{lineno}: expected 'image_0X: 12 numbers'")
        out[name.strip()] = _pose(_numbers(path, lineno, rest.split(), 12))
    return out


def read_cam_to_velo(path: str | os.PathLike) -> np.ndarray:
    """``calibration/calib_cam_to_velo.txt``: 12 numbers, camera 0 -> Velodyne."""
    path = Path(path)
    return _pose(_numbers(path, 1, path.read_text().split(), 12))


def read_velodyne(path: str | os.PathLike) -> np.ndarray:
    """``velodyne_points/data/%010d.bin``: float32 ``[N, 4]`` (x, y, z, reflectance), Velodyne frame."""
    path = Path(path)
    raw = np.fromfile(path, dtype=np.float32)
    if raw.size % 4:
        raise ValueError(f"{path}: size {raw.size * 4} bytes is not a whole number of float32 x 4 points")
    return raw.reshape(-1, 4)
