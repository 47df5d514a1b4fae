"""Readers of the real fisheye frames with metric ground truth, each from its own folder under a root
the caller names:

- ``kitti360``: the left KITTI-360 fisheye (Mei model) with its Velodyne scan projected as Euclidean
  distances and the ego-vehicle body mask.
- ``scannetpp``: a ScanNet++ DSLR fisheye (Kannala-Brandt) with depth rendered from the laser scan.
- ``adt_{left,right}_{0,1}``: the two grey SLAM cameras of Aria Digital Twin (native Fisheye624) with
  the digital twin's rendered depth, frames 0 and 1; the grey image becomes three equal channels.
- ``ddad_<camera>``: each camera (pinhole) of a DDAD scene's first sample with the sample's LiDAR sweep
  projected into it (:mod:`.ddad`, the projection its importer writes). The car of ``ddad_scene01``
  stands still, so its later samples are the same view again. DDAD ships no body mask: the side
  cameras' pixels on the car's hood carry the ground the roof LiDAR saw beyond it.

The dense frames store z-depth in millimetres; :func:`z_to_distance` turns it into distance along each
pixel's ray with the frame's own calibration, and the frame's range is its ground truth's rounded up to
a whole metre (:func:`indoor_cap`); the LiDAR frame reaches 80 m. A frame whose files are absent is
:class:`Missing`, named with the path it lacks; a malformed file raises a ``ValueError`` (a
``CalibrationError`` for a calibration) naming the file and the field.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor

from ..cameras import (
    CalibrationError,
    CameraModel,
    Fisheye624Camera,
    RayCache,
    camera_from_mapping,
    load_camera,
    load_json,
)
from ..cameras.fisheye624 import ARIA_PARAMS
from ..cameras.io import field
from ..data.ddad import read_scene
from ..images import read_image

FRAME_SETS = ("kitti360", "scannetpp", "adt", "ddad")  # what a caller chooses from; adt holds four frames
FOLDERS = {
    "kitti360": "kitti360_frame",
    "scannetpp": "scannetpp_frame",
    "adt": "adt_slam",
    "ddad": "ddad_scene01",
}
ADT_FRAMES = (
    ("camera-slam-left", 0),
    ("camera-slam-left", 1),
    ("camera-slam-right", 0),
    ("camera-slam-right", 1),
)
OUTDOOR_CAP = 80.0  # metres: the farthest LiDAR return scored
RAYS = RayCache(max_entries=16)  # every frame's camera at its native size, shared by reading and scoring


@dataclasses.dataclass(frozen=True)
class Missing:
    """A frame that cannot be scored because ``path`` (a file or folder it needs) is absent."""

    name: str
    path: Path


@dataclasses.dataclass(frozen=True, eq=False)
class RealFrame:
    """One real image with metric ground truth, at its native size."""

    name: str
    image: Tensor  # [1, 3, H, W] RGB in [0, 1]
    camera: CameraModel
    distance: Tensor  # [H, W] metres along the ray, 0 without ground truth
    mask: Tensor  # [H, W] bool: usable pixels (not the ego body)
    files: tuple[Path, ...]  # what it was read from
    source: str | None = None  # "lidar" for a projected scan, None for a dense map
    cap: float = OUTDOOR_CAP  # metres: the frame's range, the farthest ground truth that counts


# ------------------------------------------------------------------ reading the files
def _need(path: Path, name: str) -> Missing | None:
    return None if path.exists() else Missing(name, path)


def read_uint16(path: Path, unit: str) -> np.ndarray:
    """A one-channel 16-bit PNG (``unit``: what a value means, for the message); errors name the file."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found")
    data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None or data.dtype != np.uint16 or data.ndim != 2:
        kind = "unreadable" if data is None else f"{data.dtype} with shape {data.shape}"
        raise ValueError(f"{path}: expected a one-channel uint16 PNG ({unit}), got {kind}")
    return data


