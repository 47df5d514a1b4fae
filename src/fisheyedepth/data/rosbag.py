"""ROS bags into the robot-rig layout (docs/data-format.md), with the pure-Python ``rosbags`` library.

``import_rosbag(bag, out, cameras={name: image_topic}, ...)`` reads a ROS 1 ``.bag`` or a ROS 2 bag (a
folder with ``metadata.yaml`` and sqlite3 ``.db3`` or ``.mcap`` files) and writes:

- ``<sequence>/images/<camera>/<stamp_ns>.png`` from ``sensor_msgs/Image`` (mono8, mono16, rgb8,
  bgr8, rgba8, bgra8) or ``sensor_msgs/CompressedImage``, stamped by their headers; 16-bit images are
  scaled from their bit depth (detected over the whole topic, or given) to the full 16-bit range;
- ``calibration/<camera>.yaml`` from the camera's ``sensor_msgs/CameraInfo`` (``plumb_bob`` with 5
  coefficients or ``rational_polynomial`` with 8 -> the ``opencv`` model, a pinhole with OpenCV's
  distortion; either without distortion -> pinhole; ``equidistant`` with 4 -> Kannala-Brandt; anything
  else is refused, naming the topic, the model and the coefficient count; see :func:`camera_from_info`)
  or from a calibration file the user gives;
- ``rig.yaml`` with each camera's ``cam_to_body`` from ``/tf_static`` (the chain from the body frame
  to the camera's ``frame_id``) or given;
- ``<sequence>/poses.txt`` from ``nav_msgs/Odometry`` (``--odometry``) or from ``/tf``
  (``--tf-poses WORLD BODY``, a direct edge). The rig layout interpolates them to each image's stamp;
  images outside the poses' time range, or in a gap of the poses longer than ``max_pose_gap``, are
  dropped here and counted, as the rig layout would drop them.

The import is written into a hidden folder beside ``out``, opened with ``RigLayout`` (what training
will read) and only then moved into place: a failed import leaves nothing at ``out``. A corrupt image
message is skipped and counted (refused with ``strict``). Nothing is overwritten without ``overwrite``.
Camera and sequence names become folder and file names under ``out``: each must be one plain name
(:func:`fisheyedepth.files.path_name`: no ``/``, no ``..``, ...).
"""

from __future__ import annotations

import logging
import os
from collections import defaultdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from tqdm import tqdm

from ..cameras import CameraModel, load_camera, save_camera
from ..cameras.opencv import ROS_MODELS
from ..files import inside, move_into_place, path_name, staged_folder
from ..geometry import make_pose, rigid_transform
from ..images import read_image
from .layouts import RigLayout, in_pose_gap, max_gap_ns, quaternion_matrix, unit_quaternion

log = logging.getLogger(__name__)

