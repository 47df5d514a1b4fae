"""A live rig's outputs served to Foxglove (``foxglove-sdk``'s WebSocket server, on localhost by default):
the same topics as a bag of them (:class:`~.bag.BagRecorder`) in Foxglove's own schemas, logged as each
instant is computed. Open Foxglove, "Open connection", ``ws://127.0.0.1:PORT``."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ..cameras.base import CameraModel
from ..cameras.rays import RayCache
from ..geometry.se3 import matrix_to_quaternion
from . import messages as m
from .bag import BODY_FRAME, WORLD_FRAME, body_points

PORT = 8765  # Foxglove's default
FOXGLOVE_MODELS = {"equidistant": "kannala_brandt"}  # its name for a ROS distortion model, where it differs


def import_foxglove():
    try:
        import foxglove
    except ImportError:
        raise ImportError("serving to Foxglove needs foxglove-sdk: pip install -e '.[ros]'") from None
    return foxglove


class FoxgloveLive:
    """A WebSocket server on ``host:port`` (port 0: any free one, :attr:`port` says which) with, per
    camera, ``image`` (the camera's picture, ``bgr8``), ``distance`` and ``confidence`` (``32FC1``, 0
    where nothing is kept), ``camera_info`` and ``points`` (body frame, with confidence and colour), and
    ``/tf`` (odom -> body, body -> each camera): :meth:`add` logs one image's, :meth:`close` stops the
    server. A client sees what is logged after it subscribes (nothing is stored for late joiners)."""

    def __init__(self, cameras: Mapping[str, CameraModel], cam_to_body: Mapping[str, np.ndarray],
                 host: str = "127.0.0.1", port: int = PORT, image_topics: Mapping[str, str] | None = None,
                 frame_ids: Mapping[str, str] | None = None):  # fmt: skip
        foxglove = import_foxglove()
        from foxglove import channels

        self.fx = foxglove.messages
        self.context = foxglove.Context()
        self.cameras = dict(cameras)
        self.cam_to_body = {name: np.asarray(T, dtype=np.float64) for name, T in cam_to_body.items()}
        self.frame_ids = {name: (frame_ids or {}).get(name, name) for name in self.cameras}
        self.rays = RayCache()
        kinds = {"image": channels.RawImageChannel, "distance": channels.RawImageChannel,
                 "confidence": channels.RawImageChannel, "camera_info": channels.CameraCalibrationChannel,
                 "points": channels.PointCloudChannel}  # fmt: skip
        self.channels = {}
        for name in self.cameras:
            topics = m.topics((image_topics or {}).get(name), name)
            topics["image"] = topics["distance"].rsplit("/", 1)[0] + "/image"
            self.channels[name] = {
                what: kind(topics[what], context=self.context) for what, kind in kinds.items()
            }
        self.tf = channels.FrameTransformsChannel("/tf", context=self.context)
        try:
            self.server = foxglove.start_server(
                name="fisheyedepth", host=host, port=port, context=self.context
            )
        except Exception as err:  # noqa: BLE001 - the SDK raises its own error types for a taken port
            raise ValueError(f"--foxglove: cannot serve on {host}:{port} ({err})") from None
        self.port = self.server.port

    def _stamp(self, stamp_ns: int):
        return self.fx.Timestamp(sec=stamp_ns // 1_000_000_000, nsec=stamp_ns % 1_000_000_000)

    def _transform(self, T: np.ndarray, parent: str, child: str, stamp_ns: int):
        q = matrix_to_quaternion(T[:3, :3])
        return self.fx.FrameTransform(
            timestamp=self._stamp(stamp_ns), parent_frame_id=parent, child_frame_id=child,
            translation=self.fx.Vector3(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
            rotation=self.fx.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
        )  # fmt: skip

    def _image(self, values: np.ndarray, encoding: str, stamp_ns: int, frame: str):
        values = np.ascontiguousarray(values)
        height, width = values.shape[:2]
        return self.fx.RawImage(timestamp=self._stamp(stamp_ns), frame_id=frame, width=width, height=height,
                                encoding=encoding, step=values.strides[0], data=values.tobytes())  # fmt: skip

    def add(self, camera: str, stamp_ns: int, image_bgr: np.ndarray, distance: np.ndarray,
            confidence: np.ndarray, body_to_world: np.ndarray | None) -> None:  # fmt: skip
        """One image's messages, logged at ``stamp_ns``; ``body_to_world``: the odometry's pose, or None."""
        fx, frame, out = self.fx, self.frame_ids[camera], self.channels[camera]
        edges = [self._transform(self.cam_to_body[camera], BODY_FRAME, frame, stamp_ns)]
        if body_to_world is not None:
            edges.append(self._transform(np.asarray(body_to_world, float), WORLD_FRAME, BODY_FRAME, stamp_ns))
        self.tf.log(fx.FrameTransforms(transforms=edges), log_time=stamp_ns)
        bgr = image_bgr if image_bgr.ndim == 3 else np.repeat(image_bgr[..., None], 3, 2)
        kept = np.where(distance > 0, distance, 0).astype("<f4")
        sure = np.where(kept > 0, confidence, 0).astype("<f4")
        out["image"].log(self._image(bgr.astype(np.uint8), "bgr8", stamp_ns, frame), log_time=stamp_ns)
        out["distance"].log(self._image(kept, "32FC1", stamp_ns, frame), log_time=stamp_ns)
        out["confidence"].log(self._image(sure, "32FC1", stamp_ns, frame), log_time=stamp_ns)
        cam = self.cameras[camera]
        info = m.camera_info_fields(cam)
        calibration = fx.CameraCalibration(
            timestamp=self._stamp(stamp_ns), frame_id=frame, width=cam.width, height=cam.height,
            distortion_model=FOXGLOVE_MODELS.get(info["distortion_model"], info["distortion_model"]),
            D=[float(v) for v in info["d"]], K=[float(v) for v in info["k"]],
            R=np.eye(3).reshape(-1).tolist(), P=m.paraxial_projection(cam),
        )  # fmt: skip
        out["camera_info"].log(calibration, log_time=stamp_ns)
        points, rows, cols = body_points(self.rays, cam, self.cam_to_body[camera], kept)
        out["points"].log(self._cloud(points, sure[rows, cols], bgr[rows, cols], stamp_ns), log_time=stamp_ns)

    def _cloud(self, points: np.ndarray, confidence: np.ndarray, bgr: np.ndarray, stamp_ns: int):
        """x, y, z, confidence (float32), red, green, blue, alpha (uint8): 20 bytes a point."""
        fx = self.fx
        table = np.zeros(len(points), dtype=[("xyz", "<f4", 3), ("confidence", "<f4"), ("rgba", "u1", 4)])
        table["xyz"], table["confidence"] = points, confidence
        table["rgba"][:, :3], table["rgba"][:, 3] = bgr[:, ::-1], 255
        f32, u8 = fx.PackedElementFieldNumericType.Float32, fx.PackedElementFieldNumericType.Uint8
        names = (("x", 0, f32), ("y", 4, f32), ("z", 8, f32), ("confidence", 12, f32), ("red", 16, u8),
                 ("green", 17, u8), ("blue", 18, u8), ("alpha", 19, u8))  # fmt: skip
        identity = fx.Pose(position=fx.Vector3(x=0.0, y=0.0, z=0.0),
                           orientation=fx.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))  # fmt: skip
        return fx.PointCloud(
            timestamp=self._stamp(stamp_ns), frame_id=BODY_FRAME, pose=identity, point_stride=20,
            fields=[fx.PackedElementField(name=n, offset=o, type=t) for n, o, t in names],
            data=table.tobytes(),
        )  # fmt: skip

    def close(self) -> None:
        self.server.stop()

    def __enter__(self) -> FoxgloveLive:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
