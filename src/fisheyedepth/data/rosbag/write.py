"""The second pass over a bag: its images streamed to disk one at a time (memory does not grow with the
bag), then the calibrations, the poses and ``rig.yaml`` written, and the result opened as training will
open it (:func:`check_loads`)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import cv2
import yaml
from tqdm import tqdm

from ...cameras import save_camera
from ..layouts import RigLayout
from .index import BagIndex, CameraPlan
from .messages import CorruptMessage, RosbagError, decode_image, listed, open_bag, scale_bit_depth, stamp_ns

log = logging.getLogger("fisheyedepth.data.rosbag")


def write_import(found: BagIndex, plan: CameraPlan, out: Path) -> dict[str, Any]:
    """Every kept image (a stamp seen twice keeps its first readable image), the calibrations, the poses
    and ``rig.yaml`` into the empty folder ``out``, checked by opening it with ``RigLayout``; the summary."""
    job, summary = found.job, plan.summary
    bag, sequence = job.bag, job.sequence
    by_image = {topic: name for name, topic in job.cameras.items()}
    reader = open_bag(bag)
    try:
        connections = [c for c in reader.connections if c.topic in by_image]
        for connection, _, raw in tqdm(
            reader.messages(connections=connections), total=sum(c.msgcount for c in connections),
            desc="writing images", unit="image",
        ):  # fmt: skip
            name, topic = by_image[connection.topic], connection.topic
            try:
                msg = reader.deserialize(raw, connection.msgtype)
            except Exception:  # counted in the first pass
                continue
            stamp = stamp_ns(msg.header)
            if stamp not in plan.keep[name]:
                continue
            try:
                image = decode_image(msg, topic)
            except CorruptMessage as err:
                found.skip(name, topic, stamp, err.why)
                continue
            plan.keep[name].discard(stamp)
            camera = plan.models[name]
            if (image.shape[1], image.shape[0]) != (camera.width, camera.height):
                raise RosbagError(
                    f"{bag}: {topic}: the image at {stamp} ns is {image.shape[1]}x{image.shape[0]}, but the "
                    f"calibration is {camera.width}x{camera.height}"
                )
            ok, png = cv2.imencode(".png", scale_bit_depth(image, plan.bits.get(name, 16)))
            if not ok:
                raise RosbagError(f"{bag}: {topic}: the image at {stamp} ns could not be encoded as PNG")
            folder = out / sequence / "images" / name
            folder.mkdir(parents=True, exist_ok=True)
            (folder / f"{stamp}.png").write_bytes(png.tobytes())
            summary["images"][name] = summary["images"].get(name, 0) + 1
    finally:
        reader.close()
    for name, topic in job.cameras.items():
        corrupt = found.corrupt[name]
        summary["corrupt"][name] = len(corrupt)
        if corrupt:
            log.warning("%s: %s: %d corrupt image messages skipped, at %s ns (%s)", bag, topic,
                        len(corrupt), listed(sorted(corrupt)), next(iter(corrupt.values())))  # fmt: skip
        if not summary["images"].get(name):
            raise RosbagError(f"{bag}: {topic}: no readable image within the poses")
    for name, camera in plan.models.items():
        save_camera(camera, out / "calibration" / f"{name}.yaml")
    lines = [f"{s} " + " ".join(repr(float(v)) for v in values) for s, values in found.poses]
    header = (
        f"# timestamp_ns tx ty tz qx qy qz qw ({found.body_frame} -> world), from {job.odometry or '/tf'}\n"
    )
    (out / sequence).mkdir(parents=True, exist_ok=True)
    (out / sequence / "poses.txt").write_text(header + "\n".join(lines) + "\n")
    rig = {"cameras": plan.rig_cameras, "source": f"ROS bag {bag} (fisheyedepth.data.rosbag)"}
    if job.max_pose_gap is not None:
        rig["max_pose_gap"] = float(job.max_pose_gap)
    (out / "rig.yaml").write_text(yaml.safe_dump(rig, sort_keys=False, width=120))
    check_loads(bag, out, sequence, summary["images"])
    return summary


def check_loads(bag: Path, out: Path, sequence: str, counts: dict[str, int]) -> None:
    """Open the finished import as training will (``RigLayout``, the calibrations, an image per camera):
    whatever the loader would refuse stops the import before it is moved into place."""
    try:
        layout = RigLayout(out)
        for name, count in counts.items():
            frames = layout.frames(sequence, name)
            if len(frames) != count:
                raise ValueError(f"the rig layout keeps {len(frames)} of the {count} images of {name}")
            layout.read_image(sequence, name, frames[0])  # at its calibration's size, or refused
    except (ValueError, FileNotFoundError) as err:
        raise RosbagError(f"{bag}: the import would not load for training: {err}") from None