ENCODINGS = {"mono8": (np.uint8, 1), "mono16": (np.uint16, 1), "rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3),
             "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4)}  # fmt: skip
PNG = b"\x89PNG\r\n\x1a\n"


class RosbagError(ValueError):
    """Something in the bag cannot be imported: names the bag, the topic and what."""


class CorruptMessage(RosbagError):
    """One image message whose pixels cannot be read: skipped and counted, or refused with ``strict``."""

    def __init__(self, topic: str, why: str):
        super().__init__(f"{topic}: {why}")
        self.why = why


def _stamp(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _field(msg, *names):
    for name in names:  # ROS 1 and ROS 2 spell some fields differently (K / k)
        if hasattr(msg, name):
            return getattr(msg, name)
    raise AttributeError(names[0])


def decode_image(msg, topic: str) -> np.ndarray:
    """BGR (or grey) pixels of a ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage``."""
    if hasattr(msg, "format"):  # CompressedImage
        image = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise CorruptMessage(topic, f"a CompressedImage ({msg.format}) could not be decoded")
        return image
    encoding = str(msg.encoding).lower()
    if encoding not in ENCODINGS:
        raise RosbagError(f"{topic}: image encoding {msg.encoding!r} is not one of {sorted(ENCODINGS)}")
    dtype, channels = ENCODINGS[encoding]
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    data = np.frombuffer(bytes(msg.data), np.uint8)
    if msg.step < msg.width * channels * dt.itemsize or data.size != msg.height * msg.step:
        raise CorruptMessage(
            topic,
            f"image data of {data.size} bytes does not fit height {msg.height} x step {msg.step} "
            f"for {msg.width} px of {encoding}",
        )
    rows = data.reshape(msg.height, msg.step)
    pixels = rows[:, : msg.width * channels * dt.itemsize].copy().view(dt)
    image = pixels.reshape(msg.height, msg.width, channels).astype(dtype)
    if encoding.startswith("rgb"):
        image = image[..., [2, 1, 0, 3][:channels]]
    return image[..., 0] if channels == 1 else image


def is_16_bit(msg) -> bool:
    """Whether an image message holds 16-bit pixels (``mono16``, or a 16-bit PNG), without decoding it."""
    if hasattr(msg, "format"):
        head = bytes(msg.data[:25])
        return head[:8] == PNG and len(head) == 25 and head[24] == 16  # IHDR bit depth
    return ENCODINGS.get(str(msg.encoding).lower(), (np.uint8,))[0] == np.uint16


def scale_bit_depth(image: np.ndarray, bits: int) -> np.ndarray:
    """16-bit pixels holding ``bits`` bits of data, stretched to the full 16-bit range (a 12-bit camera's
    4095 becomes 65535): read as 16 bits they would train as near-black (4095 / 65535 = 6 %)."""
    if image.dtype != np.uint16 or bits >= 16:
        return image
    return np.minimum(np.rint(image * (65535 / (2**bits - 1))), 65535).astype(np.uint16)


# distortion_model -> (our model, our field for each coefficient of D, in order)
CAMERA_INFO_MODELS: dict[str, tuple[str, tuple[str, ...]]] = {
    **{name: ("opencv", fields) for name, fields in ROS_MODELS.items()},  # plumb_bob, rational_polynomial
    "equidistant": ("kannala_brandt", ("k1", "k2", "k3", "k4")),
}


def camera_from_info(msg, topic: str) -> CameraModel:
    """The camera model of a ``sensor_msgs/CameraInfo``, for the *raw* (distorted) image.

    ``K`` gives fx, fy, cx, cy (its skew ``K[1]`` is ignored: no model has one; a warning says so), and
    ``D`` the distortion of ``distortion_model``:

    - ``plumb_bob``, 5 coefficients k1 k2 p1 p2 k3 -> ``opencv`` (OpenCV's radial-tangential model);
    - ``rational_polynomial``, 8 coefficients k1 k2 p1 p2 k3 k4 k5 k6 -> ``opencv`` (rational model);
    - either with every coefficient zero, or an empty ``distortion_model`` without distortion -> pinhole;
    - ``equidistant``, 4 coefficients k1 k2 k3 k4 -> Kannala-Brandt (``cv2.fisheye``).

    Anything else (another model, another number of coefficients) is refused, naming the topic, the model
    and the coefficient count. ``R`` (the stereo rectification) and ``P`` (the projection of the
    rectified image) are ignored: they describe ``image_rect``, not the raw image; to import rectified
    images, give a pinhole calibration file built from ``P`` instead (``--calibration NAME=FILE``).

    Refused too, naming the topic and the field: a ``K`` that is not ``[fx 0 cx 0 fy cy 0 0 1]`` (written
    column-major, ``K[8]`` not 1); a ``binning_x``/``binning_y`` above 1 or a ``roi`` smaller than the
    calibrated image (``K`` and ``D`` describe the full sensor, the images are binned or cropped from it:
    this import does not rescale the calibration); and a calibration that cannot be a real camera's
    (:func:`~fisheyedepth.cameras.base.check_plausible`).
    """
    from ..cameras.opencv import ros_matrix_fault

    K = [float(v) for v in _field(msg, "k", "K")]
    D = [float(v) for v in _field(msg, "d", "D")]
    model = str(msg.distortion_model)
    size = {"width": int(msg.width), "height": int(msg.height)}
    shape = f"{size['width']}x{size['height']}"
    instead = "give the calibration of the images as they are in the bag instead (--calibration NAME=FILE)"
    if len(K) != 9:
        raise RosbagError(f"{topic}: the CameraInfo's K has {len(K)} numbers, expected 9 (row-major 3x3)")
    if not any(K):
        raise RosbagError(
            f"{topic}: the CameraInfo's K is all zeros (an uncalibrated camera); give the camera's "
            "calibration file instead (--calibration NAME=FILE)"
        )
    if (fault := ros_matrix_fault(K)) is not None:
        raise RosbagError(f"{topic}: the CameraInfo's {fault[0]}: {fault[1]}")
    binning = {key: int(getattr(msg, key, 0)) for key in ("binning_x", "binning_y")}
    for key, factor in binning.items():
        if factor > 1:  # 0 and 1 both mean no binning
            raise RosbagError(
                f"{topic}: the CameraInfo's {key} is {factor}: its K and D describe the {shape} sensor "
                f"before binning, not the binned images, and this import does not rescale them; {instead}"
            )
    roi = getattr(msg, "roi", None)
    if roi is not None:
        x, y, w, h = (int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height))
        if (x, y) != (0, 0) or (w, h) not in ((0, 0), (size["width"], size["height"])):  # 0 0 0 0: none
            raise RosbagError(
                f"{topic}: the CameraInfo's roi (x_offset {x}, y_offset {y}, width {w}, height {h}) crops "
                f"the {shape} calibrated image: its K and D describe the whole image, not the crop, and "
                f"this import does not shift them; {instead}"
            )
    if K[1] != 0:
        log.warning("%s: the CameraInfo's K has a skew of %g, which is ignored (no camera model has one)",
                    topic, K[1])  # fmt: skip
    intrinsics = {"fx": K[0], "fy": K[4], "cx": K[2], "cy": K[5]}
    if model in ("plumb_bob", "rational_polynomial", "") and not any(D):
        data = {"model": "pinhole", **size, **intrinsics}
    elif model in CAMERA_INFO_MODELS and len(D) == len(CAMERA_INFO_MODELS[model][1]):
        ours, fields = CAMERA_INFO_MODELS[model]
        data = {"model": ours, **size, **intrinsics, **dict(zip(fields, D, strict=True))}
    else:
        expected = "; ".join(
            f"{name} with {len(fields)} ({' '.join(fields)})"
            for name, (_, fields) in CAMERA_INFO_MODELS.items()
        )
        raise RosbagError(
            f"{topic}: distortion model {model!r} with {len(D)} coefficients {D} is not supported (expected "
            f"{expected}, or no distortion); give the camera's calibration file instead "
            "(--calibration NAME=FILE)"
        )
    try:
        return CameraModel.from_dict(data)  # checks that it can be a real camera's too
    except ValueError as err:  # an impossible parameter: a zero size, a negative focal length, fx 1e30
        raise RosbagError(f"{topic}: CameraInfo {shape}, distortion {model!r}, K {K}, D {D}: {err}") from None


def _transform(t, where: str) -> np.ndarray:
    """4x4 of a ``geometry_msgs/Transform`` (parent <- child), refused naming ``where`` unless rigid."""
    r, tr = t.rotation, t.translation
    return rigid_pose([tr.x, tr.y, tr.z, r.x, r.y, r.z, r.w], where)


def rigid_pose(values, where: str) -> np.ndarray:
    """``tx ty tz qx qy qz qw`` as a 4x4 rigid transform: a unit quaternion and finite numbers
    (:func:`~fisheyedepth.geometry.rigid_transform`), else a :class:`RosbagError` naming ``where``."""
    values = np.asarray(values, dtype=float)
    try:
        q = unit_quaternion(values[3:], where)
        return rigid_transform(make_pose(quaternion_matrix(q), values[:3]), where)
    except ValueError as err:
        raise RosbagError(str(err)) from None


def chain(edges: dict[tuple[str, str], np.ndarray], parent: str, child: str) -> np.ndarray | None:
    """``T_parent_child`` through a tree of static transforms ``{(parent, child): T}``, or None."""
    graph: dict[str, list[tuple[str, np.ndarray]]] = defaultdict(list)
    for (a, b), T in edges.items():
        graph[a].append((b, T))
        graph[b].append((a, np.linalg.inv(T)))
    todo, seen = [(parent.lstrip("/"), np.eye(4))], {parent.lstrip("/")}
    while todo:
        frame, T = todo.pop()
        if frame == child.lstrip("/"):
            return T
        for nxt, step in graph[frame]:
            if nxt not in seen:
                seen.add(nxt)
                todo.append((nxt, T @ step))
    return None


def _open(bag: Path):
    from rosbags.highlevel import AnyReader

    try:
        reader = AnyReader([bag])
        reader.open()
    except Exception as err:  # rosbags raises its own types for unreadable bags
        raise RosbagError(f"{bag}: not a readable ROS 1 or ROS 2 bag ({err})") from None
    return reader


def _listed(stamps: list[int], at_most: int = 10) -> str:
    more = f" and {len(stamps) - at_most} more" if len(stamps) > at_most else ""
    return ", ".join(map(str, stamps[:at_most])) + more


def import_rosbag(
    bag: str | os.PathLike,
    out: str | os.PathLike,
    cameras: dict[str, str],
    info_topics: dict[str, str] | None = None,
    calibrations: dict[str, str | os.PathLike] | None = None,
    extrinsics: dict[str, Any] | None = None,
    odometry: str | None = None,
    tf_poses: tuple[str, str] | None = None,
    body_frame: str | None = None,
    sequence: str = "seq0",
    overwrite: bool = False,
    max_pose_gap: float | None = None,
    bit_depth: int | None = None,
    strict: bool = False,
) -> dict[str, Any]:
    """Import ``bag`` into the rig layout at ``out`` (module docstring); returns a summary.

    ``cameras``: name -> image topic. ``info_topics``: name -> CameraInfo topic (default: the image
    topic's namespace + ``/camera_info``). ``calibrations``/``extrinsics``: given per camera instead of
    the bag's (``extrinsics`` values: 4x4 camera -> body). Poses from ``odometry`` (a topic) or
    ``tf_poses`` (world frame, body frame); ``body_frame`` defaults to the odometry's child frame.
    ``max_pose_gap``: seconds; images in a longer gap of the poses are dropped (default: ``GAP_FACTOR``
    median pose intervals; a given value is written to ``rig.yaml`` so that training drops the same).
    ``bit_depth``: the bits of data in 16-bit images (default: the highest set bit over each topic).
    ``strict``: a corrupt image message stops the import instead of being skipped and counted.

    Two passes over the bag: the first reads poses, calibrations, stamps, extrinsics and 16-bit peaks and
    checks every camera, so most problems stop the import before an image is decoded; the second streams
    the images to disk one at a time (memory does not grow with the bag). ``overwrite`` replaces
    ``rig.yaml``, the cameras' calibration files and the sequence's folder; other files of ``out`` stay."""
    bag, out = Path(bag), Path(out)
    if (odometry is None) == (tf_poses is None):
        raise ValueError("poses: give exactly one of odometry=TOPIC or tf_poses=(WORLD, BODY)")
    if bit_depth is not None and not 8 <= bit_depth <= 16:
        raise ValueError(f"bit_depth: expected 8 to 16 bits, got {bit_depth}")
    if max_pose_gap is not None and not max_pose_gap > 0:
        raise ValueError(f"max_pose_gap: expected seconds > 0, got {max_pose_gap}")
    path_name(sequence, "sequence", "--sequence")  # each becomes a folder or file name under out
    for name in cameras:
        path_name(name, "camera", "--camera")
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out} exists and is not a folder")
    parts = [Path(sequence), *(Path("calibration") / f"{name}.yaml" for name in cameras), Path("rig.yaml")]
    for part in reversed(parts):  # rig.yaml first: the clash that says "this is a rig already"
        if os.path.lexists(inside(out, out / part, "--out")) and not overwrite:
            raise FileExistsError(f"{out / part} exists; pass overwrite=True (--overwrite) to replace it")
    with staged_folder(out, "importing") as staging:
        try:
            summary = _import(bag, staging, cameras, info_topics, calibrations, extrinsics, odometry,
                              tf_poses, body_frame, sequence, max_pose_gap, bit_depth, strict)  # fmt: skip
            move_into_place(staging, out, parts, overwrite)  # rig.yaml last: a rig is complete with it
        except RosbagError as err:  # named by the bag, and by the path the file would have had
            message = str(err).replace(str(staging), str(out))
            raise RosbagError(message if str(bag) in message else f"{bag}: {message}") from None
    summary["out"] = str(out)
    return summary


