"""ROS bags into the robot-rig layout (docs/data-format.md), with the pure-Python ``rosbags`` library.

``import_rosbag(bag, out, cameras={name: image_topic}, ...)`` reads a ROS 1 ``.bag`` or a ROS 2 bag (a
folder with ``metadata.yaml`` and sqlite3 ``.db3`` or ``.mcap`` files) and writes:

- ``<sequence>/images/<camera>/<stamp_ns>.png`` from ``sensor_msgs/Image`` (mono8, mono16, rgb8,
  bgr8, rgba8, bgra8) or ``sensor_msgs/CompressedImage``, stamped by their headers;
- ``calibration/<camera>.yaml`` from the camera's ``sensor_msgs/CameraInfo`` (``equidistant`` ->
  Kannala-Brandt; ``plumb_bob``/``rational_polynomial`` without distortion -> pinhole; any other
  model is refused, naming the topic and the model) or from a calibration file the user gives;
- ``rig.yaml`` with each camera's ``cam_to_body`` from ``/tf_static`` (the chain from the body frame
  to the camera's ``frame_id``) or given;
- ``<sequence>/poses.txt`` from ``nav_msgs/Odometry`` (``--odometry``) or from ``/tf``
  (``--tf-poses WORLD BODY``, a direct edge). The rig layout interpolates them to each image's stamp;
  images outside the poses' time range are dropped here and counted.

Nothing is overwritten without ``overwrite``; every file is written atomically.
"""

from __future__ import annotations

import os
from collections import defaultdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from tqdm import tqdm

from ..cameras import CameraModel, KannalaBrandtCamera, PinholeCamera, load_camera, save_camera
from ..geometry import make_pose
from ..utils import atomic_write_bytes, atomic_write_text
from .layouts import _transform as read_transform
from .layouts import quaternion_matrix

