"""TRI's DDAD scenes (the scene format of TRI's ``dgp`` tools) into the robot-rig layout
(docs/data-format.md, "Robot rig layout"), the LiDAR sweeps projected into each camera as ground truth.

A DDAD scene folder as in ``realdata/ddad_scene01``:

    scene_<hash>.json            samples (each: calibration_key, datum_keys, id.timestamp) and data (each
                                 datum: key, id.name, id.timestamp, and an image or a point_cloud with its
                                 filename and pose, sensor -> world, rotation qw qx qy qz)
    calibration/<key>.json       names, intrinsics (fx fy cx cy skew), extrinsics (sensor -> vehicle), in
                                 one order
    rgb/<camera>/<stamp>.jpg     images (wherever each image datum's filename says)
    point_cloud/<lidar>/<stamp>.npz   key ``data``: N x (x, y, z, ...) metres in the LiDAR's frame

becomes ``rig.yaml`` (every camera with an image datum: its pinhole model in ``calibration/<camera>.yaml``
and ``cam_to_body`` = its extrinsic, the body being DDAD's vehicle frame), ``<sequence>/poses.txt`` (the
vehicle in the world at every datum's timestamp: ``T_world_sensor @ inv(T_vehicle_sensor)``),
``<sequence>/images/<camera>/<t>.png`` (the rig layout reads PNG only) and
``<sequence>/distance/<camera>/<t>.npy``: float32 metres along each pixel's ray, 0 where no LiDAR point,
from the sample's sweep (:meth:`DdadScene.ground_truth`).

- **Quaternions** are DDAD's ``qw, qx, qy, qz`` (scalar first, as ``pyquaternion`` in ``dgp``); the front
  camera's extrinsic then maps its optical axis onto the vehicle's x (forward). They must be unit
  quaternions within the layout's tolerance (:data:`~.layouts.QUATERNION_NORM_TOLERANCE`); poses.txt
  writes them x, y, z, w.
- **Time**: DDAD's stamps lie in the year 2463 (1.56e16 microseconds since 1970: 1.56e19 ns, beyond int64's
  9.2e18, the year 2262), so ``t`` counts nanoseconds from the scene's earliest datum, written to
  ``rig.yaml`` as ``time_origin`` (DDAD's own text of that stamp).
- **Poses**: the datums of one timestamp (a sample's cameras share one) must give one vehicle pose, within
  :data:`SAME_POSE_METRES` and :data:`SAME_POSE_DEGREES`; a calibration that disagrees with the scene's
  poses is refused, since training would place the cameras by the calibration and the ground truth was
  projected with the datums' own poses.
- **Ground truth**: a point lands on the pixel nearest its projection, the nearest point of a pixel wins,
  points behind the camera are dropped, and the project's occlusion filter
  (:func:`~.kitti360.occlusion_filter`, the rule the KITTI-360 LiDAR is scored with) drops a point 10 %
  behind the nearest within 3 pixels: what the roof LiDAR saw around an edge the camera cannot see.
  The ego body is another matter: the LiDAR sees the ground beyond the car where a side camera sees the
  car's hood, and no point lies on the body to hide it. A body mask per camera (``masks``, 255 = usable)
  keeps the ground truth off the body and is written to ``masks/<camera>.png`` for training; without one
  the ground truth on the body's pixels is the ground behind it.

Nothing reaches ``out`` unchecked: the scene gets the checks the rig layout and the dataset make when they
read the result back, the output is written into a hidden folder beside ``out`` and loaded back through
:class:`~.layouts.RigLayout` before it is moved into place. A refused scene leaves nothing behind. The
console script ``fisheyedepth-import-ddad`` (:func:`main`) converts one from the command line.
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import os
import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from ..cameras import CalibrationError, PinholeCamera, camera_from_mapping, load_json, save_camera
from ..files import atomic_write_npy, inside, move_into_place, path_name, staged_folder
from ..images import ImageError, read_image
from .kitti360 import OCCLUSION, project_points
from .layouts import quaternion_matrix, unit_quaternion, written_rig

SCENE_PATTERN = "scene_*.json"
# Two datums of one timestamp give one vehicle pose within these (measured on realdata/ddad_scene01:
# 5e-7 m and 4e-5 degrees); 0.01 degrees is a third of a pixel at the front camera's focal (2168 px).
SAME_POSE_METRES = 1e-3
SAME_POSE_DEGREES = 0.01
# Distortion fields of dgp's camera intrinsics: a pinhole has none (DDAD's cameras are pinholes).
DISTORTION = ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2", "xi", "alpha", "beta")
TIMESTAMP = re.compile(r"(\d{4})-(\d\d)-(\d\d)T(\d\d):(\d\d):(\d\d)(?:\.(\d{1,9}))?Z")
EPOCH = datetime.date(1970, 1, 1).toordinal()


@dataclasses.dataclass(frozen=True)
class Datum:
    """One sensor's record of one sample."""

    name: str  # the sensor: CAMERA_01, LIDAR
    kind: str  # "image" or "point_cloud"
    stamp_ns: int  # nanoseconds since 1970 (beyond int64 for DDAD: a Python int)
    stamp_text: str  # as the scene writes it
    path: Path  # the image or the point cloud
    pose: np.ndarray  # 4x4 sensor -> world
    size: tuple[int, int] | None  # (width, height) of an image
    where: str  # its place in the scene file, for messages: data[3]


