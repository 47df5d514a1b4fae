"""The scene a synthetic dataset is rendered from: its world (a street or a room) drawn from the seed, the
rig's trajectory through it with the traffic around it, poses between two frames (motion blur), and the
trajectory frames that each split (train, val, test) takes, one :class:`Job` per frame."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..geometry import axis_angle_to_matrix, make_pose
from .indoor import make_indoor_trajectory, make_indoor_world
from .traffic import Traffic, make_traffic, no_traffic
from .world import SCENES, World, make_drive, make_world

SPLITS = ("train", "val", "test")
SEQUENCES = {split: f"2013_05_28_drive_{i:04d}_sync" for i, split in enumerate(SPLITS)}
GAP = 10  # trajectory frames left out between two splits, so no two splits share a segment
LANES = {"right": 1.75, "left": -1.75}  # the car's offset from the street's centreline, metres to its right


@dataclass(frozen=True)
class Job:
    """One frame to render: its sequence (split), its number there and its body pose."""

    sequence: str
    frame: int
    pose: np.ndarray
    index: int = 0  # the frame's place on the whole trajectory (traffic, exposure and noise follow it)


def split_frames(frames: int) -> dict[str, tuple[int, int]]:
    """Trajectory index ranges [start, stop) per split: 80 / 10 / 10 %, GAP frames apart."""
    if frames < 9:
        raise ValueError(f"need at least 9 frames (3 per split), got {frames}")
    n_val = n_test = max(3, round(0.1 * frames))
    n_train = frames - n_val - n_test
    starts = (0, n_train + GAP, n_train + n_val + 2 * GAP)
    return {s: (a, a + n) for s, a, n in zip(SPLITS, starts, (n_train, n_val, n_test), strict=True)}


def split_jobs(ranges: dict[str, tuple[int, int]], poses: np.ndarray) -> list[Job]:
    """Every frame of every split of ``ranges`` (:func:`split_frames`), numbered from 0 in its split."""
    return [Job(SEQUENCES[s], i - a, poses[i], i) for s, (a, b) in ranges.items() for i in range(a, b)]


def make_scene_world(scene: str, seed: int) -> World:
    """The world of ``scene`` ("street" or "indoor") drawn from ``seed``."""
    if scene not in SCENES:
        raise ValueError(f"scene must be one of {SCENES}, got {scene!r}")
    return make_world(seed) if scene == "street" else make_indoor_world(seed)


def make_scene_trajectory(world: World, frames: int, seed: int, lane: str = "right") -> np.ndarray:
    """``[frames, 4, 4]`` body poses through ``world``: the car in ``lane``, or the walk around the room."""
    return make_scene_motion(world, frames, seed, lane)[0]


def make_scene_motion(
    world: World, frames: int, seed: int, lane: str = "right", traffic: float = 0.0
) -> tuple[np.ndarray, Traffic]:
    """The body poses of :func:`make_scene_trajectory` and the traffic at density ``traffic`` (streets
    only; 0 leaves the world as it was)."""
    if world.scene == "indoor":
        if traffic:
            raise ValueError(f"traffic: {traffic} asked for, but the indoor scene has no streets (use 0)")
        return make_indoor_trajectory(world, frames, seed), no_traffic(frames)
    drive = make_drive(world, frames, seed, LANES[lane])
    return drive.poses, make_traffic(world, drive, traffic, seed)


def pose_at(poses: np.ndarray, time: float) -> np.ndarray:
    """The ``[4, 4]`` pose at a fractional trajectory frame: positions interpolated linearly, rotations
    along the shortest arc between the two frames around it (extrapolated past either end)."""
    k = int(np.clip(np.floor(time), 0, len(poses) - 2))
    u = time - k
    a, b = poses[k], poses[k + 1]
    step = a[:3, :3].T @ b[:3, :3]
    angle = float(np.arccos(np.clip((np.trace(step) - 1) / 2, -1.0, 1.0)))
    axis = np.array([step[2, 1] - step[1, 2], step[0, 2] - step[2, 0], step[1, 0] - step[0, 1]])
    axis *= 0.0 if angle < 1e-12 else angle / (2 * math.sin(angle))  # the rotation's log: axis x angle
    R = a[:3, :3] @ axis_angle_to_matrix(torch.from_numpy(u * axis)).numpy()
    return make_pose(R, (1 - u) * a[:3, 3] + u * b[:3, 3]).numpy()
