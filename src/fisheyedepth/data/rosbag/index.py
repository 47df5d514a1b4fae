"""The first pass over a bag: everything but the pixels (poses, calibrations, stamps, extrinsics and the
16-bit images' peaks) read into a :class:`BagIndex`, then every camera checked against it
(:func:`plan_cameras`), so that most problems stop the import before an image is decoded."""

from __future__ import annotations

import logging
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from tqdm import tqdm

from ...cameras import CameraModel, load_camera
from ..layouts import in_pose_gap, max_gap_ns
from .messages import (
    CorruptMessage,
    RosbagError,
    camera_from_info,
    chain,
    decode_image,
    is_16_bit,
    open_bag,
    rigid_pose,
    stamp_ns,
    transform,
)
from .options import BagImport

log = logging.getLogger("fisheyedepth.data.rosbag")


@dataclass
class BagIndex:
    """What the first pass found: per camera its CameraInfo, frame id, image stamps, raw image sizes,
    16-bit peak and corrupt messages (stamp -> why); the static transforms; the poses, sorted, one per
    stamp (``repeats``: exact repeats dropped); the body frame."""

    job: BagImport
    infos: dict[str, Any] = field(default_factory=dict)
    frame_ids: dict[str, str] = field(default_factory=dict)
    stamps: dict[str, list[int]] = field(default_factory=lambda: defaultdict(list))
    sizes: dict[str, set[tuple[int, int]]] = field(default_factory=lambda: defaultdict(set))
    peaks: dict[str, int] = field(default_factory=dict)
    corrupt: dict[str, dict[int, str]] = field(default_factory=lambda: defaultdict(dict))
    static: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)
    poses: list[tuple[int, np.ndarray]] = field(default_factory=list)
    repeats: int = 0
    body_frame: str | None = None

    def skip(self, name: str, topic: str, stamp: int, why: str) -> None:
        """A corrupt image message: counted, or with ``strict`` the import's end."""
        if self.job.strict:
            raise CorruptMessage(f"{self.job.bag}: {topic}", f"the image at {stamp} ns is corrupt ({why}); "
                                 "without --strict it would be skipped and counted")  # fmt: skip
        self.corrupt[name][stamp] = why


@dataclass
class CameraPlan:
    """What the second pass writes: each camera's model, its rig entry, the stamps to keep and its bits
    of data (16-bit images); and the summary so far."""

    models: dict[str, CameraModel]
    rig_cameras: list[dict[str, Any]]
    keep: dict[str, set[int]]
    bits: dict[str, int]
    summary: dict[str, Any]


def index_bag(job: BagImport) -> BagIndex:
    """The first pass (module docstring), the poses checked: one pose per stamp, each rigid, two or more."""
    bag, cameras, odometry, tf_poses = job.bag, job.cameras, job.odometry, job.tf_poses
    by_image = {topic: name for name, topic in cameras.items()}
    by_info = {topic: name for name, topic in job.info_topics.items()}
    found = BagIndex(job, body_frame=job.body_frame)
    reader = open_bag(bag)
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
                found.skip(by_image[topic], topic, bag_time, f"cannot be deserialized: {err}")
                continue
            if topic in by_image:
                _image(found, by_image[topic], topic, msg)
            elif topic in by_info and by_info[topic] not in found.infos:
                found.infos[by_info[topic]] = msg
                found.frame_ids[by_info[topic]] = msg.header.frame_id
            elif topic == odometry:
                p, q = msg.pose.pose.position, msg.pose.pose.orientation
                found.poses.append(
                    (stamp_ns(msg.header), np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w], float))
                )
                found.body_frame = found.body_frame or msg.child_frame_id
            elif topic in ("/tf_static", "/tf"):
                _transforms(found, topic, msg)
    finally:
        reader.close()
    if tf_poses:
        found.body_frame = found.body_frame or tf_poses[1]
    _check_poses(found)
    return found


def _image(found: BagIndex, name: str, topic: str, msg) -> None:
    stamp = stamp_ns(msg.header)
    found.stamps[name].append(stamp)
    found.frame_ids.setdefault(name, msg.header.frame_id)
    if not hasattr(msg, "format"):
        found.sizes[name].add((int(msg.width), int(msg.height)))
    if is_16_bit(msg):
        found.peaks.setdefault(name, 0)
        try:
            if found.job.bit_depth is None:  # over the whole topic: one dark frame does not decide
                found.peaks[name] = max(found.peaks[name], int(decode_image(msg, topic).max()))
        except CorruptMessage as err:
            found.skip(name, topic, stamp, err.why)


def _transforms(found: BagIndex, topic: str, msg) -> None:
    tf_poses = found.job.tf_poses
    for t in msg.transforms:
        edge = (t.header.frame_id.lstrip("/"), t.child_frame_id.lstrip("/"))
        if topic == "/tf_static":
            found.static[edge] = transform(t.transform, f"{found.job.bag}: /tf_static {edge[0]} -> {edge[1]}")
        elif tf_poses and edge == (tf_poses[0].lstrip("/"), tf_poses[1].lstrip("/")):
            r, tr = t.transform.rotation, t.transform.translation
            found.poses.append((stamp_ns(t.header), np.array([tr.x, tr.y, tr.z, r.x, r.y, r.z, r.w], float)))


