"""What a bag's messages hold, read and checked: images (``sensor_msgs/Image`` and ``CompressedImage``,
16-bit depths), calibrations (``sensor_msgs/CameraInfo``), transforms (``/tf``, ``/tf_static``, odometry
poses as rigid transforms) and the bag itself opened; every refusal a :class:`RosbagError` naming the
bag, the topic and what."""

from __future__ import annotations

import logging
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

from ...cameras import CameraModel
from ...cameras.opencv import ROS_MODELS
from ...geometry import make_pose, rigid_transform
from ..layouts import quaternion_matrix, unit_quaternion

log = logging.getLogger("fisheyedepth.data.rosbag")

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


def stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def field_of(msg, *names):
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
    - ``equidistant``, 4 coefficients k1 k2 k3 k4 -> Kannala-Brandt (``cv2.fisheye``);
    - ``fisheyedepth/<model>`` (what :mod:`fisheyedepth.rosout` writes for a model ROS has no name for:
      Mei, double sphere, Fisheye624, ...), ``D`` the model's parameters beyond its four intrinsics.

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
    from ...cameras.opencv import ros_matrix_fault

    K = [float(v) for v in field_of(msg, "k", "K")]
    D = [float(v) for v in field_of(msg, "d", "D")]
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
    elif (own := own_model(model, len(D))) is not None:  # what fisheyedepth.rosout writes
        names = (own._fu, own._fv, own._cu, own._cv)
        rest = [f for f in own.param_names() if f not in names]
        data = {"model": own.model_name, **size, **dict(zip(names, intrinsics.values(), strict=True)),
                **dict(zip(rest, D, strict=True))}  # fmt: skip
    else:
        expected = (
            "; ".join(
                f"{name} with {len(fields)} ({' '.join(fields)})"
                for name, (_, fields) in CAMERA_INFO_MODELS.items()
            )
            + "; fisheyedepth/<model> with its parameters beyond fx fy cx cy"
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


def own_model(distortion_model: str, coefficients: int):
    """The camera model class of a ``fisheyedepth/<model>`` distortion model (written by
    :func:`fisheyedepth.rosout.messages.camera_info_fields`) with as many coefficients as the model has
    parameters beyond its four intrinsics, or None."""
    from ...cameras.base import CAMERA_MODELS

    prefix, _, name = distortion_model.partition("/")
    cls = CAMERA_MODELS.get(name) if prefix == "fisheyedepth" else None
    if cls is None or len(cls.param_names()) - 4 != coefficients:
        return None
    return cls


def transform(t, where: str) -> np.ndarray:
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


def open_bag(bag: Path):
    from rosbags.highlevel import AnyReader

    try:
        reader = AnyReader([bag])
        reader.open()
    except Exception as err:  # rosbags raises its own types for unreadable bags
        raise RosbagError(f"{bag}: not a readable ROS 1 or ROS 2 bag ({err})") from None
    return reader


def listed(stamps: list[int], at_most: int = 10) -> str:
    more = f" and {len(stamps) - at_most} more" if len(stamps) > at_most else ""
    return ", ".join(map(str, stamps[:at_most])) + more
