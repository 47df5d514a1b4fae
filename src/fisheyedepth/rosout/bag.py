"""A ROS 2 bag of a run's outputs (``fisheyedepth-multiview --bag-out``, the live rig's ``--bag-out``):
:class:`BagWriter` writes messages into a hidden folder beside the target and puts the bag in place when it
is closed; :class:`BagRecorder` turns each image's maps into the messages of :mod:`.messages`."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from ..cameras.base import CameraModel
from ..cameras.rays import RayCache
from ..files import check_writable
from . import messages as m

BODY_FRAME = "base_link"  # REP 105's names: the rig's body, and the odometry's fixed frame
WORLD_FRAME = "odom"


def check_bag_out(path: str | os.PathLike, overwrite: bool, option: str = "--bag-out") -> Path:
    """Before any work: ``path`` ending ``.mcap`` is one MCAP file, any other a ROS 2 bag folder; its
    folder can be written; nothing is there unless ``overwrite``, and then only a bag of the same kind (a
    file for ``.mcap``, a folder with ``metadata.yaml`` otherwise), never another folder or file."""
    path = Path(path)
    check_writable(path.parent, option)
    if not os.path.lexists(path):
        return path
    single = path.suffix == ".mcap"
    same_kind = path.is_file() if single else (path / "metadata.yaml").is_file()
    if not same_kind:
        kind = "an MCAP file" if single else "a ROS 2 bag folder (metadata.yaml)"
        raise FileExistsError(f"{option}: {path} exists and is not {kind}; move it away")
    if not overwrite:
        raise FileExistsError(f"{option}: {path} exists; pass --overwrite to replace it")
    return path


class BagWriter:
    """ROS 2 messages (CDR, :data:`.messages.STORE`'s definitions) into ``path``: one MCAP file when it
    ends ``.mcap`` (what Foxglove opens and ``ros2 bag play`` plays from Jazzy on), otherwise a ROS 2 bag
    folder with MCAP storage (``metadata.yaml`` beside it: every ROS 2 distribution plays it). Nothing is
    at ``path`` until :meth:`close`; :meth:`discard` (or an exception in a ``with`` block) leaves nothing."""

    def __init__(self, path: str | os.PathLike, overwrite: bool = False):
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.path, self.overwrite = check_bag_out(path, overwrite), overwrite
        self.store = m.typestore()
        self.tmp = Path(tempfile.mkdtemp(dir=self.path.parent, prefix=f".{self.path.name}.bag-"))
        stem = self.path.stem if self.path.suffix == ".mcap" else self.path.name
        self.folder = self.tmp / stem
        self.writer = Writer(self.folder, version=9, storage_plugin=StoragePlugin.MCAP)
        self.writer.open()
        self.connections: dict[str, object] = {}
        self.count = 0

    def write(self, topic: str, message, stamp_ns: int) -> None:
        msgtype = message.__msgtype__
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        self.writer.write(self.connections[topic], int(stamp_ns), self.store.serialize_cdr(message, msgtype))
        self.count += 1

    def close(self) -> Path:
        """Finish the bag and put it at ``path`` (replacing a bag there only with ``overwrite``)."""
        try:
            self.writer.close()
            made = self.folder / f"{self.folder.name}.mcap" if self.path.suffix == ".mcap" else self.folder
            if os.path.lexists(self.path):
                check_bag_out(self.path, self.overwrite)  # a bag of the same kind, and replacing allowed
                if self.path.is_dir():
                    old = self.tmp / "replaced"
                    os.rename(self.path, old)  # out of the way, removed with the temporary folder
            os.replace(made, self.path)
        finally:
            shutil.rmtree(self.tmp, ignore_errors=True)
        return self.path

    def discard(self) -> None:
        try:
            self.writer.close()
        except Exception:  # noqa: BLE001 - a half-written bag is removed whatever its state
            pass
        shutil.rmtree(self.tmp, ignore_errors=True)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.discard()


class BagRecorder:
    """Each image's outputs as messages (``docs/inference.md``, "ROS 2 bags and Foxglove"): under its
    camera's namespace (:func:`.messages.topics`) ``distance`` and ``confidence`` (``32FC1``, 0 where
    nothing is kept; no confidence where the source has none, as a network's distance), ``camera_info``
    and ``points`` (the kept points in the body frame with their confidence and colour), stamped with the
    image's stamp in its camera's frame; ``/tf_static`` body -> each camera once, ``/tf`` odom -> body at
    every instant the odometry gives."""

    def __init__(
        self,
        writer: BagWriter,
        cameras: Mapping[str, CameraModel],
        cam_to_body: Mapping[str, np.ndarray],
        image_topics: Mapping[str, str] | None = None,
        frame_ids: Mapping[str, str] | None = None,
    ):
        self.writer, self.cameras = writer, dict(cameras)
        self.image_topics, self.frame_ids = dict(image_topics or {}), dict(frame_ids or {})
        self.cam_to_body = {name: np.asarray(T, dtype=np.float64) for name, T in cam_to_body.items()}
        self.rays = RayCache()
        self.static_written = False
        self.poses_written: set[int] = set()

    def frame_id(self, camera: str) -> str:
        return self.frame_ids.get(camera, camera)

    def _static(self, stamp_ns: int) -> None:
        edges = [(T, BODY_FRAME, self.frame_id(n)) for n, T in self.cam_to_body.items()]
        self.writer.write("/tf_static", m.transforms(self.writer.store, edges, stamp_ns), stamp_ns)
        self.static_written = True

    def add(self, camera: str, stamp_ns: int, image_bgr: np.ndarray, distance: np.ndarray,
            confidence: np.ndarray | None, body_to_world: np.ndarray | None,
            model: CameraModel | None = None) -> None:  # fmt: skip
        """One image's messages; ``body_to_world``: the odometry's pose at its stamp (``/tf``), or None;
        ``model``: the camera as this image was taken, where it differs from the rig's (a resized frame)."""
        store, frame = self.writer.store, self.frame_id(camera)
        topics = m.topics(self.image_topics.get(camera), camera)
        model = model or self.cameras[camera]
        if not self.static_written:
            self._static(stamp_ns)
        if body_to_world is not None and stamp_ns not in self.poses_written:
            tf = m.transforms(store, [(np.asarray(body_to_world, float), WORLD_FRAME, BODY_FRAME)], stamp_ns)
            self.writer.write("/tf", tf, stamp_ns)
            self.poses_written.add(stamp_ns)
        kept = np.where(np.nan_to_num(distance) > 0, distance, 0).astype(np.float32)
        self.writer.write(topics["distance"], m.float_image(store, kept, stamp_ns, frame), stamp_ns)
        sure = None
        if confidence is not None:
            sure = np.where(kept > 0, confidence, 0).astype(np.float32)
            self.writer.write(topics["confidence"], m.float_image(store, sure, stamp_ns, frame), stamp_ns)
        self.writer.write(topics["camera_info"], m.camera_info(store, model, stamp_ns, frame), stamp_ns)
        points, rows, cols = body_points(self.rays, model, self.cam_to_body[camera], kept)
        grey = image_bgr.ndim == 2
        rgb = np.repeat(image_bgr[rows, cols, None], 3, 1) if grey else image_bgr[rows, cols][:, ::-1]
        cloud = m.point_cloud(store, points, None if sure is None else sure[rows, cols], rgb.astype(np.uint8),
                              stamp_ns, BODY_FRAME)  # fmt: skip
        self.writer.write(topics["points"], cloud, stamp_ns)


def body_points(rays: RayCache, camera: CameraModel, cam_to_body: np.ndarray, distance: np.ndarray):
    """The pixels of ``distance`` with a value and a ray as points in the body frame ``[N, 3]`` (float64),
    and those pixels (rows, columns)."""
    grid, valid = (x.numpy() for x in rays.get(camera, dtype=torch.float64))
    rows, cols = np.nonzero(valid & (distance > 0))
    local = grid[rows, cols] * distance[rows, cols, None].astype(np.float64)
    return local @ cam_to_body[:3, :3].T + cam_to_body[:3, 3], rows, cols
