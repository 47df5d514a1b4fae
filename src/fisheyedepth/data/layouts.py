"""Where frames, poses, cameras and masks live on disk: what every layout answers, and the robot-rig layout.

A layout answers a few questions for the dataset, which builds every sample the same way for both:
which cameras exist (model, camera-to-body extrinsic, optional body mask), which frames a sequence has
in time order (with body-to-world poses), and where each frame's image (and ground truth) lies.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import re
from pathlib import Path

import numpy as np
import torch

from ..cameras import CalibrationError, CameraModel, camera_from_mapping, load_camera, load_yaml
from ..geometry import make_pose, pose_from_3x4, quaternion_to_matrix

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class CameraSpec:
    name: str
    camera: CameraModel  # at the native image size
    cam_to_body: np.ndarray  # 4x4
    mask: Path | None = None  # body mask image (255 / nonzero = usable), native size


@dataclasses.dataclass(frozen=True)
class Frame:
    key: int  # frame index (KITTI-360) or timestamp in ns (rig)
    pose: np.ndarray  # 4x4 body to world


class RigLayout:
    """A robot's own recording (docs/data-format.md, "Robot rig layout").

    ``root/rig.yaml`` lists the cameras; ``root/<sequence>/images/<camera>/<timestamp_ns>.png`` hold the
    images and ``root/<sequence>/poses.txt`` the body poses as ``timestamp_ns tx ty tz qx qy qz qw``.
    Poses are interpolated to each image's timestamp (linear translation, slerp rotation); images outside
    the pose time range are reported and left out, never extrapolated.
    """

    name = "rig"

    def __init__(
        self,
        root: str | os.PathLike,
        cameras: list[str] | None = None,
        masks: dict[str, str | os.PathLike] | None = None,
        expect_masks: bool = True,
    ):
        """``expect_masks``: a mask that ``rig.yaml`` (or ``masks``) names must exist; off for the
        command that is about to write it. ``mask_paths``: each camera's named mask, existing or not
        (None: the camera has none)."""
        self.root = Path(root)
        rig_file = existing(self.root / "rig.yaml", "rig description")
        try:
            text = rig_file.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            raise CalibrationError(rig_file, None, "not a text file (not UTF-8)") from None
        rig = load_yaml(text, rig_file)  # safe, and reads 1e-3 as a number like OpenCV does
        entries = rig.get("cameras") if isinstance(rig, dict) else None
        if not isinstance(entries, list) or not entries:
            raise CalibrationError(rig_file, "cameras", "expected a non-empty list of cameras")
        self.cameras = {}
        self.mask_paths: dict[str, Path | None] = {}
        for i, entry in enumerate(entries):
            where = f"cameras[{i}]"
            if not isinstance(entry, dict) or "name" not in entry:
                raise CalibrationError(rig_file, f"{where}.name", "missing")
            name = str(entry["name"])
            if cameras is not None and name not in cameras:
                continue
            if "calibration" in entry:
                camera = load_camera(self.root / entry["calibration"])
            elif "model" in entry:
                camera = camera_from_mapping(dict(entry["model"]), f"{rig_file} ({where}.model)")
            else:
                raise CalibrationError(rig_file, f"{where}.model", "missing (or give 'calibration: FILE')")
            if "cam_to_body" not in entry:
                raise CalibrationError(rig_file, f"{where}.cam_to_body", "missing")
            extrinsic = _transform(entry["cam_to_body"], rig_file, f"{where}.cam_to_body")
            mask = masks.get(name) if masks else entry.get("mask")
            self.mask_paths[name] = mask = None if mask is None else self.root / mask
            if mask is not None and (expect_masks or mask.is_file()):
                existing(mask, "body mask")
            else:
                mask = None
            self.cameras[name] = CameraSpec(name, camera, extrinsic, mask)
        if cameras is not None and set(cameras) - set(self.cameras):
            raise CalibrationError(
                rig_file, "cameras", f"no camera named {sorted(set(cameras) - set(self.cameras))}"
            )
        self._frames: dict[tuple[str, str], list[Frame]] = {}
        self.outside: dict[tuple[str, str], list[int]] = {}

    def sequences(self) -> list[str]:
        return sorted(p.name for p in self.root.iterdir() if (p / "poses.txt").is_file())

    def _poses(self, sequence: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        path = existing(self.root / sequence / "poses.txt", "pose file")
        stamps, rows = [], []
        lines: dict[int, int] = {}
        for lineno, line in enumerate(path.read_text().splitlines(), start=1):
            fields = line.split()
            if not fields or fields[0].startswith("#"):
                continue
            try:
                stamp, values = _timestamp(fields[0]), [float(x) for x in fields[1:]]
            except ValueError:
                raise ValueError(f"{path}:{lineno}: expected 'timestamp_ns tx ty tz qx qy qz qw'") from None
            if len(values) != 7 or not all(math.isfinite(v) for v in values):
                raise ValueError(f"{path}:{lineno}: expected 8 finite numbers, got {len(values) + 1}")
            if not np.linalg.norm(values[3:]) > 0:
                raise ValueError(f"{path}:{lineno}: quaternion is zero")
            if stamp in lines:
                raise ValueError(
                    f"{path}:{lineno}: timestamp {stamp} already has a pose on line {lines[stamp]}"
                )
            lines[stamp] = lineno
            stamps.append(stamp)
            rows.append(values)
        if len(rows) < 2:
            raise ValueError(f"{path}: needs at least two poses to interpolate")
        order = np.argsort(np.array(stamps, dtype=np.int64), kind="stable")
        times, a = np.array(stamps, dtype=np.int64)[order], np.array(rows)[order]
        q = a[:, 3:7] / np.linalg.norm(a[:, 3:7], axis=1, keepdims=True)
        return times, a[:, :3], q

    def frames(self, sequence: str, camera: str) -> list[Frame]:
        key = (sequence, camera)
        if key not in self._frames:
            times, trans, quats = self._poses(sequence)
            folder = self.root / sequence / "images" / camera
            stamps = sorted(int(p.stem) for p in folder.glob("*.png") if re.fullmatch(r"\d+", p.stem))
            if not stamps:
                raise FileNotFoundError(f"{folder}: no images named <timestamp_ns>.png")
            inside = [t for t in stamps if times[0] <= t <= times[-1]]
            self.outside[key] = [t for t in stamps if not times[0] <= t <= times[-1]]
            if self.outside[key]:
                log.warning(
                    "%s: %d images of %s lie outside the pose time range and are left out",
                    self.root / sequence,
                    len(self.outside[key]),
                    camera,
                )
            self._frames[key] = [Frame(t, interpolate_pose(times, trans, quats, t)) for t in inside]
        return self._frames[key]

    def image(self, sequence: str, camera: str, frame: Frame) -> Path:
        return self.root / sequence / "images" / camera / f"{frame.key}.png"

    def distance(self, sequence: str, camera: str, frame: Frame) -> Path | None:
        path = self.root / sequence / "distance" / camera / f"{frame.key}.npy"
        return path if path.is_file() else None


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (shortest arc)."""
    dot = float(np.dot(q0, q1))
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(dot)
    return (math.sin((1 - u) * theta) * q0 + math.sin(u * theta) * q1) / math.sin(theta)


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) to a rotation matrix: ``geometry.quaternion_to_matrix`` for numpy."""
    return quaternion_to_matrix(torch.from_numpy(np.asarray(q, dtype=np.float64))).numpy()


def interpolate_pose(times: np.ndarray, trans: np.ndarray, quats: np.ndarray, t: int) -> np.ndarray:
    """Body-to-world pose at ``t`` (inside ``times``): linear in translation, slerp in rotation."""
    i = int(np.searchsorted(times, t, side="right")) - 1
    i = min(max(i, 0), len(times) - 2)
    u = (t - times[i]) / (times[i + 1] - times[i])
    R = quaternion_matrix(slerp(quats[i], quats[i + 1], float(u)))
    return make_pose(R, (1 - u) * trans[i] + u * trans[i + 1]).numpy()


def _transform(value, path: Path, key: str) -> np.ndarray:
    """A 4x4 / 3x4 matrix (nested lists) or ``{translation: [3], quaternion_xyzw: [4]}``."""
    try:
        if isinstance(value, dict):
            q = np.asarray(value["quaternion_xyzw"], float)
            T = make_pose(
                quaternion_matrix(q / np.linalg.norm(q)), np.asarray(value["translation"], float)
            ).numpy()
        else:
            m = np.asarray(value, dtype=float)
            if m.shape not in ((3, 4), (4, 4)):
                raise ValueError
            T = pose_from_3x4(m[:3]).numpy()
    except (KeyError, ValueError, TypeError):
        raise CalibrationError(
            path, key, "expected a 3x4/4x4 matrix or {translation, quaternion_xyzw}"
        ) from None
    if not isinstance(value, dict) and m.shape == (4, 4) and not np.allclose(m[3], (0, 0, 0, 1)):
        raise CalibrationError(path, key, f"the last row of a 4x4 transform must be 0 0 0 1, got {m[3]}")
    R = T[:3, :3]
    if not np.isfinite(T).all() or not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise CalibrationError(path, key, "not a rigid transform (rotation must be orthonormal, det +1)")
    return T


def _timestamp(field: str) -> int:
    """A nanosecond timestamp, parsed exactly: as a float, today's ~1.7e18 ns would lose 8 bits."""
    try:
        return int(field)
    except ValueError:
        value = float(field)  # "1.5e9" and the like; a ValueError here is the caller's to report
        if not math.isfinite(value) or value != int(value):
            raise ValueError(field) from None
        return int(value)


def existing(path: Path, what: str) -> Path:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {what} not found")
    return path