ENCODINGS = {"mono8": (np.uint8, 1), "mono16": (np.uint16, 1), "rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3),
             "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4)}  # fmt: skip


class RosbagError(ValueError):
    """Something in the bag cannot be imported: names the bag, the topic and what."""


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
            raise RosbagError(f"{topic}: a CompressedImage ({msg.format}) could not be decoded")
        return image
    encoding = str(msg.encoding).lower()
    if encoding not in ENCODINGS:
        raise RosbagError(f"{topic}: image encoding {msg.encoding!r} is not one of {sorted(ENCODINGS)}")
    dtype, channels = ENCODINGS[encoding]
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    data = np.frombuffer(bytes(msg.data), np.uint8)
    if msg.step < msg.width * channels * dt.itemsize or data.size != msg.height * msg.step:
        raise RosbagError(
            f"{topic}: image data of {data.size} bytes does not fit height {msg.height} x step {msg.step} "
            f"for {msg.width} px of {encoding}"
        )
    rows = data.reshape(msg.height, msg.step)
    pixels = rows[:, : msg.width * channels * dt.itemsize].copy().view(dt)
    image = pixels.reshape(msg.height, msg.width, channels).astype(dtype)
    if encoding.startswith("rgb"):
        image = image[..., [2, 1, 0, 3][:channels]]
    return image[..., 0] if channels == 1 else image


def camera_from_info(msg, topic: str) -> CameraModel:
    """The camera model of a ``sensor_msgs/CameraInfo``."""
    K = [float(v) for v in _field(msg, "k", "K")]
    D = [float(v) for v in _field(msg, "d", "D")]
    model = str(msg.distortion_model)
    size = {"width": int(msg.width), "height": int(msg.height)}
    intrinsics = {"fx": K[0], "fy": K[4], "cx": K[2], "cy": K[5]}
    if model == "equidistant":
        if len(D) != 4:
            raise RosbagError(f"{topic}: 'equidistant' needs 4 coefficients, got {len(D)}")
        return KannalaBrandtCamera(**size, **intrinsics, k1=D[0], k2=D[1], k3=D[2], k4=D[3])
    if model in ("plumb_bob", "rational_polynomial", "") and not any(D):
        return PinholeCamera(**size, **intrinsics)
    raise RosbagError(
        f"{topic}: distortion model {model!r} with coefficients {D} is not supported (equidistant, or "
        "none); give the camera's calibration file instead (--calibration NAME=FILE)"
    )


def _transform(t) -> np.ndarray:
    """4x4 of a ``geometry_msgs/Transform`` (parent <- child)."""
    q = np.array([t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w], float)
    R = quaternion_matrix(q / np.linalg.norm(q))
    return make_pose(R, np.array([t.translation.x, t.translation.y, t.translation.z], float)).numpy()


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
) -> dict[str, Any]:
    """Import ``bag`` into the rig layout at ``out`` (module docstring); returns a summary.

    ``cameras``: name -> image topic. ``info_topics``: name -> CameraInfo topic (default: the image
    topic's namespace + ``/camera_info``). ``calibrations``/``extrinsics``: given per camera instead of
    the bag's (``extrinsics`` values: 4x4 camera -> body). Poses from ``odometry`` (a topic) or
    ``tf_poses`` (world frame, body frame); ``body_frame`` defaults to the odometry's child frame.

    Two passes over the bag: the first reads poses, calibrations, frames and extrinsics and checks every
    camera, so a problem stops the import before anything is written; the second streams the images to
    disk one at a time (memory does not grow with the bag)."""
    bag, out = Path(bag), Path(out)
    if (odometry is None) == (tf_poses is None):
        raise ValueError("poses: give exactly one of odometry=TOPIC or tf_poses=(WORLD, BODY)")
    if (out / "rig.yaml").exists() and not overwrite:
        raise FileExistsError(f"{out / 'rig.yaml'} exists; pass overwrite=True (--overwrite) to replace it")
    info_topics = dict(info_topics or {})
    for (
        name,
        topic,
    ) in cameras.items():  # image_transport: <ns>/image_raw[/compressed] beside <ns>/camera_info
        base = topic.removesuffix("/compressed")
        info_topics.setdefault(name, base.rsplit("/", 1)[0] + "/camera_info")
    calibrations, extrinsics = dict(calibrations or {}), dict(extrinsics or {})
    by_image = {topic: name for name, topic in cameras.items()}
    by_info = {topic: name for name, topic in info_topics.items()}
    infos: dict[str, Any] = {}
    frame_ids: dict[str, str] = {}
    stamps: dict[str, list[int]] = defaultdict(list)
    static: dict[tuple[str, str], np.ndarray] = {}
    poses: list[tuple[int, np.ndarray]] = []

    # ---- pass 1: everything but the pixels
    reader = _open(bag)
    try:
        topics = {c.topic for c in reader.connections}
        for topic in list(cameras.values()) + ([odometry] if odometry else []):
            if topic not in topics:
                raise RosbagError(f"{bag}: topic {topic} is not in the bag (it has {sorted(topics)})")
        wanted = set(by_image) | set(by_info) | {odometry, "/tf_static", "/tf"}
        connections = [c for c in reader.connections if c.topic in wanted]
        for connection, _, raw in tqdm(
            reader.messages(connections=connections), total=sum(c.msgcount for c in connections),
            desc=f"indexing {bag.name}", unit="msg",
        ):  # fmt: skip
            topic = connection.topic
            msg = reader.deserialize(raw, connection.msgtype)
            if topic in by_image:
                name = by_image[topic]
                stamps[name].append(_stamp(msg.header))
                frame_ids.setdefault(name, msg.header.frame_id)
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
                        static[edge] = _transform(t.transform)
                    elif tf_poses and edge == (tf_poses[0].lstrip("/"), tf_poses[1].lstrip("/")):
                        r, tr = t.transform.rotation, t.transform.translation
                        values = [tr.x, tr.y, tr.z, r.x, r.y, r.z, r.w]
                        poses.append((_stamp(t.header), np.array(values, float)))
    finally:
        reader.close()
    if tf_poses:
        body_frame = body_frame or tf_poses[1]
    if len(poses) < 2:
        source = odometry or f"/tf {tf_poses[0]} -> {tf_poses[1]}"
        raise RosbagError(f"{bag}: {source}: fewer than two poses")
    poses.sort(key=lambda p: p[0])
    first, last = poses[0][0], poses[-1][0]

    # ---- every camera checked before anything is written
    models, rig_cameras, keep = {}, [], {}
    summary = {
        "images": {},
        "outside_poses": {},
        "duplicate_stamps": {},
        "poses": len(poses),
        "out": str(out),
    }
    for name, topic in cameras.items():
        if not stamps[name]:
            raise RosbagError(f"{bag}: topic {topic} has no images")
        if name in calibrations:
            models[name] = load_camera(calibrations[name])
        elif name in infos:
            models[name] = camera_from_info(infos[name], info_topics[name])
        else:
            raise RosbagError(
                f"{bag}: no CameraInfo on {info_topics[name]} for camera {name}; "
                f"give --calibration {name}=FILE"
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
        inside = sorted(s for s in stamps[name] if first <= s <= last)
        keep[name] = set(inside)
        summary["images"][name] = len(keep[name])
        summary["outside_poses"][name] = len(stamps[name]) - len(inside)
        summary["duplicate_stamps"][name] = len(inside) - len(keep[name])
        if not keep[name]:
            raise RosbagError(
                f"{bag}: {topic}: none of its {len(stamps[name])} images lies within the poses' time range "
                f"[{first}, {last}] ns (header stamps in another clock?)"
            )
        rig_cameras.append(
            {"name": name, "calibration": f"calibration/{name}.yaml", "cam_to_body": cam_to_body.tolist()}
        )
    if not overwrite:
        for name in cameras:
            for stamp in keep[name]:
                if (out / sequence / "images" / name / f"{stamp}.png").exists():
                    raise FileExistsError(f"{out / sequence / 'images' / name / f'{stamp}.png'} exists; "
                                          "pass overwrite=True (--overwrite)")  # fmt: skip

    # ---- pass 2: the images, one at a time (a stamp seen twice keeps its first image)
    reader = _open(bag)
    try:
        connections = [c for c in reader.connections if c.topic in by_image]
        for connection, _, raw in tqdm(
            reader.messages(connections=connections), total=sum(c.msgcount for c in connections),
            desc="writing images", unit="image",
        ):  # fmt: skip
            name, topic = by_image[connection.topic], connection.topic
            msg = reader.deserialize(raw, connection.msgtype)
            stamp = _stamp(msg.header)
            if stamp not in keep[name]:
                continue
            keep[name].discard(stamp)
            image = decode_image(msg, topic)
            camera = models[name]
            if image.shape[1] * camera.height != image.shape[0] * camera.width:
                raise RosbagError(
                    f"{topic}: image {image.shape[1]}x{image.shape[0]} at {stamp} ns, but the calibration is "
                    f"{camera.width}x{camera.height} (another aspect ratio)"
                )
            ok, png = cv2.imencode(".png", image)
            if not ok:
                raise RosbagError(f"{topic}: the image at {stamp} ns could not be encoded as PNG")
            atomic_write_bytes(out / sequence / "images" / name / f"{stamp}.png", png.tobytes())
    finally:
        reader.close()
    for name, camera in models.items():
        save_camera(camera, out / "calibration" / f"{name}.yaml", overwrite=overwrite)
    lines = [f"{s} " + " ".join(repr(float(v)) for v in values) for s, values in poses]
    header = f"# timestamp_ns tx ty tz qx qy qz qw ({body_frame} -> world), from {odometry or '/tf'}\n"
    atomic_write_text(out / sequence / "poses.txt", header + "\n".join(lines) + "\n")
    rig = {"cameras": rig_cameras, "source": f"ROS bag {bag} (fisheyedepth.data.rosbag)"}
    atomic_write_bytes(out / "rig.yaml", yaml.safe_dump(rig, sort_keys=False, width=120).encode())
    return summary


def _pairs(values: list[str], what: str) -> dict[str, str]:
    out = {}
    for value in values or []:
        if "=" not in value:
            raise SystemExit(f"error: {what}: expected NAME=VALUE, got {value!r}")
        name, _, rest = value.partition("=")
        out[name] = rest
    return out


def main(argv=None) -> int:
    """Console script ``fisheyedepth-import-rosbag`` (also ``scripts/import_rosbag.py``)."""
    import argparse
    import json

    parser = argparse.ArgumentParser(
        description="Import a ROS 1 or ROS 2 bag into the rig layout (docs/data-format.md).",
        epilog="example: fisheyedepth-import-rosbag run.bag --out data/my_rig "
        "--camera front=/front/image_raw --camera left=/left/image_raw/compressed --odometry /odom",
    )
    parser.add_argument("bag", type=Path, help="a ROS 1 .bag, or a ROS 2 bag folder (.db3 or .mcap)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--camera", action="append", required=True, metavar="NAME=IMAGE_TOPIC")
    parser.add_argument(
        "--camera-info", action="append", metavar="NAME=TOPIC", help="default: <ns>/camera_info"
    )
    parser.add_argument("--calibration", action="append", metavar="NAME=FILE", help="instead of CameraInfo")
    parser.add_argument(
        "--extrinsics", type=Path, help="YAML {NAME: 4x4 camera->body}, instead of /tf_static"
    )
    poses = parser.add_mutually_exclusive_group(required=True)
    poses.add_argument("--odometry", metavar="TOPIC", help="nav_msgs/Odometry poses of the body")
    poses.add_argument("--tf-poses", nargs=2, metavar=("WORLD", "BODY"), help="body poses from /tf")
    parser.add_argument("--body-frame", help="default: the odometry's child_frame_id (or BODY)")
    parser.add_argument("--sequence", default="seq0")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    try:
        extrinsics = {}
        if args.extrinsics:
            data = yaml.safe_load(args.extrinsics.read_text())
            if not isinstance(data, dict):
                raise ValueError(f"{args.extrinsics}: expected a mapping NAME: 4x4 camera -> body")
            extrinsics = {k: read_transform(v, args.extrinsics, k) for k, v in data.items()}
        summary = import_rosbag(
            args.bag, args.out, _pairs(args.camera, "--camera"), _pairs(args.camera_info, "--camera-info"),
            _pairs(args.calibration, "--calibration"), extrinsics, args.odometry,
            tuple(args.tf_poses) if args.tf_poses else None, args.body_frame, args.sequence, args.overwrite,
        )  # fmt: skip
    except (RosbagError, FileExistsError, FileNotFoundError, ValueError, yaml.YAMLError) as err:
        print(f"error: {err}")
        return 2
    print(json.dumps(summary, indent=2))
    return 0
