"""Readers for KITTI-360's text and binary files (poses, extrinsics, Velodyne scans).

Every malformed line raises a ``ValueError`` naming the file and the line: numbers that are missing or
not finite, a rotation that is not rigid (scaled, sheared or mirrored), a frame or camera given twice.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ...geometry import pose_from_3x4, rigid_problem


def _numbers(path: Path, lineno: int, fields: list[str], count: int) -> np.ndarray:
    try:
        values = np.array([float(x) for x in fields], dtype=np.float64)
    except ValueError:
        raise ValueError(f"{path}:{lineno}: expected {count} numbers, got {' '.join(fields)!r}") from None
    if values.size != count or not np.isfinite(values).all():
        raise ValueError(f"{path}:{lineno}: expected {count} finite numbers, got {values.size}")
    return values


def _rigid_pose(path: Path, lineno: int, values: np.ndarray, what: str) -> np.ndarray:
    """A 3x4 row-major pose whose rotation block must be orthonormal with det +1 (KITTI-360 writes its
    rotations to about 1e-9; :func:`~fisheyedepth.geometry.rigid_problem`)."""
    T = pose_from_3x4(values).numpy()
    problem = rigid_problem(T)
    if problem is not None:
        raise ValueError(f"{path}:{lineno}: {what}: {problem}")
    return T


def read_poses(path: str | os.PathLike) -> dict[int, np.ndarray]:
    """``data_poses/<seq>/poses.txt``: ``frame_index`` + 12 numbers (pose frame -> world) per line."""
    path = Path(path)
    poses: dict[int, np.ndarray] = {}
    lines: dict[int, int] = {}
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        values = _numbers(path, lineno, fields, 13)
        if values[0] != int(values[0]) or values[0] < 0:
            raise ValueError(
                f"{path}:{lineno}: frame index must be a non-negative integer, got {fields[0]!r}"
            )
        frame = int(values[0])
        if frame in lines:
            raise ValueError(f"{path}:{lineno}: frame {frame} already has a pose on line {lines[frame]}")
        lines[frame] = lineno
        poses[frame] = _rigid_pose(path, lineno, values[1:], f"frame {frame}")
    return poses


def read_cam_to_pose(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """``calibration/calib_cam_to_pose.txt``: ``image_0X: 12 numbers`` (camera -> pose frame)."""
    path = Path(path)
    out = {}
    lines: dict[str, int] = {}
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        name, sep, rest = line.partition(":")
        name = name.strip()
        if not sep or not name:
            raise ValueError(f"{path}:{lineno}: expected 'image_0X: 12 numbers'")
        if name in lines:
            raise ValueError(f"{path}:{lineno}: camera {name!r} already given on line {lines[name]}")
        lines[name] = lineno
        out[name] = _rigid_pose(path, lineno, _numbers(path, lineno, rest.split(), 12), f"camera {name!r}")
    return out


def read_cam_to_velo(path: str | os.PathLike) -> np.ndarray:
    """``calibration/calib_cam_to_velo.txt``: 12 numbers, camera 0 -> Velodyne."""
    path = Path(path)
    return _rigid_pose(path, 1, _numbers(path, 1, path.read_text().split(), 12), "camera 0 to Velodyne")


def read_velodyne(path: str | os.PathLike) -> np.ndarray:
    """``velodyne_points/data/%010d.bin``: float32 ``[N, 4]`` (x, y, z, reflectance), Velodyne frame."""
    path = Path(path)
    raw = np.fromfile(path, dtype=np.float32)
    if raw.size % 4:
        raise ValueError(f"{path}: size {raw.size * 4} bytes is not a whole number of float32 x 4 points")
    return raw.reshape(-1, 4)
