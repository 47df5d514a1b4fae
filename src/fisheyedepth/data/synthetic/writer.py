"""Writing a synthetic dataset in the KITTI-360 layout (see docs/data-format.md).

The dataset is written into a hidden temporary folder beside ``out`` and renamed into place only when
complete, so an interrupted run never looks like a dataset; ``synthetic.json`` is written last.
"""

from __future__ import annotations

import json
import os
import shutil
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from ... import __version__
from ...cameras import CameraModel, KannalaBrandtCamera, MeiCamera
from .raycast import scene_tensors
from .render import CameraRenderer, LidarRenderer
from .rig import RIGS, Rig, make_rig
from .world import make_trajectory, make_world

SPLITS = ("train", "val", "test")
SEQUENCES = {split: f"2013_05_28_drive_{i:04d}_sync" for i, split in enumerate(SPLITS)}
GAP = 10  # trajectory frames left out between two splits, so no two splits share a segment


@dataclass(frozen=True)
class Job:
    sequence: str
    frame: int
    pose: np.ndarray


def opencv_yaml(name: str, camera: CameraModel) -> str:
    """A calibration file in KITTI-360's (CamOdoCal's) OpenCV YAML layout."""
    head = (
        f"%YAML:1.0\n---\nmodel_type: {{}}\ncamera_name: {name}\nimage_width: {camera.width}\n"
        f"image_height: {camera.height}\n"
    )
    if isinstance(camera, MeiCamera):
        c = camera
        return head.format("MEI") + (
            f"mirror_parameters:\n   xi: {c.xi!r}\n"
            f"distortion_parameters:\n   k1: {c.k1!r}\n   k2: {c.k2!r}\n   p1: {c.p1!r}\n   p2: {c.p2!r}\n"
            f"projection_parameters:\n   gamma1: {c.gamma1!r}\n   gamma2: {c.gamma2!r}\n   u0: {c.u0!r}\n"
            f"   v0: {c.v0!r}\n"
        )
    if isinstance(camera, KannalaBrandtCamera):
        c = camera
        return head.format("KANNALA_BRANDT") + (
            f"projection_parameters:\n   k2: {c.k1!r}\n   k3: {c.k2!r}\n   k4: {c.k3!r}\n   k5: {c.k4!r}\n"
            f"   mu: {c.fx!r}\n   mv: {c.fy!r}\n   u0: {c.cx!r}\n   v0: {c.cy!r}\n"
        )
    raise TypeError(f"no OpenCV YAML layout for {type(camera).__name__}")


def _row(T: np.ndarray) -> str:
    return " ".join(f"{v:.10f}" for v in T[:3].reshape(-1))


def split_frames(frames: int) -> dict[str, tuple[int, int]]:
    """Trajectory index ranges [start, stop) per split: 80 / 10 / 10 %, GAP frames apart."""
    if frames < 9:
        raise ValueError(f"need at least 9 frames (3 per split), got {frames}")
    n_val = n_test = max(3, round(0.1 * frames))
    n_train = frames - n_val - n_test
    starts = (0, n_train + GAP, n_train + n_val + 2 * GAP)
    return {s: (a, a + n) for s, a, n in zip(SPLITS, starts, (n_train, n_val, n_test), strict=True)}


class _Worker:
    """Renders and writes whole frames; built once per process."""

    def __init__(self, root: Path, seed: int, rig_name: str, size: int, supersample: int, lidar: bool):
        self.root, self.world, self.rig = root, make_world(seed), make_rig(rig_name, size)
        self.scene = scene_tensors(self.world)
        self.cameras = {
            name: CameraRenderer(cam, self.rig.cam_to_pose[name], supersample)
            for name, cam in self.rig.cameras.items()
        }
        self.lidar = LidarRenderer(self.rig.velo_to_pose) if lidar else None

    def __call__(self, job: Job) -> None:
        stem = f"{job.frame:010d}"
        for name, renderer in self.cameras.items():
            frame = renderer.render(self.scene, self.world, job.pose)
            image = self.root / "data_2d_raw" / job.sequence / name / "data_rgb" / f"{stem}.png"
            if not cv2.imwrite(str(image), frame.image[..., ::-1]):
                raise OSError(f"could not write {image}")
            np.save(self.root / "data_2d_distance" / job.sequence / name / f"{stem}.npy", frame.distance)
        if self.lidar is not None:
            points = self.lidar.render(self.scene, self.world, job.pose)
            points.tofile(
                self.root / "data_3d_raw" / job.sequence / "velodyne_points" / "data" / f"{stem}.bin"
            )


_WORKER: _Worker | None = None


def _init_worker(*args) -> None:
    global _WORKER
    torch.set_num_threads(1)
    _WORKER = _Worker(*args)