def read_rgb(path: Path) -> Tensor:
    """``[1, 3, H, W]`` float RGB in [0, 1]; a grey file becomes three equal channels."""
    bgr = read_image(path).bgr
    return torch.from_numpy(np.ascontiguousarray(bgr[..., ::-1])).permute(2, 0, 1).float()[None] / 255.0


def read_json(path: Path) -> dict[str, Any]:
    try:
        data = load_json(path.read_bytes(), path)  # not JSON, not text, nested too deeply: names the file
    except OSError as err:
        raise CalibrationError(path, None, f"not readable JSON ({err})") from None
    if not isinstance(data, dict):
        raise CalibrationError(path, None, f"expected a JSON object, got {type(data).__name__}")
    return data


def _number(value: Any, key: str, path: Path) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise CalibrationError(path, key, f"expected a number, got {value!r}")
    return float(value)


def _numbers(values: Any, count: int, key: str, path: Path) -> list[float]:
    """``values`` as ``count`` finite numbers; a CalibrationError naming ``key`` otherwise."""
    if not isinstance(values, list) or len(values) != count:
        got = f"{len(values)} values" if isinstance(values, list) else repr(values)
        raise CalibrationError(path, key, f"expected a list of {count} numbers, got {got}")
    return [_number(v, f"{key}[{i}]", path) for i, v in enumerate(values)]


def _pixels(value: float, key: str, path: Path) -> int:
    if not value.is_integer() or value <= 0:
        raise CalibrationError(path, key, f"expected a positive whole number of pixels, got {value:g}")
    return int(value)


def _check_size(path: Path, array: np.ndarray | Tensor, camera: CameraModel, calibration: Path) -> None:
    h, w = array.shape[-2:]
    if (w, h) != (camera.width, camera.height):
        raise ValueError(f"{path}: {w}x{h}, but {calibration.name} says {camera.width}x{camera.height}")


def one_match(folder: Path, pattern: str) -> Path | None:
    """The one file of ``folder`` matching ``pattern``, None without one; a ValueError for several."""
    found = sorted(folder.glob(pattern))
    if len(found) > 1:
        raise ValueError(
            f"{folder}: {len(found)} files match {pattern} ({found[0].name}, {found[1].name}); expected one"
        )
    return found[0] if found else None


def z_to_distance(z: Tensor, camera: CameraModel) -> Tensor:
    """Z-depth ``[H, W]`` (along the optical axis, 0 = unknown) as distance along each pixel's ray,
    ``z |ray| / ray_z``; 0 where z is 0 or the pixel has no ray in front of the camera. The rays are
    the evaluation's (float32, correctly rounded from float64), the division in float64."""
    rays, valid = RAYS.get(camera)
    rays = rays.double()
    front = valid & (rays[..., 2] > 1e-9)
    ratio = rays.norm(dim=-1) / torch.where(front, rays[..., 2], torch.ones_like(rays[..., 2]))
    zd = z.to(torch.float64)
    return torch.where(front & (zd > 0), zd * ratio, torch.zeros_like(zd)).to(z.dtype)


def indoor_cap(distance: Tensor, camera: CameraModel, path: Path) -> float:
    """The frame's ground-truth range over the pixels the camera sees, rounded up to a whole metre: the
    largest distance's floor + 1; a ValueError naming ``path`` without a positive one."""
    usable = distance[(distance > 0) & RAYS.get(camera)[1]]
    if usable.numel() == 0:
        raise ValueError(f"{path}: no pixel with a positive depth inside the camera's field of view")
    return float(math.floor(float(usable.max())) + 1)


