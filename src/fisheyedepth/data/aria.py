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

Nothing reaches ``out`` unchecked: the export gets the checks the rig layout and the dataset make when
they read the result back (each camera's model and extrinsic, the poses, one image per capture time, every
image whole and of its camera's size), then the output is written into a hidden folder beside ``out`` and
loaded back through :class:`~fisheyedepth.data.layouts.RigLayout` before it is moved into place. A
refused export leaves nothing behind. The console script ``fisheyedepth-import-aria`` (:func:`main`)
converts one from the command line.
"""

from __future__ import annotations

import csv
import os
import re
import shutil
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..cameras import CalibrationError, Fisheye624Camera, camera_from_mapping, load_json, save_camera
from ..files import inside, move_into_place, path_name, staged_folder
from ..images import ImageError, read_image
from .layouts import pose_row, read_transform, written_rig

CALIBRATION = "calib_slam_fisheye624.json"
POSES = "vio_high_frequency_T_odometry_device.csv"
POSE_COLUMNS = ("tracking_timestamp_us", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
IMAGE_NAME = re.compile(r"^(?:\d+_)?(\d+)\.png$")  # NN_<capture_ns>.png or <capture_ns>.png


def read_aria_poses(path: str | os.PathLike) -> list[tuple[int, list[float]]]:
    """``(timestamp_ns, [tx, ty, tz, qx, qy, qz, qw])`` rows of Aria's VIO CSV (microseconds in the file).
    Two rows with one timestamp are refused, as the rig layout refuses them."""
    path = Path(path)
    rows, lines = [], {}
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
            pose_row(f"{path}:{line}", values, stamp, f"{stamp // 1000} us", lines, line)
            rows.append((stamp, values))
    if len(rows) < 2:
        raise ValueError(f"{path}: fewer than two poses")
    return rows


def aria_camera(calib_path: Path, name: str, entry: dict) -> tuple[Fisheye624Camera, np.ndarray]:
    """Camera ``name`` of the calibration and its ``T_device_camera``, refused (naming the file and the
    camera) where the rig layout would refuse them: an image size that is not whole pixels, a model
    that gives (almost) no pixel a ray, a transform that is not rigid."""
    camera = Fisheye624Camera.from_aria(calib_path, name)
    try:
        camera_from_mapping(camera.to_dict(), calib_path)  # what load_camera checks on the written YAML
    except CalibrationError as err:
        raise CalibrationError(calib_path, name, err.reason) from None
    T = entry.get("T_device_camera")
    if T is None or np.asarray(T, dtype=object).shape != (4, 4):
        raise CalibrationError(calib_path, f"{name}.T_device_camera", f"expected a 4x4 matrix, got {T!r}")
    read_transform(T, calib_path, f"{name}.T_device_camera")  # the rig layout's check: rigid, finite
    return camera, np.asarray(T, dtype=float)


def image_files(folder: Path) -> dict[int, Path]:
    """The images of one camera by capture time (ns). Two files with one capture time would become one
    ``<capture_ns>.png``: refused, naming both."""
    files: dict[int, Path] = {}
    for path in sorted(p for p in folder.iterdir() if IMAGE_NAME.match(p.name)):
        stamp = int(IMAGE_NAME.match(path.name).group(1))
        if stamp in files:
            raise ValueError(
                f"{folder}: {files[stamp].name} and {path.name} have one capture time, {stamp} ns: "
                "one image would replace the other"
            )
        files[stamp] = path
    if not files:
        raise FileNotFoundError(f"{folder}: no images named NN_<capture_ns>.png")
    return files


def check_image(path: Path, camera: Fisheye624Camera, name: str) -> None:
    """What the dataset checks when it reads the image: whole, decodable and of the camera's size."""
    size = read_image(path).bgr.shape[1::-1]
    if tuple(size) != (camera.width, camera.height):
        raise ImageError(
            f"{path}: image is {size[0]}x{size[1]}, camera {name} of {CALIBRATION} is "
            f"{camera.width}x{camera.height}"
        )


def aria_to_rig(
    src: str | os.PathLike, out: str | os.PathLike, sequence: str = "seq0", overwrite: bool = False
) -> dict:
    """Convert an Aria export ``src`` (module docstring) into the rig layout at ``out``; returns a summary
    (cameras, images per camera, those outside the poses' time range, poses). Nothing is overwritten
    unless ``overwrite``; nothing is written when the export is refused."""
    src, out = Path(src), Path(out)
    path_name(sequence, "sequence", "--sequence")  # a folder under out
    calib_path = src / CALIBRATION
    if not calib_path.is_file():
        raise FileNotFoundError(f"{calib_path}: Aria calibration not found")
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out} is a file, not a folder for the rig layout")
    if (out / "rig.yaml").exists() and not overwrite:
        raise FileExistsError(f"{out / 'rig.yaml'} exists; pass overwrite=True (--overwrite) to replace it")
    calibration = load_json(calib_path.read_bytes(), calib_path)  # not JSON, not text, nested too deeply
    if not isinstance(calibration, dict):
        raise CalibrationError(calib_path, None, "expected a mapping {camera: calibration}")
    for name in calibration:  # each names a folder of src, and one under out
        path_name(name, "camera", calib_path)
    names = sorted(n for n in calibration if (src / n).is_dir())
    if not names:
        raise FileNotFoundError(f"{src}: no image folder named like a camera of {calib_path.name}")
    cameras = {name: aria_camera(calib_path, name, calibration[name]) for name in names}
    images = {name: image_files(src / name) for name in names}
    if not (src / POSES).is_file():
        raise FileNotFoundError(f"{src / POSES}: Aria's VIO poses not found (the export's odometry)")
    poses = read_aria_poses(src / POSES)
    targets = [Path("rig.yaml"), Path(sequence) / "poses.txt"]
    targets += [Path("calibration") / f"{name}.yaml" for name in names]
    targets += [Path(sequence) / "images" / n / f"{t}.png" for n, files in images.items() for t in files]
    taken = next((out / t for t in targets if os.path.lexists(inside(out, out / t, "--out"))), None)
    if taken is not None and not overwrite:
        raise FileExistsError(f"{taken} exists; pass overwrite=True (--overwrite) to replace it")

    with staged_folder(out, "partial") as staging:
        total = sum(len(f) for f in images.values())
        with tqdm(total=total, desc="aria -> rig", unit="image") as bar:
            for name, files in images.items():
                folder = staging / sequence / "images" / name
                folder.mkdir(parents=True)
                for stamp, path in files.items():
                    check_image(path, cameras[name][0], name)
                    shutil.copyfile(path, folder / f"{stamp}.png")
                    bar.update()
        for name, (camera, _) in cameras.items():  # the project's YAML: predict.py camera=... reads it too
            save_camera(camera, staging / "calibration" / f"{name}.yaml")
        lines = [f"{stamp} " + " ".join(repr(v) for v in values) for stamp, values in poses]
        header = "# timestamp_ns tx ty tz qx qy qz qw (device -> odometry)\n"
        (staging / sequence / "poses.txt").write_text(header + "\n".join(lines) + "\n")
        rig = {
            "cameras": [
                {
                    "name": n,
                    "calibration": f"calibration/{n}.yaml",
                    "cam_to_body": T.tolist(),
                }
                for n, (_, T) in cameras.items()
            ],
            "source": f"Aria export {src} (fisheyedepth.data.aria)",
        }
        kept = written_rig(staging, rig, sequence, names, src, out)  # as training reads it, or refused
        if not any(kept.values()):  # a rig of images without poses: nothing to train or match on
            first = min(min(files) for files in images.values())
            raise ValueError(
                f"{src / POSES}: no image lies within the poses' time range (poses {poses[0][0]}-"
                f"{poses[-1][0]} ns, the first image at {first} ns): is tracking_timestamp_us in "
                "microseconds?"
            )
        move_into_place(staging, out, [*targets[1:], targets[0]], overwrite)  # file by file, rig.yaml last
    return {
        "cameras": names,
        "images": {n: len(f) for n, f in images.items()},
        "outside_poses": {n: len(images[n]) - kept[n] for n in names},
        "poses": len(poses),
        "out": str(out),
    }