@dataclasses.dataclass(frozen=True)
class Sample:
    index: int
    stamp_ns: int
    datums: dict[str, Datum]  # by sensor name


@dataclasses.dataclass(frozen=True)
class DdadScene:
    """A DDAD scene read and checked (:func:`read_scene`)."""

    folder: Path
    scene_file: Path
    calibration_file: Path
    cameras: dict[str, PinholeCamera]  # every sensor with an image datum, by name, sorted
    extrinsics: dict[str, np.ndarray]  # 4x4 sensor -> vehicle, cameras and point clouds
    lidar: str | None  # the point-cloud sensor the ground truth comes from (None: the scene has none)
    samples: list[Sample]

    def points(self, datum: Datum) -> np.ndarray:
        """The point cloud of ``datum``: ``[N, 3]`` float64 metres in its sensor's frame. A point with a
        non-finite coordinate is no measurement and is left out."""
        return read_points(datum.path)

    def ground_truth(
        self, sample: Sample, camera: str, points: np.ndarray | None = None
    ) -> np.ndarray | None:
        """``[H, W]`` float32 distance along each pixel's ray of camera ``camera`` in ``sample`` from the
        sample's sweep (``points``: that sweep, when read already), 0 where no point; None when the sample
        has no sweep. ``p_cam = inv(T_world_cam) T_world_lidar p``: each datum's own pose, so the motion
        between the sweep's and the image's timestamps is accounted for."""
        image = sample.datums[camera]
        sweep = sample.datums.get(self.lidar) if self.lidar is not None else None
        if sweep is None:
            return None
        if points is None:
            points = self.points(sweep)
        T = np.linalg.inv(image.pose) @ sweep.pose
        distance, _ = project_points(points, T, self.cameras[camera], OCCLUSION)
        return distance.astype(np.float32)

    def time_origin(self) -> Datum:
        """The scene's earliest datum: its timestamp is the layout's 0."""
        return min((d for s in self.samples for d in s.datums.values()), key=lambda d: d.stamp_ns)