def _check_poses(found: BagIndex) -> None:
    bag, source, poses = found.job.bag, found.job.pose_source, found.poses
    poses.sort(key=lambda p: p[0])
    repeats = [i for i in range(1, len(poses)) if poses[i][0] == poses[i - 1][0]]
    clashes = [i for i in repeats if not np.array_equal(poses[i][1], poses[i - 1][1])]
    if clashes:
        raise RosbagError(
            f"{bag}: {source}: {len(clashes)} stamps carry two different poses (the first at "
            f"{poses[clashes[0]][0]} ns); a pose file holds one pose per stamp"
        )
    found.poses = [p for i, p in enumerate(poses) if i == 0 or p[0] != poses[i - 1][0]]  # exact repeats: one
    found.repeats = len(repeats)
    for stamp, values in found.poses:
        rigid_pose(values, f"{bag}: {source}: the pose at {stamp} ns")
    if len(found.poses) < 2:
        raise RosbagError(f"{bag}: {source}: fewer than two poses")


def plan_cameras(found: BagIndex) -> CameraPlan:
    """Every camera checked before an image is decoded: images on its topic, a calibration (given, or its
    CameraInfo) of its images' size, an extrinsic (given, or ``/tf_static``'s chain from the body frame),
    images within the poses' time range outside their gaps; and which stamps the second pass keeps."""
    job = found.job
    bag, source = job.bag, job.pose_source
    times = np.array([p[0] for p in found.poses], np.int64)
    first, last, gap = times[0], times[-1], max_gap_ns(times, job.max_pose_gap)
    plan = CameraPlan({}, [], {}, {}, {
        "images": {},
        "outside_poses": {},
        "pose_gaps": {},
        "duplicate_stamps": {},
        "corrupt": {},
        "poses": len(found.poses),
        "repeated_poses": found.repeats,
        "max_pose_gap": gap * 1e-9,
        "bit_depth": {},
    })  # fmt: skip
    summary = plan.summary
    for name, topic in job.cameras.items():
        stamps = found.stamps[name]
        if not stamps:
            raise RosbagError(f"{bag}: topic {topic} has no images")
        if name in job.calibrations:
            camera, origin = load_camera(job.calibrations[name]), str(job.calibrations[name])
        elif name in found.infos:
            info = job.info_topics[name]
            camera, origin = camera_from_info(found.infos[name], f"{bag}: {info}"), info
        else:
            raise RosbagError(
                f"{bag}: no CameraInfo on {job.info_topics[name]} for camera {name}; "
                f"give --calibration {name}=FILE"
            )
        plan.models[name] = camera
        wrong = sorted(found.sizes[name] - {(camera.width, camera.height)})
        if wrong:  # the dataset refuses an image of another size than its calibration
            raise RosbagError(
                f"{bag}: {topic}: images are {wrong[0][0]}x{wrong[0][1]}, but the calibration ({origin}) "
                f"is {camera.width}x{camera.height}"
            )
        if name in job.extrinsics:
            cam_to_body = np.asarray(job.extrinsics[name], float)
        else:
            cam_to_body = chain(found.static, found.body_frame, found.frame_ids.get(name, ""))
            if cam_to_body is None:
                raise RosbagError(
                    f"{bag}: /tf_static has no chain from the body frame {found.body_frame!r} to camera "
                    f"{name}'s frame {found.frame_ids.get(name)!r}; give its extrinsic (--extrinsics)"
                )
        inside = sorted(s for s in stamps if first <= s <= last and s not in found.corrupt[name])
        gapped = in_pose_gap(times, inside, gap)
        plan.keep[name] = {s for s, g in zip(inside, gapped, strict=True) if not g}
        summary["outside_poses"][name] = sum(not first <= s <= last for s in stamps)
        summary["pose_gaps"][name] = len({s for s, g in zip(inside, gapped, strict=True) if g})
        summary["duplicate_stamps"][name] = len(inside) - len(set(inside))
        if summary["pose_gaps"][name]:
            log.warning(
                "%s: %s: %d images lie in gaps of %s longer than %.3f s (max_pose_gap; the longest gap is "
                "%.3f s) and are dropped",
                bag, topic, summary["pose_gaps"][name], source, gap * 1e-9, np.diff(times).max() * 1e-9,
            )  # fmt: skip
        if not plan.keep[name]:
            raise RosbagError(
                f"{bag}: {topic}: none of its {len(stamps)} images lies within the poses' time range "
                f"[{first}, {last}] ns outside a gap longer than {gap * 1e-9:.3f} s (header stamps in "
                "another clock?)"
            )
        if name in found.peaks:
            plan.bits[name] = job.bit_depth or max(8, found.peaks[name].bit_length())
            summary["bit_depth"][name] = plan.bits[name]
            log.info("%s: %s: 16-bit images with %d bits of data (highest value %d), scaled to 16 bits",
                     bag, topic, plan.bits[name], found.peaks[name])  # fmt: skip
        ros = {
            "image_topic": topic,
            **({"frame_id": found.frame_ids[name]} if found.frame_ids.get(name) else {}),
        }
        plan.rig_cameras.append({"name": name, "calibration": f"calibration/{name}.yaml",
                                 "cam_to_body": cam_to_body.tolist(), "ros": ros})  # fmt: skip
    return plan
