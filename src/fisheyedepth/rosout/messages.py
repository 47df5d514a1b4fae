"""ROS 2 messages of what the project computes, built with ``rosbags``' typestore (no ROS install): distance
and confidence as ``sensor_msgs/Image``, a camera as ``sensor_msgs/CameraInfo``, kept points as
``sensor_msgs/PointCloud2``, poses as ``tf2_msgs/TFMessage``; and the topic names of a camera's outputs."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..cameras.base import CameraModel
from ..geometry.se3 import matrix_to_quaternion

STORE = "ros2_humble"  # the message definitions written (sensor_msgs and tf2_msgs have not changed since)
OWN_MODEL = "fisheyedepth/"  # CameraInfo.distortion_model of a model ROS has no name for: this + its name
# ROS's distortion models: ours -> (ROS's name, the fields of D in order); a pinhole is plumb_bob, D zero
ROS_NAMES: dict[str, tuple[str, tuple[str, ...]]] = {
    "kannala_brandt": ("equidistant", ("k1", "k2", "k3", "k4")),
    "pinhole": ("plumb_bob", ()),
}
POINT_FIELDS = ("x", "y", "z", "confidence", "rgb")  # PointCloud2: float32 each, rgb packed 0x00RRGGBB
FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32


def typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores(STORE))


def header(store, stamp_ns: int, frame_id: str):
    types = store.types
    time = types["builtin_interfaces/msg/Time"](
        sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000
    )
    return types["std_msgs/msg/Header"](stamp=time, frame_id=frame_id)


def float_image(store, values: np.ndarray, stamp_ns: int, frame_id: str):
    """``32FC1`` ``sensor_msgs/Image`` of an ``H x W`` map, little-endian."""
    values = np.ascontiguousarray(values, dtype="<f4")
    if values.ndim != 2:
        raise ValueError(f"an image of floats is H x W, not {values.shape}")
    height, width = values.shape
    return store.types["sensor_msgs/msg/Image"](
        header=header(store, stamp_ns, frame_id), height=height, width=width, encoding="32FC1",
        is_bigendian=0, step=4 * width, data=values.view(np.uint8).reshape(-1),
    )  # fmt: skip


def camera_info_fields(camera: CameraModel) -> dict[str, Any]:
    """``distortion_model``, ``d`` and ``k`` of ``camera``: ROS's own names where ROS has the model
    (``plumb_bob`` and ``rational_polynomial`` for OpenCV's, ``equidistant`` for Kannala-Brandt, a pinhole
    as ``plumb_bob`` without distortion); any other model as ``fisheyedepth/<model>`` with ``d`` its
    parameters in :meth:`~CameraModel.param_names` order after the four of ``k`` (a Mei camera:
    ``fisheyedepth/mei``, ``d`` = xi, k1, k2, p1, p2; ``k`` from gamma1, gamma2, u0, v0). Read back by
    :func:`fisheyedepth.data.rosbag.camera_from_info`."""
    fu, fv = getattr(camera, camera._fu), getattr(camera, camera._fv)
    cu, cv = camera.principal_point
    k = [fu, 0.0, cu, 0.0, fv, cv, 0.0, 0.0, 1.0]
    name = camera.model_name
    if name == "opencv":
        ros = camera.to_ros()
        return {"distortion_model": ros["distortion_model"], "d": ros["D"], "k": ros["K"]}
    if name in ROS_NAMES:
        model, fields = ROS_NAMES[name]
        return {"distortion_model": model, "d": [getattr(camera, f) for f in fields] or [0.0] * 5, "k": k}
    intrinsics = {camera._fu, camera._fv, camera._cu, camera._cv}
    d = [getattr(camera, f) for f in camera.param_names() if f not in intrinsics]
    return {"distortion_model": OWN_MODEL + name, "d": d, "k": k}


def paraxial_projection(camera: CameraModel) -> list[float]:
    """The 3x4 ``P`` (row-major) of the paraxial pinhole: the focal length at the principal point
    (:meth:`~CameraModel.paraxial_focal`), a zero fourth column."""
    (fu, fv), (cu, cv) = camera.paraxial_focal(), camera.principal_point
    return [fu, 0.0, cu, 0.0, 0.0, fv, cv, 0.0, 0.0, 0.0, 1.0, 0.0]


def camera_info(store, camera: CameraModel, stamp_ns: int, frame_id: str):
    """``sensor_msgs/CameraInfo`` of the raw image (:func:`camera_info_fields`); ``r`` the identity and
    ``p`` the paraxial pinhole (the focal length at the principal point,
    :meth:`~CameraModel.paraxial_focal`, with a zero fourth column): nothing is rectified."""
    fields = camera_info_fields(camera)
    types = store.types
    k = np.asarray(fields["k"], dtype=np.float64)
    p = np.asarray(paraxial_projection(camera))
    roi = types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    return types["sensor_msgs/msg/CameraInfo"](
        header=header(store, stamp_ns, frame_id), height=camera.height, width=camera.width,
        distortion_model=fields["distortion_model"], d=np.asarray(fields["d"], dtype=np.float64), k=k,
        r=np.eye(3).reshape(-1), p=p, binning_x=0, binning_y=0, roi=roi,
    )  # fmt: skip


def point_cloud(store, points: np.ndarray, confidence: np.ndarray | None, rgb: np.ndarray, stamp_ns: int,
                frame_id: str):  # fmt: skip
    """``sensor_msgs/PointCloud2`` of ``points [N, 3]`` (metres in ``frame_id``) with their confidence
    ``[N]`` (None: the source has none, and the field is left out) and colour ``[N, 3]`` uint8 RGB:
    :data:`POINT_FIELDS`, float32 each, one row, every point finite (``is_dense``)."""
    names = [f for f in POINT_FIELDS if f != "confidence" or confidence is not None]
    packed = (rgb[:, 0].astype(np.uint32) << 16) | (rgb[:, 1].astype(np.uint32) << 8) | rgb[:, 2]
    columns = {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2], "confidence": confidence,
               "rgb": packed.astype("<u4").view("<f4")}  # fmt: skip
    table = np.empty((len(points), len(names)), dtype="<f4")
    for i, name in enumerate(names):
        table[:, i] = columns[name]
    if not np.isfinite(table[:, [i for i, n in enumerate(names) if n != "rgb"]]).all():
        raise ValueError("a point cloud's points and confidences must be finite")
    types = store.types
    fields = [types["sensor_msgs/msg/PointField"](name=name, offset=4 * i, datatype=FLOAT32, count=1)
              for i, name in enumerate(names)]  # fmt: skip
    step = 4 * len(names)
    return types["sensor_msgs/msg/PointCloud2"](
        header=header(store, stamp_ns, frame_id), height=1, width=len(points), fields=fields,
        is_bigendian=False, point_step=step, row_step=step * len(points),
        data=table.view(np.uint8).reshape(-1), is_dense=True,
    )  # fmt: skip


def transforms(store, edges: list[tuple[np.ndarray, str, str]], stamp_ns: int):
    """``tf2_msgs/TFMessage`` of ``(T_parent_child, parent, child)`` edges at ``stamp_ns``."""
    types = store.types
    out = []
    for T, parent, child in edges:
        q = matrix_to_quaternion(T[:3, :3])
        transform = types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](
                x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])
            ),
            rotation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )
        out.append(types["geometry_msgs/msg/TransformStamped"](
            header=header(store, stamp_ns, parent), child_frame_id=child, transform=transform))  # fmt: skip
    return types["tf2_msgs/msg/TFMessage"](transforms=out)


def namespace(image_topic: str | None, camera: str) -> str:
    """Where a camera's outputs go: its image topic's namespace (``/front/image_raw`` and
    ``/front/image_raw/compressed`` -> ``/front``), or ``/<camera>`` without one."""
    if not image_topic:
        return f"/{camera}"
    parts = image_topic.strip("/").split("/")
    if parts and parts[-1] in ("compressed", "theora", "compressedDepth"):
        parts = parts[:-1]
    parts = parts[:-1]  # the image's own name: image_raw, image_color, image, ...
    return "/" + "/".join(parts) if parts else f"/{camera}"


def topics(image_topic: str | None, camera: str) -> dict[str, str]:
    """A camera's output topics: ``distance``, ``confidence``, ``camera_info`` and ``points``."""
    base = namespace(image_topic, camera).rstrip("/")
    return {what: f"{base}/{what}" for what in ("distance", "confidence", "camera_info", "points")}