def _import(bag: Path, out: Path, cameras, info_topics, calibrations, extrinsics, odometry, tf_poses,
            body_frame, sequence, max_pose_gap, bit_depth, strict) -> dict[str, Any]:  # fmt: skip
    """``import_rosbag`` into the empty folder ``out``, checked by opening it with ``RigLayout``."""
    info_topics = dict(info_topics or {})
    # image_transport: <ns>/image_raw[/compressed] beside <ns>/camera_info
    for name, topic in cameras.items():
        base = topic.removesuffix("/compressed")
        info_topics.setdefault(name, base.rsplit("/", 1)[0] + "/camera_info")
    calibrations, extrinsics = dict(calibrations or {}), dict(extrinsics or {})
    by_image = {topic: name for name, topic in cameras.items()}
    by_info = {topic: name for name, topic in info_topics.items()}
    infos: dict[str, Any] = {}
    frame_ids: dict[str, str] = {}
    stamps: dict[str, list[int]] = defaultdict(list)
    sizes: dict[str, set[tuple[int, int]]] = defaultdict(set)  # of the raw Images
    peaks: dict[str, int] = {}  # of the 16-bit images
    corrupt: dict[str, dict[int, str]] = defaultdict(dict)  # stamp (or bag time) -> why
    static: dict[tuple[str, str], np.ndarray] = {}
    poses: list[tuple[int, np.ndarray]] = []

    def skip(name: str, topic: str, stamp: int, why: str) -> None:
        if strict:
            raise CorruptMessage(f"{bag}: {topic}", f"the image at {stamp} ns is corrupt ({why}); "
                                 "without --strict it would be skipped and counted")  # fmt: skip
        corrupt[name][stamp] = why

    # ---- pass 1: everything but the pixels (and the 16-bit images' peaks)
    reader = _open(bag)
    try:
        topics = {c.topic for c in reader.connections}
        for topic in list(cameras.values()) + ([odometry] if odometry else []):
            if topic not in topics:
                raise RosbagError(f"{bag}: topic {topic} is not in the bag (it has {sorted(topics)})")
        wanted = set(by_image) | set(by_info) | {odometry, "/tf_static", "/tf"}
        connections = [c for c in reader.connections if c.topic in wanted]
        for connection, bag_time, raw in tqdm(
            reader.messages(connections=connections), total=sum(c.msgcount for c in connections),
            desc=f"indexing {bag.name}", unit="msg",
        ):  # fmt: skip
            topic = connection.topic
            try:
                msg = reader.deserialize(raw, connection.msgtype)
            except Exception as err:  # a truncated or garbled message
                if topic not in by_image:
                    raise RosbagError(
                        f"{bag}: {topic}: a message at {bag_time} ns cannot be read ({err})"
                    ) from None
                skip(by_image[topic], topic, bag_time, f"cannot be deserialized: {err}")
                continue
            if topic in by_image:
                name, stamp = by_image[topic], _stamp(msg.header)
                stamps[name].append(stamp)
                frame_ids.setdefault(name, msg.header.frame_id)
                if not hasattr(msg, "format"):
                    sizes[name].add((int(msg.width), int(msg.height)))
                if is_16_bit(msg):
                    peaks.setdefault(name, 0)
                    try:
                        if bit_depth is None:  # over the whole topic: one dark frame does not decide
                            peaks[name] = max(peaks[name], int(decode_image(msg, topic).max()))
                    except CorruptMessage as err:
                        skip(name, topic, stamp, err.why)
            elif topic in by_info and by_info[topic] not in infos:
                infos[by_info[topic]] = msg
                frame_ids[by_info[topic]] = msg.header.frame_id
            elif topic == odometry:
                p, q = msg.pose.pose.position, msg.pose.pose.orientation
                poses.append((_stamp(msg.header), np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w], float)))
                body_frame = body_frame or msg.child_frame_id
            elif topic in ("/tf_static", "/tf"):
                for t in msg.transforms:
                    edge = (t.header.frame_id.lstrip("/"), t.child_frame_id.lstrip("/"))
                    if topic == "/tf_static":
                        static[edge] = _transform(t.transform, f"{bag}: /tf_static {edge[0]} -> {edge[1]}")
                    elif tf_poses and edge == (tf_poses[0].lstrip("/"), tf_poses[1].lstrip("/")):
                        r, tr = t.transform.rotation, t.transform.translation
                        values = [tr.x, tr.y, tr.z, r.x, r.y, r.z, r.w]
                        poses.append((_stamp(t.header), np.array(values, float)))
    finally:
        reader.close()
    if tf_poses:
        body_frame = body_frame or tf_poses[1]
    source = odometry or f"/tf {tf_poses[0]} -> {tf_poses[1]}"
    poses.sort(key=lambda p: p[0])
    repeats = [i for i in range(1, len(poses)) if poses[i][0] == poses[i - 1][0]]
    clashes = [i for i in repeats if not np.array_equal(poses[i][1], poses[i - 1][1])]
    if clashes:
        raise RosbagError(
            f"{bag}: {source}: {len(clashes)} stamps carry two different poses (the first at "
            f"{poses[clashes[0]][0]} ns); a pose file holds one pose per stamp"
        )
    poses = [p for i, p in enumerate(poses) if i == 0 or p[0] != poses[i - 1][0]]  # exact repeats: one
    for stamp, values in poses:
        rigid_pose(values, f"{bag}: {source}: the pose at {stamp} ns")
    if len(poses) < 2:
        raise RosbagError(f"{bag}: {source}: fewer than two poses")
    times = np.array([p[0] for p in poses], np.int64)
    first, last, gap = times[0], times[-1], max_gap_ns(times, max_pose_gap)

    # ---- every camera checked before an image is decoded
    models, rig_cameras, keep, bits = {}, [], {}, {}
    summary: dict[str, Any] = {
        "images": {},
        "outside_poses": {},
        "pose_gaps": {},
        "duplicate_stamps": {},
        "corrupt": {},
        "poses": len(poses),
        "repeated_poses": len(repeats),
        "max_pose_gap": gap * 1e-9,
        "bit_depth": {},
    }
    for name, topic in cameras.items():
        if not stamps[name]:
            raise RosbagError(f"{bag}: topic {topic} has no images")
        if name in calibrations:
            camera, origin = load_camera(calibrations[name]), str(calibrations[name])
        elif name in infos:
            camera, origin = camera_from_info(infos[name], f"{bag}: {info_topics[name]}"), info_topics[name]
        else:
            raise RosbagError(
                f"{bag}: no CameraInfo on {info_topics[name]} for camera {name}; "
                f"give --calibration {name}=FILE"
            )
        models[name] = camera
        wrong = sorted(sizes[name] - {(camera.width, camera.height)})
        if wrong:  # the dataset refuses an image of another size than its calibration
            raise RosbagError(
                f"{bag}: {topic}: images are {wrong[0][0]}x{wrong[0][1]}, but the calibration ({origin}) "
                f"is {camera.width}x{camera.height}"
            )
        if name in extrinsics:
            cam_to_body = np.asarray(extrinsics[name], float)
        else:
            cam_to_body = chain(static, body_frame, frame_ids.get(name, ""))
            if cam_to_body is None:
                raise RosbagError(
                    f"{bag}: /tf_static has no chain from the body frame {body_frame!r} to camera {name}'s "
                    f"frame {frame_ids.get(name)!r}; give its extrinsic (--extrinsics)"
                )
        inside = sorted(s for s in stamps[name] if first <= s <= last and s not in corrupt[name])
        gapped = in_pose_gap(times, inside, gap)
        keep[name] = {s for s, g in zip(inside, gapped, strict=True) if not g}
        summary["outside_poses"][name] = sum(not first <= s <= last for s in stamps[name])
        summary["pose_gaps"][name] = len({s for s, g in zip(inside, gapped, strict=True) if g})
        summary["duplicate_stamps"][name] = len(inside) - len(set(inside))
        if summary["pose_gaps"][name]:
            log.warning(
                "%s: %s: %d images lie in gaps of %s longer than %.3f s (max_pose_gap; the longest gap is "
                "%.3f s) and are dropped",
                bag, topic, summary["pose_gaps"][name], source, gap * 1e-9, np.diff(times).max() * 1e-9,
            )  # fmt: skip
        if not keep[name]:
            raise RosbagError(
                f"{bag}: {topic}: none of its {len(stamps[name])} images lies within the poses' time range "
                f"[{first}, {last}] ns outside a gap longer than {gap * 1e-9:.3f} s (header stamps in "
                "another clock?)"
            )
        if name in peaks:
            bits[name] = bit_depth or max(8, peaks[name].bit_length())
            summary["bit_depth"][name] = bits[name]
            log.info("%s: %s: 16-bit images with %d bits of data (highest value %d), scaled to 16 bits",
                     bag, topic, bits[name], peaks[name])  # fmt: skip
        entry = {"name": name, "calibration": f"calibration/{name}.yaml", "cam_to_body": cam_to_body.tolist()}
        rig_cameras.append(entry)

    # ---- pass 2: the images, one at a time (a stamp seen twice keeps its first readable image)
    reader = _open(bag)
    try:
        connections = [c for c in reader.connections if c.topic in by_image]
        for connection, _, raw in tqdm(
            reader.messages(connections=connections), total=sum(c.msgcount for c in connections),
            desc="writing images", unit="image",
        ):  # fmt: skip
            name, topic = by_image[connection.topic], connection.topic
            try:
                msg = reader.deserialize(raw, connection.msgtype)
            except Exception:  # counted in pass 1
                continue
            stamp = _stamp(msg.header)
            if stamp not in keep[name]:
                continue
            try:
                image = decode_image(msg, topic)
            except CorruptMessage as err:
                skip(name, topic, stamp, err.why)
                continue
            keep[name].discard(stamp)
            camera = models[name]
            if (image.shape[1], image.shape[0]) != (camera.width, camera.height):
                raise RosbagError(
                    f"{bag}: {topic}: the image at {stamp} ns is {image.shape[1]}x{image.shape[0]}, but the "
                    f"calibration is {camera.width}x{camera.height}"
                )
            ok, png = cv2.imencode(".png", scale_bit_depth(image, bits.get(name, 16)))
            if not ok:
                raise RosbagError(f"{bag}: {topic}: the image at {stamp} ns could not be encoded as PNG")
            folder = out / sequence / "images" / name
            folder.mkdir(parents=True, exist_ok=True)
            (folder / f"{stamp}.png").write_bytes(png.tobytes())
            summary["images"][name] = summary["images"].get(name, 0) + 1
    finally:
        reader.close()
    for name, topic in cameras.items():
        summary["corrupt"][name] = len(corrupt[name])
        if corrupt[name]:
            why = next(iter(corrupt[name].values()))
            log.warning("%s: %s: %d corrupt image messages skipped, at %s ns (%s)", bag, topic,
                        len(corrupt[name]), _listed(sorted(corrupt[name])), why)  # fmt: skip
        if not summary["images"].get(name):
            raise RosbagError(f"{bag}: {topic}: no readable image within the poses")
    for name, camera in models.items():
        save_camera(camera, out / "calibration" / f"{name}.yaml")
    lines = [f"{s} " + " ".join(repr(float(v)) for v in values) for s, values in poses]
    header = f"# timestamp_ns tx ty tz qx qy qz qw ({body_frame} -> world), from {odometry or '/tf'}\n"
    (out / sequence).mkdir(parents=True, exist_ok=True)
    (out / sequence / "poses.txt").write_text(header + "\n".join(lines) + "\n")
    rig = {"cameras": rig_cameras, "source": f"ROS bag {bag} (fisheyedepth.data.rosbag)"}
    if max_pose_gap is not None:
        rig["max_pose_gap"] = float(max_pose_gap)
    (out / "rig.yaml").write_text(yaml.safe_dump(rig, sort_keys=False, width=120))
    _check_loads(bag, out, sequence, summary["images"])
    return summary


def _check_loads(bag: Path, out: Path, sequence: str, counts: dict[str, int]) -> None:
    """Open the finished import as training will (``RigLayout``, the calibrations, an image per camera):
    whatever the loader would refuse stops the import before it is moved into place."""
    try:
        layout = RigLayout(out)
        for name, count in counts.items():
            frames = layout.frames(sequence, name)
            if len(frames) != count:
                raise ValueError(f"the rig layout keeps {len(frames)} of the {count} images of {name}")
            camera = layout.cameras[name].camera
            image = read_image(layout.image(sequence, name, frames[0])).bgr
            if image.shape[1::-1] != (camera.width, camera.height):
                raise ValueError(f"{name}: image {image.shape[1]}x{image.shape[0]}, calibration "
                                 f"{camera.width}x{camera.height}")  # fmt: skip
    except (ValueError, FileNotFoundError) as err:
        raise RosbagError(f"{bag}: the import would not load for training: {err}") from None
