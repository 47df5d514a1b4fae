"""Samples from a dataset in the KITTI-360 layout (real KITTI-360 or the synthetic world).

``load_sample(root, sequence, frame, camera)`` builds one training sample (see ``fisheyedepth.data.batch``):
the target frame, its neighbours in ``poses.txt`` order (KITTI-360's frame indices are sparse, so
neighbours are neighbouring pose rows), real-scale relative poses, the body mask and, when present, the
ground-truth distance.
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from ..cameras import load_camera
from ..geometry import relative_pose
from .kitti360_files import read_cam_to_pose, read_poses


@lru_cache(maxsize=64)
def _poses(path: str) -> tuple[list[int], dict[int, np.ndarray]]:
    poses = read_poses(path)
    return sorted(poses), poses


@lru_cache(maxsize=16)
def _extrinsics(path: str) -> dict[str, np.ndarray]:
    return read_cam_to_pose(path)


def read_image(path: Path, size: tuple[int, int] | None = None) -> torch.Tensor:
    """RGB ``[3, H, W]`` float in [0, 1]; a clear error naming the file when it is missing or unreadable."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: image not found")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError(f"{path}: not a readable image")
    if size is not None and bgr.shape[1::-1] != size:
        bgr = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
    return torch.from_numpy(np.ascontiguousarray(bgr[..., ::-1])).permute(2, 0, 1).float() / 255.0


def load_sample(
    root: str | os.PathLike,
    sequence: str,
    frame: int,
    camera: str,
    offsets: tuple[int, ...] = (-1, 1),
    size: tuple[int, int] | None = None,
) -> dict[str, Any]:
    """One sample; ``size=(width, height)`` resizes images and resizes the camera model to match."""
    root = Path(root)
    cam = load_camera(root / "calibration" / f"{camera}.yaml")
    image_size = (cam.width, cam.height)
    if size is not None:
        cam = cam.resize(*size)
    order, poses = _poses(str(root / "data_poses" / sequence / "poses.txt"))
    if frame not in poses:
        raise KeyError(f"{root / 'data_poses' / sequence / 'poses.txt'}: no pose for frame {frame}")
    row = order.index(frame)
    E = torch.from_numpy(_extrinsics(str(root / "calibration" / "calib_cam_to_pose.txt"))[camera])
    images = root / "data_2d_raw" / sequence / camera / "data_rgb"
    out: dict[str, Any] = {
        "camera": cam,
        "image": read_image(images / f"{frame:010d}.png", size or image_size),
    }
    sources, rel = [], []
    for offset in offsets:
        if not 0 <= row + offset < len(order):
            raise IndexError(f"frame {frame} of {sequence} has no neighbour at offset {offset}")
        other = order[row + offset]
        sources.append(read_image(images / f"{other:010d}.png", size or image_size))
        rel.append(relative_pose(torch.from_numpy(poses[frame]), torch.from_numpy(poses[other]), E))
    out["sources"], out["poses"] = torch.stack(sources), torch.stack(rel)
    mask_path = root / "calibration" / f"body_mask_{camera}.png"
    mask = (
        np.ones(image_size[::-1], np.uint8) * 255
        if not mask_path.is_file()
        else cv2.imread(str(mask_path), 0)
    )
    if size is not None:
        mask = cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST)
    out["mask"] = torch.from_numpy((mask > 127).astype(np.float32))[None]
    gt = root / "data_2d_distance" / sequence / camera / f"{frame:010d}.npy"
    if gt.is_file():
        distance = np.load(gt)
        if size is not None:
            distance = cv2.resize(distance, size, interpolation=cv2.INTER_NEAREST)
        out["distance"] = torch.from_numpy(distance.astype(np.float32))[None]
    return out
