"""What a synthetic dataset holds on disk, in the KITTI-360 layout (docs/data-format.md): the calibration
(camera YAMLs, body masks, extrinsics), poses and split lists, each frame's image, distance map, mask of
moving pixels and LiDAR scan, and ``synthetic.json``, the parameters and world it was rendered with.

Every file is written through Python's file objects, whose failures carry ``ENOSPC`` and name the file
(``ndarray.tofile`` and ``cv2.imwrite`` report only a short write, or nothing)."""

from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np
import yaml

from .. import __version__
from ..cameras import CameraModel, opencv_yaml
from .rig import Rig
from .scene import SEQUENCES, SPLITS, Job
from .spec import WorldSpec
from .traffic import Traffic


def _row(T: np.ndarray) -> str:
    return " ".join(f"{v:.10f}" for v in T[:3].reshape(-1))


def _write(path: Path, data: bytes) -> None:
    """``path.write_bytes(data)``; a failure names the file (a full disk's ENOSPC arrives without it)."""
    try:
        path.write_bytes(data)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None


def _png(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"could not encode a {image.shape} {image.dtype} image as PNG")
    return data.tobytes()


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def calibration_text(camera: CameraModel, name: str) -> str:
    """A camera's ``calibration/<name>.yaml``: KITTI-360's OpenCV YAML for the models it has a layout for
    (Mei, Kannala-Brandt), the project's own YAML for the others (double sphere, Fisheye624); both are
    what ``load_camera`` reads back to the same camera."""
    try:
        return opencv_yaml(camera, name)
    except TypeError:
        return yaml.safe_dump(camera.to_dict(), sort_keys=False)


def write_layout(
    root: Path,
    rig: Rig,
    body_masks: dict[str, np.ndarray],
    jobs: list[Job],
    lidar: bool,
    moving: bool = False,
) -> None:
    """Everything but the frames: the calibration, the folders the frames go into, poses and splits."""
    calib = root / "calibration"
    calib.mkdir(parents=True)
    for name, cam in rig.written.items():
        (calib / f"{name}.yaml").write_text(calibration_text(cam, name))
        _write(calib / f"body_mask_{name}.png", _png(np.where(body_masks[name], 255, 0).astype(np.uint8)))
    (calib / "calib_cam_to_pose.txt").write_text(
        "".join(f"{k}: {_row(T)}\n" for k, T in rig.cam_to_pose.items())
    )
    (calib / "calib_cam_to_velo.txt").write_text(_row(rig.cam0_to_velo) + "\n")
    for seq in sorted({j.sequence for j in jobs}):
        for name in rig.cameras:
            (root / "data_2d_raw" / seq / name / "data_rgb").mkdir(parents=True)
            (root / "data_2d_distance" / seq / name).mkdir(parents=True)
            if moving:
                (root / "data_2d_moving" / seq / name).mkdir(parents=True)
        if lidar:
            (root / "data_3d_raw" / seq / "velodyne_points" / "data").mkdir(parents=True)
        (root / "data_poses" / seq).mkdir(parents=True)
        rows = [f"{j.frame} {_row(j.pose)}\n" for j in jobs if j.sequence == seq]
        (root / "data_poses" / seq / "poses.txt").write_text("".join(rows))
    (root / "splits").mkdir()
    for split, seq in SEQUENCES.items():
        lines = [f"{seq} {j.frame}\n" for j in jobs if j.sequence == seq]
        (root / "splits" / f"{split}.txt").write_text("".join(lines))


def write_camera_frame(
    root: Path, job: Job, camera: str, rgb: np.ndarray, distance: np.ndarray, moving: np.ndarray | None
) -> None:
    """One camera's files of ``job``: the ``[H, W, 3]`` uint8 RGB image, the distance map and, with
    traffic, the ``[H, W]`` mask of pixels that see a moving agent."""
    stem = f"{job.frame:010d}"
    _write(root / "data_2d_raw" / job.sequence / camera / "data_rgb" / f"{stem}.png", _png(rgb[..., ::-1]))
    _write(root / "data_2d_distance" / job.sequence / camera / f"{stem}.npy", _npy(distance))
    if moving is not None:
        _write(root / "data_2d_moving" / job.sequence / camera / f"{stem}.png", _png(moving * np.uint8(255)))


def write_scan(root: Path, job: Job, points: np.ndarray) -> None:
    """The Velodyne scan of ``job``: ``[N, 4]`` float32 points, KITTI's ``.bin``."""
    scan = root / "data_3d_raw" / job.sequence / "velodyne_points" / "data" / f"{job.frame:010d}.bin"
    _write(scan, np.ascontiguousarray(points).tobytes())


def metadata(
    rig: Rig, world, ranges: dict[str, tuple[int, int]], spec: WorldSpec, lidar: bool, agents: Traffic
) -> dict:
    """``synthetic.json``: the generator, the parameters of ``spec`` (:meth:`~.spec.WorldSpec.written`),
    the cameras, each split's trajectory frames, a description of the world, and whether it has LiDAR."""
    counts = {"boxes": len(world.boxes), "cylinders": len(world.cylinders), "spheres": len(world.spheres)}
    if world.scene == "indoor":
        described = {
            "room": world.room.tolist(),
            "walkway": world.walkway.tolist(),
            "light": world.sun.tolist(),
            "style": {k: np.asarray(v).tolist() for k, v in world.style.items()},
            **counts,
        }
    else:
        described = {"pitch": world.pitch, "sun": world.sun.tolist(), **counts}
        if agents.n_agents:
            described["agents"] = {k: agents.kind.count(k) for k in sorted(set(agents.kind))}
    return {
        "generator": f"fisheyedepth {__version__}",
        **spec.written(),
        "cameras": {name: cam.to_dict() for name, cam in rig.cameras.items()},
        "sequences": {
            split: {"name": SEQUENCES[split], "trajectory_frames": list(ranges[split])} for split in SPLITS
        },
        "world": described,
        "lidar": lidar,
    }