# ------------------------------------------------------------------ the frames
def load_kitti360(folder: Path, camera: str = "image_02") -> RealFrame | Missing:
    """``folder``/``camera``.yaml, ``camera``_rgb.png, ``camera``_body_mask.png and
    ``camera``_lidar_distance.png (uint16, metres * 256, 0 = no return), checked against each other."""
    calibration = folder / f"{camera}.yaml"
    paths = {k: folder / f"{camera}_{k}.png" for k in ("rgb", "body_mask", "lidar_distance")}
    for path in (folder, calibration, *paths.values()):
        if (gone := _need(path, "kitti360")) is not None:
            return gone
    cam = load_camera(calibration)
    image = read_rgb(paths["rgb"])
    mask = cv2.cvtColor(read_image(paths["body_mask"]).bgr, cv2.COLOR_BGR2GRAY) > 127
    lidar = read_uint16(paths["lidar_distance"], "metres * 256").astype(np.float32) / 256.0
    for key, array in (("rgb", image), ("body_mask", mask), ("lidar_distance", lidar)):
        _check_size(paths[key], array, cam, calibration)
    return RealFrame(
        "kitti360",
        image,
        cam,
        torch.from_numpy(lidar),
        torch.from_numpy(mask),
        (calibration, *paths.values()),
        source="lidar",
    )


def scannetpp_camera(path: Path) -> CameraModel:
    """``calibration.json``: OpenCV fisheye (Kannala-Brandt) ``width height fx fy cx cy k1..k4``."""
    data = read_json(path)
    keys = ("width", "height", "fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")
    values: dict[str, Any] = {key: _number(field(data, key, path), key, path) for key in keys}
    for key in ("width", "height"):
        values[key] = _pixels(values[key], key, path)
    return camera_from_mapping({"model": "kannala_brandt", **values}, path)


def load_scannetpp(folder: Path) -> RealFrame | Missing:
    """``folder``/rgb.jpg, calibration.json (Kannala-Brandt) and depth_z_mm.png (uint16 z-depth in mm)."""
    calibration, rgb, depth = folder / "calibration.json", folder / "rgb.jpg", folder / "depth_z_mm.png"
    for path in (folder, calibration, rgb, depth):
        if (gone := _need(path, "scannetpp")) is not None:
            return gone
    return z_depth_frame("scannetpp", rgb, depth, scannetpp_camera(calibration), calibration)


def z_depth_frame(
    name: str, image_path: Path, depth_path: Path, cam: CameraModel, calibration: Path
) -> RealFrame:
    """An indoor frame: the image, and its uint16 z-depth in millimetres turned into distance along each
    pixel's ray (every pixel usable, the range the ground truth's rounded up to a whole metre)."""
    image = read_rgb(image_path)
    z = read_uint16(depth_path, "millimetres of z-depth")
    _check_size(image_path, image, cam, calibration)
    _check_size(depth_path, z, cam, calibration)
    distance = z_to_distance(torch.from_numpy(z.astype(np.float32) / 1000.0), cam)
    mask = torch.ones_like(distance, dtype=torch.bool)
    cap = indoor_cap(distance, cam, depth_path)
    return RealFrame(name, image, cam, distance, mask, (calibration, image_path, depth_path), cap=cap)


def adt_camera(path: Path, name: str) -> CameraModel:
    """Camera ``name`` of ``adt_sample.json``: ``cameras.<name>.projection_params`` (Fisheye624,
    ``[f, cx, cy, k0..k5, p0, p1, s0..s3]``) and ``image_size`` ``[W, H]``."""
    data = read_json(path)
    key = f"cameras.{name}"
    params_key, size_key = f"{key}.projection_params", f"{key}.image_size"
    params = _numbers(field(data, params_key, path), len(ARIA_PARAMS), params_key, path)
    width, height = (
        _pixels(v, size_key, path) for v in _numbers(field(data, size_key, path), 2, size_key, path)
    )
    values = dict(zip(ARIA_PARAMS, params, strict=True))
    focal = values.pop("f")
    keys = {p: f"{params_key}[{i}]" for i, p in enumerate(ARIA_PARAMS)}
    source = {**keys, "fx": keys["f"], "fy": keys["f"], "width": size_key, "height": size_key}
    mapping = {
        "model": Fisheye624Camera.model_name,
        "width": width,
        "height": height,
        "fx": focal,
        "fy": focal,
    }
    return camera_from_mapping({**mapping, **values, "_source_keys": source}, path)