def _run_job(job: Job) -> None:
    assert _WORKER is not None
    _WORKER(job)


def _write_layout(
    root: Path, rig: Rig, body_masks: dict[str, np.ndarray], jobs: list[Job], lidar: bool
) -> None:
    calib = root / "calibration"
    calib.mkdir(parents=True)
    for name, cam in rig.written.items():
        (calib / f"{name}.yaml").write_text(opencv_yaml(name, cam))
        cv2.imwrite(str(calib / f"body_mask_{name}.png"), np.where(body_masks[name], 255, 0).astype(np.uint8))
    (calib / "calib_cam_to_pose.txt").write_text(
        "".join(f"{k}: {_row(T)}\n" for k, T in rig.cam_to_pose.items())
    )
    (calib / "calib_cam_to_velo.txt").write_text(_row(rig.cam0_to_velo) + "\n")
    for seq in sorted({j.sequence for j in jobs}):
        for name in rig.cameras:
            (root / "data_2d_raw" / seq / name / "data_rgb").mkdir(parents=True)
            (root / "data_2d_distance" / seq / name).mkdir(parents=True)
        if lidar:
            (root / "data_3d_raw" / seq / "velodyne_points" / "data").mkdir(parents=True)
        (root / "data_poses" / seq).mkdir(parents=True)
        rows = [f"{j.frame} {_row(j.pose)}\n" for j in jobs if j.sequence == seq]
        (root / "data_poses" / seq / "poses.txt").write_text("".join(rows))
    (root / "splits").mkdir()
    for split, seq in SEQUENCES.items():
        lines = [f"{seq} {j.frame}\n" for j in jobs if j.sequence == seq]
        (root / "splits" / f"{split}.txt").write_text("".join(lines))


def generate(
    out: str | os.PathLike,
    rig: str = "kitti360",
    frames: int = 200,
    size: int = 256,
    seed: int = 0,
    supersample: int = 2,
    workers: int = 0,
    lidar: bool = True,
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Render ``frames`` frames of every camera of ``rig`` (plus LiDAR) into ``out``. Returns ``out``."""
    out = Path(out)
    if rig not in RIGS:
        raise ValueError(f"unknown rig {rig!r}; one of {RIGS}")
    if size < 16 or size % 8:
        raise ValueError(f"size must be a multiple of 8 and at least 16, got {size}")
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not overwrite:
        raise FileExistsError(f"{out} exists and is not empty; pass --overwrite to replace it")
    ranges = split_frames(frames)
    world = make_world(seed)
    poses = make_trajectory(world, ranges["test"][1], seed)
    jobs = [Job(SEQUENCES[s], i - a, poses[i]) for s, (a, b) in ranges.items() for i in range(a, b)]

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        worker = _Worker(tmp, seed, rig, size, supersample, lidar)
        masks = {name: r.body_mask for name, r in worker.cameras.items()}
        _write_layout(tmp, worker.rig, masks, jobs, lidar)
        bar = tqdm(total=len(jobs), desc=f"rendering {rig} {size}px", unit="frame", disable=not progress)
        if workers > 1:
            ctx = get_context("spawn")
            args = (tmp, seed, rig, size, supersample, lidar)
            with ProcessPoolExecutor(
                workers, mp_context=ctx, initializer=_init_worker, initargs=args
            ) as pool:
                for future in as_completed([pool.submit(_run_job, job) for job in jobs]):
                    future.result()
                    bar.update()
        else:
            for job in jobs:
                worker(job)
                bar.update()
        bar.close()
        meta = {
            "generator": f"fisheyedepth {__version__}",
            "seed": seed,
            "rig": rig,
            "size": size,
            "supersample": supersample,
            "frames": frames,
            "cameras": {name: cam.to_dict() for name, cam in worker.rig.cameras.items()},
            "sequences": {
                split: {"name": SEQUENCES[split], "trajectory_frames": list(ranges[split])}
                for split in SPLITS
            },
            "world": {
                "pitch": world.pitch,
                "sun": world.sun.tolist(),
                "boxes": len(world.boxes),
                "cylinders": len(world.cylinders),
                "spheres": len(world.spheres),
            },
            "lidar": lidar,
        }
        (tmp / "synthetic.json").write_text(json.dumps(meta, indent=2) + "\n")
        if out.exists():
            old = out.parent / f".{out.name}.old-{os.getpid()}"
            out.rename(old)
            tmp.rename(out)
            shutil.rmtree(old)
        else:
            tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def is_complete(root: str | os.PathLike) -> bool:
    """A finished dataset has its ``synthetic.json`` (written last, before the atomic rename)."""
    return (Path(root) / "synthetic.json").is_file()
