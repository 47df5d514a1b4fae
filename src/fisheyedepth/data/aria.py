"""Project Aria recordings into the robot-rig layout (docs/data-format.md, "Robot rig layout").

An Aria export as in ``realdata/aria_gen2_rig``:

    calib_slam_fisheye624.json                 {camera: {model, params [15], size, T_device_camera}}
    vio_high_frequency_T_odometry_device.csv   tracking_timestamp_us, tx, ty, tz, qx, qy, qz, qw
    <camera>/NN_<capture_ns>.png               images, capture time in the device clock (ns)

becomes ``rig.yaml`` (every camera of the calibration that has an image folder: its Fisheye624 model in
``calibration/<camera>.yaml`` and ``cam_to_body = T_device_camera``, the body being Aria's device
frame), ``<sequence>/poses.txt`` (the odometry poses, device -> odometry, at nanosecond stamps of the
same clock) and
``<sequence>/images/<camera>/<capture_ns>.png``. The rig layout interpolates the poses to each image.
"""

from __future__ import annotations

import csv
import json
import os
import re
from pathlib import Path

import numpy as np
import yaml
from tqdm import tqdm

from ..cameras import CalibrationError, Fisheye624Camera, save_camera
from ..utils import atomic_write_bytes, atomic_write_text

CALIBRATION = "calib_slam_fisheye624.json"
POSES = "vio_high_frequency_T_odometry_device.csv"
POSE_COLUMNS = ("tracking_timestamp_us", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
IMAGE_NAME = re.compile(r"^(?:\d+_)?(\d+)\.png$")  # NN_<capture_ns>.png or <capture_ns>.png


def read_aria_poses(path: str | os.PathLike) -> list[tuple[int, list[float]]]:
    """``(timestamp_ns, [tx, ty, tz, qx, qy, qz, qw])`` rows of Aria's VIO CSV (microseconds in the file)."""
    path = Path(path)
    rows = []
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in POSE_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path}: column '{missing[0]}' missing (expected {', '.join(POSE_COLUMNS)})")
        for line, row in enumerate(reader, start=2):
            try:
                stamp = int(row["tracking_timestamp_us"]) * 1000
                values = [float(row[c]) for c in POSE_COLUMNS[1:]]
            except (TypeError, ValueError):
                raise ValueError(f"{path}:{line}: expected an integer timestamp and 7 numbers") from None
            if not all(np.isfinite(values)) or not np.linalg.norm(values[3:]) > 0:
                raise ValueError(f"{path}:{line}: a non-finite value or a zero quaternion")
            rows.append((stamp, values))
    if len(rows) < 2:
        raise ValueError(f"{path}: fewer than two poses")
    return rows


def aria_to_rig(
    src: str | os.PathLike, out: str | os.PathLike, sequence: str = "seq0", overwrite: bool = False
) -> dict:
    """Convert an Aria export ``src`` (module docstring) into the rig layout at ``out``; returns a summary
    (cameras, images per camera, poses). Nothing is overwritten unless ``overwrite``."""
    src, out = Path(src), Path(out)
    calib_path = src / CALIBRATION
    if not calib_path.is_file():
        raise FileNotFoundError(f"{calib_path}: Aria calibration not found")
    if (out / "rig.yaml").exists() and not overwrite:
        raise FileExistsError(f"{out / 'rig.yaml'} exists; pass overwrite=True (--overwrite) to replace it")
    try:
        calibration = json.loads(calib_path.read_text())
    except ValueError as err:
        raise CalibrationError(calib_path, None, f"not readable JSON ({err})") from None
    names = sorted(n for n in calibration if (src / n).is_dir())
    if not names:
        raise FileNotFoundError(f"{src}: no image folder named like a camera of {calib_path.name}")
    cameras, images, calibrations = [], {}, {}
    for name in names:
        camera = Fisheye624Camera.from_aria(calib_path, name)
        T = calibration[name].get("T_device_camera")
        if T is None or np.asarray(T, dtype=object).shape != (4, 4):
            raise CalibrationError(calib_path, f"{name}.T_device_camera", f"expected a 4x4 matrix, got {T!r}")
        files = sorted(p for p in (src / name).iterdir() if IMAGE_NAME.match(p.name))
        if not files:
            raise FileNotFoundError(f"{src / name}: no images named NN_<capture_ns>.png")
        images[name] = files
        calibrations[name] = camera
        cameras.append(
            {
                "name": name,
                "calibration": f"calibration/{name}.yaml",
                "cam_to_body": np.asarray(T, float).tolist(),
            }
        )
    poses = read_aria_poses(src / POSES)
    rig = {"cameras": cameras, "source": f"Aria export {src} (fisheyedepth.data.aria)"}
    lines = [f"{stamp} " + " ".join(repr(v) for v in values) for stamp, values in poses]
    total = sum(len(f) for f in images.values())
    with tqdm(total=total, desc="aria -> rig", unit="image") as bar:
        for name, files in images.items():
            folder = out / sequence / "images" / name
            folder.mkdir(parents=True, exist_ok=True)
            for path in files:
                stamp = IMAGE_NAME.match(path.name).group(1)
                target = folder / f"{int(stamp)}.png"
                if target.exists() and not overwrite:
                    raise FileExistsError(f"{target} exists; pass overwrite=True (--overwrite)")
                atomic_write_bytes(target, path.read_bytes())
                bar.update()
    for name, camera in calibrations.items():  # the project's YAML: predict.py camera=... reads it too
        save_camera(camera, out / "calibration" / f"{name}.yaml", overwrite=overwrite)
    atomic_write_text(
        out / sequence / "poses.txt",
        "# timestamp_ns tx ty tz qx qy qz qw (device -> odometry)\n" + "\n".join(lines) + "\n",
    )
    atomic_write_bytes(out / "rig.yaml", yaml.safe_dump(rig, sort_keys=False, width=120).encode())
    return {
        "cameras": names,
        "images": {n: len(f) for n, f in images.items()},
        "poses": len(poses),
        "out": str(out),
    }