def load_adt(folder: Path) -> list[RealFrame | Missing]:
    """The four Aria Digital Twin SLAM frames with depth: ``{camera}_{i}_<t_ns>.png`` (grey) and
    ``depthskel_{camera}_{i}_<t_ns>.png`` (uint16 z-depth in mm) for each of :data:`ADT_FRAMES`."""
    calibration = folder / "adt_sample.json"
    frames: list[RealFrame | Missing] = []
    cameras: dict[str, CameraModel] = {}
    for camera, index in ADT_FRAMES:
        name = f"adt_{camera.rsplit('-', 1)[1]}_{index}"
        if (gone := _need(folder, name) or _need(calibration, name)) is not None:
            frames.append(gone)
            continue
        image_path = one_match(folder, f"{camera}_{index}_*.png")
        depth_path = one_match(folder, f"depthskel_{camera}_{index}_*.png")
        if image_path is None or depth_path is None:
            pattern = f"{camera}_{index}_*.png" if image_path is None else f"depthskel_{camera}_{index}_*.png"
            frames.append(Missing(name, folder / pattern))
            continue
        if camera not in cameras:
            cameras[camera] = adt_camera(calibration, camera)
        frames.append(z_depth_frame(name, image_path, depth_path, cameras[camera], calibration))
    return frames


def load_ddad(folder: Path) -> list[RealFrame | Missing]:
    """Every camera of the DDAD scene's first sample (:func:`.ddad.read_scene`) with the sample's sweep
    projected into it as the ground truth (nearest point per pixel, the occlusion filter applied), every
    pixel usable; ``[Missing("ddad", folder)]`` without the folder, a frame whose image or sweep is absent
    :class:`Missing`."""
    if not folder.is_dir():
        return [Missing("ddad", folder)]
    scene = read_scene(folder)
    sample = scene.samples[0]
    sweep = sample.datums.get(scene.lidar) if scene.lidar is not None else None
    if sweep is None:
        raise ValueError(f"{scene.scene_file}: samples[0] has no point cloud: no ground truth to score")
    points = scene.points(sweep) if sweep.path.is_file() else None
    frames: list[RealFrame | Missing] = []
    for camera in scene.cameras:
        name = f"ddad_{camera}"
        datum = sample.datums.get(camera)
        if datum is None:
            raise ValueError(f"{scene.scene_file}: samples[0] has no image of {camera}")
        if (gone := _need(datum.path, name) or _need(sweep.path, name)) is not None:
            frames.append(gone)
            continue
        image = read_rgb(datum.path)
        _check_size(datum.path, image, scene.cameras[camera], scene.scene_file)
        distance = torch.from_numpy(scene.ground_truth(sample, camera, points))
        mask = torch.ones_like(distance, dtype=torch.bool)
        files = (scene.scene_file, scene.calibration_file, datum.path, sweep.path)
        frames.append(RealFrame(name, image, scene.cameras[camera], distance, mask, files, source="lidar"))
    return frames


def load_frames(root: Path, sets: Sequence[str] = FRAME_SETS) -> list[RealFrame | Missing]:
    """Every frame of ``sets`` (see :data:`FRAME_SETS`) under ``root`` (a folder per set,
    :data:`FOLDERS`), in that order; a frame whose files are absent as :class:`Missing`."""
    root = Path(root)
    out: list[RealFrame | Missing] = []
    for name in sets:
        if name not in FOLDERS:
            raise ValueError(f"frames: {name!r} is not one of {', '.join(FRAME_SETS)}")
        folder = root / FOLDERS[name]
        if name == "kitti360":
            out.append(load_kitti360(folder))
        elif name == "scannetpp":
            out.append(load_scannetpp(folder))
        elif name == "ddad":
            out.extend(load_ddad(folder))
        else:
            out.extend(load_adt(folder))
    return out