# ------------------------------------------------------------------ reading the scene
def _at(tree: Any, file: Path, prefix: str, *keys: str | int) -> Any:
    """``tree[k0][k1]...``, ``tree`` being the part of ``file`` at ``prefix`` (``data[3].datum``, "" for
    the whole file); a CalibrationError naming ``file`` and the full path of keys where one is missing."""
    node, where = tree, prefix
    for key in keys:
        where = _where(where, key) if where else _where(key)
        if isinstance(key, int):
            if not isinstance(node, list) or key >= len(node):
                raise CalibrationError(file, where, "missing")
        elif not isinstance(node, dict) or key not in node:
            raise CalibrationError(file, where, "missing")
        node = node[key]
    return node


def _where(*keys: str | int) -> str:
    where = ""
    for key in keys:
        where += f"[{key}]" if isinstance(key, int) else (f".{key}" if where else key)
    return where


def _number(value: Any, file: Path, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise CalibrationError(file, where, f"expected a number, got {value!r}")
    return float(value)


def _list(value: Any, file: Path, where: str) -> list:
    if not isinstance(value, list):
        raise CalibrationError(file, where, f"expected a list, got {type(value).__name__}")
    return value


def read_json(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found")
    data = load_json(path.read_bytes(), path)  # not JSON, not text, nested too deeply: names the file
    if not isinstance(data, dict):
        raise CalibrationError(path, None, f"expected a JSON object, got {type(data).__name__}")
    return data


def parse_timestamp(text: Any, file: Path, where: str) -> int:
    """An RFC 3339 UTC timestamp (``2463-05-15T00:38:58.203752Z``, protobuf's JSON form) as integer
    nanoseconds since 1970, exactly (a float would round DDAD's 1.56e19 ns to 2 microseconds)."""
    match = TIMESTAMP.fullmatch(text) if isinstance(text, str) else None
    if match is None:
        raise CalibrationError(
            file, where, f"expected a UTC time like 2019-05-15T00:38:58.203752Z, got {text!r}"
        )
    year, month, day, hour, minute, second = (int(g) for g in match.groups()[:6])
    try:
        days = datetime.date(year, month, day).toordinal() - EPOCH
    except ValueError as err:
        raise CalibrationError(file, where, f"{text!r}: {err}") from None
    if hour > 23 or minute > 59 or second > 60:
        raise CalibrationError(file, where, f"{text!r}: not a time of day")
    fraction = int((match.group(7) or "0").ljust(9, "0"))
    return ((days * 24 + hour) * 60 + minute) * 60 * 10**9 + second * 10**9 + fraction


def rotation(value: Any, file: Path, where: str) -> np.ndarray:
    """DDAD's ``{qw, qx, qy, qz}`` as a unit quaternion in x, y, z, w order (the project's), refused
    unless its norm is 1 within the layout's tolerance."""
    q = [_number(_at(value, file, where, k), file, f"{where}.{k}") for k in ("qx", "qy", "qz", "qw")]
    return unit_quaternion(q, f"{file}: key '{where}'")


def transform(value: Any, file: Path, where: str) -> np.ndarray:
    """``{rotation: {qw qx qy qz}, translation: {x y z}}`` as a 4x4 matrix."""
    q = rotation(_at(value, file, where, "rotation"), file, f"{where}.rotation")
    t = [_number(_at(value, file, where, "translation", k), file, f"{where}.translation.{k}") for k in "xyz"]
    T = np.eye(4)
    T[:3, :3] = quaternion_matrix(q)
    T[:3, 3] = t
    return T


def read_points(path: Path) -> np.ndarray:
    """A DDAD point cloud (``.npz``, key ``data``: N x 3 or more, x y z in metres first) as ``[N, 3]``
    float64; rows with a non-finite coordinate are left out."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: point cloud not found")
    try:
        with np.load(path, allow_pickle=False) as archive:
            if "data" not in archive.files:
                raise CalibrationError(path, "data", f"missing (the archive holds {sorted(archive.files)})")
            data = archive["data"]
    except (ValueError, OSError) as err:  # not an archive, a pickle, truncated
        raise ValueError(f"{path}: not a readable NumPy .npz archive ({err})") from None
    if data.ndim != 2 or data.shape[1] < 3 or not np.issubdtype(data.dtype, np.number):
        raise CalibrationError(
            path,
            "data",
            f"expected N x 3 or more numbers (x, y, z, ...), got {data.dtype} of shape {data.shape}",
        )
    xyz = data[:, :3].astype(np.float64)
    return xyz[np.isfinite(xyz).all(axis=1)]


def pinhole(intrinsics: Any, size: tuple[int, int], file: Path, where: str) -> PinholeCamera:
    """DDAD's ``{fx, fy, cx, cy, skew}`` at the image size ``size`` as the project's pinhole, refused where
    the model cannot hold it (a skew, a distortion) or no real camera could be it."""
    values = {
        k: _number(_at(intrinsics, file, where, k), file, f"{where}.{k}") for k in ("fx", "fy", "cx", "cy")
    }
    skew = _number(intrinsics.get("skew", 0.0), file, f"{where}.skew")
    if skew != 0:
        raise CalibrationError(file, f"{where}.skew", f"{skew:g}; the pinhole model has no skew")
    if intrinsics.get("fisheye"):
        raise CalibrationError(
            file, f"{where}.fisheye", f"{intrinsics['fisheye']!r}; DDAD's cameras are pinholes"
        )
    for key in DISTORTION:
        if key in intrinsics and _number(intrinsics[key], file, f"{where}.{key}") != 0:
            raise CalibrationError(
                file, f"{where}.{key}", f"{intrinsics[key]:g}; a pinhole has no distortion (DDAD's have none)"
            )
    keys = {k: f"{where}.{k}" for k in values}
    mapping = {"model": "pinhole", "width": size[0], "height": size[1], **values}
    return camera_from_mapping({**mapping, "_source_keys": keys}, file)


def _datum(entry: Any, i: int, folder: Path, file: Path) -> Datum | None:
    """``data[i]``: an image or a point cloud (None for another kind of datum)."""
    name = _at(entry, file, _where("data", i), "id", "name")
    if not isinstance(name, str):
        raise CalibrationError(file, _where("data", i, "id", "name"), f"expected a name, got {name!r}")
    stamp_text = _at(entry, file, _where("data", i), "id", "timestamp")
    stamp = parse_timestamp(stamp_text, file, _where("data", i, "id", "timestamp"))
    datum = _at(entry, file, _where("data", i), "datum")
    kinds = [k for k in ("image", "point_cloud") if isinstance(datum, dict) and k in datum]
    if not kinds:
        return None
    kind = kinds[0]
    body = datum[kind]
    where = _where("data", i, "datum", kind)
    filename = _at(body, file, where, "filename")
    if not isinstance(filename, str) or not filename:
        raise CalibrationError(file, f"{where}.filename", f"expected a file name, got {filename!r}")
    path = inside(folder, folder / filename, f"{file}: key '{where}.filename'")
    pose = transform(_at(body, file, where, "pose"), file, f"{where}.pose")
    size = None
    if kind == "image":
        size = tuple(
            int(_number(_at(body, file, where, k), file, f"{where}.{k}")) for k in ("width", "height")
        )
        if min(size) <= 0 or size != tuple(_at(body, file, where, k) for k in ("width", "height")):
            raise CalibrationError(file, f"{where}.width", f"expected whole pixels, got {size}")
    return Datum(path_name(name, _where("data", i, "id", "name"), file), kind, stamp, stamp_text, path, pose,
                 size, _where("data", i))  # fmt: skip


def find_scene(src: Path) -> Path:
    """``src`` itself (a scene JSON), or the one ``scene_*.json`` of the folder ``src``."""
    if src.is_file():
        return src
    if not src.is_dir():
        raise FileNotFoundError(f"{src}: no DDAD scene folder or scene file")
    found = sorted(src.glob(SCENE_PATTERN))
    if not found:
        raise FileNotFoundError(f"{src}: no {SCENE_PATTERN} (a DDAD scene folder holds one)")
    if len(found) > 1:
        raise ValueError(
            f"{src}: {len(found)} scene files ({found[0].name}, {found[1].name}); name one as --src"
        )
    return found[0]


def read_scene(
    src: str | os.PathLike, cameras: list[str] | None = None, lidar: str | None = None
) -> DdadScene:
    """The scene at ``src`` (its folder or its ``scene_*.json``), checked; ``cameras``: those to keep
    (default: every sensor with an image datum); ``lidar``: the point-cloud sensor of the ground truth
    (default: the scene's only one)."""
    scene_file = find_scene(Path(src))
    folder = scene_file.parent
    scene = read_json(scene_file)
    data = _list(_at(scene, scene_file, "", "data"), scene_file, "data")
    samples_json = _list(_at(scene, scene_file, "", "samples"), scene_file, "samples")
    if not samples_json:
        raise CalibrationError(scene_file, "samples", "empty: the scene has no sample")
    by_key: dict[str, tuple[int, Any]] = {}
    for i, entry in enumerate(data):
        key = _at(entry, scene_file, _where("data", i), "key") if isinstance(entry, dict) else None
        if not isinstance(key, str):
            raise CalibrationError(scene_file, _where("data", i, "key"), f"expected a key, got {key!r}")
        if key in by_key:
            raise CalibrationError(
                scene_file, _where("data", i, "key"), f"{key!r} is also data[{by_key[key][0]}]"
            )
        by_key[key] = (i, entry)

    first_key = None
    for s, sample in enumerate(samples_json):  # one calibration: the rig layout holds one per camera
        where = _where("samples", s, "calibration_key")
        key = _at(sample, scene_file, _where("samples", s), "calibration_key")
        if not isinstance(key, str):
            raise CalibrationError(scene_file, where, f"expected a key, got {key!r}")
        if first_key is None:
            first_key = path_name(key, f"key '{where}'", scene_file)
        elif key != first_key:
            raise CalibrationError(
                scene_file, where,
                f"{key!r} differs from samples[0]'s {first_key!r}: the rig layout holds one calibration per "
                "camera",
            )  # fmt: skip
    calibration_file = folder / "calibration" / f"{first_key}.json"
    calibration = read_json(calibration_file)
    names = _list(_at(calibration, calibration_file, "", "names"), calibration_file, "names")
    for key in ("intrinsics", "extrinsics"):
        entries = _list(_at(calibration, calibration_file, "", key), calibration_file, key)
        if len(entries) != len(names):
            raise CalibrationError(
                calibration_file, key, f"{len(entries)} entries, but 'names' has {len(names)}: one per name"
            )
    index: dict[str, int] = {}
    for i, name in enumerate(names):
        if not isinstance(name, str) or name in index:
            why = (
                f"{name!r} is also names[{index[name]}]"
                if name in index
                else f"expected a name, got {name!r}"
            )
            raise CalibrationError(calibration_file, f"names[{i}]", why)
        index[name] = i

    cache: dict[int, Datum | None] = {}
    samples: list[Sample] = []
    for s, sample in enumerate(samples_json):
        keys = _list(
            _at(sample, scene_file, _where("samples", s), "datum_keys"),
            scene_file,
            _where("samples", s, "datum_keys"),
        )
        stamp = parse_timestamp(
            _at(sample, scene_file, _where("samples", s), "id", "timestamp"),
            scene_file,
            _where("samples", s, "id", "timestamp"),
        )
        datums: dict[str, Datum] = {}
        for j, key in enumerate(keys):
            if not isinstance(key, str) or key not in by_key:
                raise CalibrationError(
                    scene_file, _where("samples", s, "datum_keys", j), f"{key!r} names no datum of 'data'"
                )
            i, entry = by_key[key]
            if i not in cache:
                cache[i] = _datum(entry, i, folder, scene_file)
            datum = cache[i]
            if datum is None:
                continue
            if datum.name in datums:
                raise CalibrationError(
                    scene_file, _where("samples", s, "datum_keys", j),
                    f"a second datum of {datum.name} in one sample ({datums[datum.name].where} and "
                    f"{datum.where})",
                )  # fmt: skip
            if datum.name not in index:
                raise CalibrationError(
                    scene_file, f"{datum.where}.id.name",
                    f"{datum.name!r} has no calibration in {calibration_file.name} "
                    f"(names: {', '.join(index)})",
                )  # fmt: skip
            datums[datum.name] = datum
        samples.append(Sample(s, stamp, datums))

    kinds: dict[str, Datum] = {}
    for sample in samples:
        for datum in sample.datums.values():
            first = kinds.setdefault(datum.name, datum)
            if datum.kind != first.kind:
                raise CalibrationError(
                    scene_file,
                    datum.where,
                    f"{datum.name} is a {datum.kind} here, a {first.kind} in {first.where}",
                )
            if datum.size != first.size:
                raise CalibrationError(
                    scene_file, f"{datum.where}.datum.image.width",
                    f"{datum.name} is {datum.size[0]}x{datum.size[1]} here, {first.size[0]}x{first.size[1]} "
                    f"in {first.where}: one camera, one image size",
                )  # fmt: skip
    image_names = sorted(n for n, d in kinds.items() if d.kind == "image")
    clouds = sorted(n for n, d in kinds.items() if d.kind == "point_cloud")
    if cameras is not None:
        unknown = sorted(set(cameras) - set(image_names))
        if unknown:
            raise ValueError(
                f"--cameras: {unknown} are not cameras of {scene_file} ({', '.join(image_names)})"
            )
        image_names = sorted(set(cameras))
    if not image_names:
        raise CalibrationError(scene_file, "data", "no image datum: the scene has no camera")
    if lidar is not None and lidar not in clouds:
        raise ValueError(
            f"--lidar: {lidar!r} is no point cloud of {scene_file} ({', '.join(clouds) or 'none'})"
        )
    if lidar is None and len(clouds) > 1:
        raise ValueError(
            f"--lidar: {scene_file} has point clouds of {', '.join(clouds)}; name the one to project"
        )
    lidar = lidar or (clouds[0] if clouds else None)
    models = {
        name: pinhole(
            calibration["intrinsics"][index[name]],
            kinds[name].size,
            calibration_file,
            f"intrinsics[{index[name]}]",
        )  # fmt: skip
        for name in image_names
    }
    extrinsics = {
        name: transform(
            calibration["extrinsics"][index[name]], calibration_file, f"extrinsics[{index[name]}]"
        )
        for name in [*image_names, *([lidar] if lidar else [])]
    }
    keep = set(image_names) | ({lidar} if lidar else set())
    samples = [Sample(s.index, s.stamp_ns, {n: d for n, d in s.datums.items() if n in keep}) for s in samples]
    return DdadScene(folder, scene_file, calibration_file, models, extrinsics, lidar, samples)


# ------------------------------------------------------------------ poses
def quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    """A rotation matrix as a unit quaternion (x, y, z, w), w >= 0 (Shepperd's method)."""
    m = R
    trace = np.trace(m)
    if trace > 0:
        s = 2 * math.sqrt(1 + trace)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2 * math.sqrt(1 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2 * math.sqrt(1 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2 * math.sqrt(1 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
    q = np.asarray(q) / np.linalg.norm(q)
    return -q if q[3] < 0 else q


def vehicle_poses(scene: DdadScene) -> dict[int, np.ndarray]:
    """The vehicle -> world pose at every datum's timestamp (ns since 1970): ``T_world_sensor @
    inv(T_vehicle_sensor)``. Datums of one timestamp that disagree beyond :data:`SAME_POSE_METRES` or
    :data:`SAME_POSE_DEGREES` are refused, naming both."""
    poses: dict[int, tuple[np.ndarray, Datum]] = {}
    for sample in scene.samples:
        for datum in sample.datums.values():
            T = datum.pose @ np.linalg.inv(scene.extrinsics[datum.name])
            if datum.stamp_ns not in poses:
                poses[datum.stamp_ns] = (T, datum)
                continue
            other, first = poses[datum.stamp_ns]
            D = np.linalg.inv(other) @ T
            metres = float(np.linalg.norm(D[:3, 3]))
            degrees = math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(D[:3, :3]) - 1) / 2))))
            if metres > SAME_POSE_METRES or degrees > SAME_POSE_DEGREES:
                raise ValueError(
                    f"{scene.scene_file}: {datum.where} ({datum.name}) and {first.where} ({first.name}) "
                    f"share the timestamp {datum.stamp_text} but place the vehicle {metres:.4g} m and "
                    f"{degrees:.4g} degrees apart through {scene.calibration_file.name}'s extrinsics "
                    f"(at most {SAME_POSE_METRES:g} m, {SAME_POSE_DEGREES:g} degrees): the calibration does "
                    "not fit the scene's poses"
                )
    return {stamp: T for stamp, (T, _) in sorted(poses.items())}


def pose_line(stamp: int, T: np.ndarray) -> str:
    """``timestamp_ns tx ty tz qx qy qz qw``, every number as Python writes it back exactly."""
    values = [*T[:3, 3].tolist(), *quaternion_xyzw(T[:3, :3]).tolist()]
    return f"{stamp} " + " ".join(repr(float(v)) for v in values)


# ------------------------------------------------------------------ the import
def read_mask(path: Path, camera: PinholeCamera, name: str) -> np.ndarray:
    """A body mask (255 / bright = usable) of the camera's size as bool ``[H, W]``; refused by name."""
    grey = cv2.cvtColor(read_image(path).bgr, cv2.COLOR_BGR2GRAY)
    if grey.shape[1::-1] != (camera.width, camera.height):
        raise ImageError(
            f"{path}: body mask of {grey.shape[1]}x{grey.shape[0]} pixels, but camera {name} is "
            f"{camera.width}x{camera.height}"
        )
    return grey > 127


def ddad_to_rig(
    src: str | os.PathLike,
    out: str | os.PathLike,
    sequence: str = "seq0",
    cameras: list[str] | None = None,
    lidar: str | None = None,
    masks: dict[str, str | os.PathLike] | None = None,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Convert the DDAD scene ``src`` (module docstring) into the rig layout at ``out``; returns a summary
    (cameras, samples, images and LiDAR pixels per camera, poses, the time origin). ``masks``: body masks
    by camera (255 = usable), copied to ``masks/<camera>.png``, the ground truth kept off the body. Nothing
    is overwritten unless ``overwrite``: it replaces ``rig.yaml``, the cameras' calibration files and masks
    and the whole sequence folder; nothing is written when the scene is refused."""
    src, out = Path(src), Path(out)
    path_name(sequence, "sequence", "--sequence")  # a folder under out
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out} is a file, not a folder for the rig layout")
    if (out / "rig.yaml").exists() and not overwrite:
        raise FileExistsError(f"{out / 'rig.yaml'} exists; pass overwrite=True (--overwrite) to replace it")
    scene = read_scene(src, cameras, lidar)
    names = list(scene.cameras)
    masks = {name: Path(path) for name, path in (masks or {}).items()}
    if set(masks) - set(names):
        raise ValueError(
            f"--mask: {sorted(set(masks) - set(names))} are not cameras of the import ({', '.join(names)})"
        )
    usable = {name: read_mask(path, scene.cameras[name], name) for name, path in masks.items()}
    poses = vehicle_poses(scene)
    origin = scene.time_origin()
    parts = [Path(sequence), *(Path("calibration") / f"{n}.yaml" for n in names)]
    parts += [Path("masks") / f"{n}.png" for n in masks]
    parts.append(Path("rig.yaml"))  # last: a rig is complete with it
    for part in reversed(parts):
        if os.path.lexists(inside(out, out / part, "--out")) and not overwrite:
            raise FileExistsError(f"{out / part} exists; pass overwrite=True (--overwrite) to replace it")
    images = {n: 0 for n in names}
    lidar_pixels: dict[str, list[int]] = {n: [] for n in names}
    with staged_folder(out, "importing") as staging:
        total = sum(n in s.datums for s in scene.samples for n in names)
        with tqdm(total=total, desc="ddad -> rig", unit="image") as bar:
            for sample in scene.samples:
                sweep = sample.datums.get(scene.lidar) if scene.lidar else None
                points = scene.points(sweep) if sweep is not None else None
                for name in names:
                    datum = sample.datums.get(name)
                    if datum is None:
                        continue
                    stamp = datum.stamp_ns - origin.stamp_ns
                    bgr = read_image(datum.path).bgr
                    if bgr.shape[1::-1] != datum.size:
                        raise ImageError(
                            f"{datum.path}: image is {bgr.shape[1]}x{bgr.shape[0]}, {scene.scene_file.name} "
                            f"{datum.where} says {datum.size[0]}x{datum.size[1]}"
                        )
                    ok, encoded = cv2.imencode(".png", bgr)
                    if not ok:
                        raise OSError(f"{datum.path}: could not encode it as PNG")
                    target = staging / sequence / "images" / name / f"{stamp}.png"
                    target.parent.mkdir(parents=True, exist_ok=True)
                    target.write_bytes(encoded.tobytes())
                    images[name] += 1
                    distance = scene.ground_truth(sample, name, points) if points is not None else None
                    if distance is not None:
                        if name in usable:
                            distance[~usable[name]] = 0
                        atomic_write_npy(staging / sequence / "distance" / name / f"{stamp}.npy", distance)
                        lidar_pixels[name].append(int((distance > 0).sum()))
                    bar.update()
        for name, camera in scene.cameras.items():  # the project's YAML: predict.py camera=... reads it too
            save_camera(camera, staging / "calibration" / f"{name}.yaml")
        for name in masks:
            target = staging / "masks" / f"{name}.png"
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(cv2.imencode(".png", usable[name].astype(np.uint8) * 255)[1].tobytes())
        header = "# timestamp_ns tx ty tz qx qy qz qw (vehicle -> world), ns since rig.yaml's time_origin\n"
        lines = [pose_line(stamp - origin.stamp_ns, T) for stamp, T in poses.items()]
        (staging / sequence / "poses.txt").write_text(header + "\n".join(lines) + "\n")
        rig = {
            "cameras": [
                {
                    "name": n,
                    "calibration": f"calibration/{n}.yaml",
                    "cam_to_body": scene.extrinsics[n].tolist(),
                    **({"mask": f"masks/{n}.png"} if n in masks else {}),
                }
                for n in names
            ],
            "source": f"DDAD scene {scene.scene_file} (fisheyedepth.data.ddad), ground truth: {scene.lidar}",
            "time_origin": origin.stamp_text,
        }
        kept = written_rig(staging, rig, sequence, names, src, out)  # as training reads it, or refused
        lost = {n: images[n] - kept[n] for n in names if kept[n] != images[n]}
        if lost:  # every image lies on a pose of its own timestamp: none may be left out
            raise ValueError(
                f"{src}: the converted rig leaves images out ({lost}); this is a bug of the import"
            )
        move_into_place(staging, out, parts, overwrite)
    return {
        "cameras": names,
        "samples": len(scene.samples),
        "images": images,
        "lidar": scene.lidar,
        "lidar_pixels": lidar_pixels,
        "poses": len(poses),
        "time_origin": origin.stamp_text,
        "out": str(out),
    }
