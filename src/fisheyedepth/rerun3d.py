"""3-D recordings of what the project computes, for the Rerun viewer (``rerun OUT/recording.rrd``): the rig's
cameras in the body frame, the body's path from odometry, each camera's image beside its distance maps, and
every camera's points in one world frame, on two timelines to scrub.

The one module that imports ``rerun`` (the ``viz`` extra: ``pip install -e ".[viz]"``, or ``make install``);
it is imported when a :class:`RigRecorder` is made, so the rest of the package runs without it.

Entities of a recording (``<camera>`` and ``<map>`` as the caller names them):

- ``world/body``: the body's pose in the world at each instant (identity where none is known);
  ``world/body/<rig>/<camera>``: each camera's pose in the body frame (static, :meth:`RigRecorder.rig`;
  ``<rig>`` is ``rig``, or ``refined`` for a refined calibration logged beside it), with its axes and name;
- ``world/trajectory``: the body's positions so far, one line strip in the order of the instants' indices
  (an instant may be logged in parts, camera by camera: its index then names one position);
- ``world/points/<camera>/<map>``: the map's points, already in the world frame, coloured by the image;
  ``world/points/<camera>/ground_truth``: the ground truth's, in one colour (:data:`TRUTH_COLOUR`);
- ``images/<camera>/image``: the image as JPEG; ``images/<camera>/<map>/colour``: the map on a log
  colour scale (:func:`fisheyedepth.viz.colourise`, near = warm; JPEG too), and
  ``images/<camera>/<map>/metres`` the map itself as a depth image in metres (0 = no value);
  ``images/<camera>/ground_truth/...`` likewise;
- ``scores/<camera>/<name>``: each score, one scalar per instant.

Timelines: ``time`` (a duration, the instant's timestamp in nanoseconds on the source's own clock) and
``frame`` (the instant's index). No pinhole frustum is drawn: a fisheye is no pinhole, so a camera is
shown by its pose, its image and its points.

Points: a pixel is a point where its map holds a finite distance above 0 and the camera model gives it a
ray; point = ray x distance, then camera -> body -> world. At most ``points_per_image`` points per map
and image, drawn uniformly at random without replacement by a generator seeded once per recording
(seed 0): the same inputs give the same recording.
"""

from __future__ import annotations

import contextlib
import glob
import os
import uuid
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch

from .cameras import CameraModel, RayCache
from .files import check_writable, place_new, remove_stale_temporaries, temporary_beside
from .geometry import rigid_transform
from .utils import is_number, is_whole
from .viz import colourise

if TYPE_CHECKING:  # the multi-view run's types, for InstantRecorder's signatures
    from .data.layouts import Frame, RigLayout
    from .stereo.fuse import Fused
    from .stereo.pairing import Pairing

TRUTH_COLOUR = (255, 0, 255)  # ground-truth points: magenta, apart from any image's colours
JPEG_QUALITY = 90
SEED = 0
AXIS_LENGTH = 0.05  # metres: each camera's axes (x red, y green, z blue) at its pose in the body frame
# The longest a finished recording may take to reach its file: the SDK waits for ever by default, so a
# writer that stops answering (a hung network mount) would hold the command; beyond this it is an error.
# Its writer keeps up with the logging as it goes, so what is left at the end takes seconds.
FLUSH_SECONDS = 300.0
STALLED_SECONDS = 2.0  # a writer whose file has not grown this long, at a file-size limit or a full disk,
# has stopped: the SDK's flush can wait for such a writer for ever, so it is named then, not at the bound


def import_rerun():
    """The ``rerun`` module, or an ImportError that names the extra to install."""
    # the SDK's own log lines about a writer that stopped (colour-coded, before the command's error
    # line, which names the cause): off unless the user's RUST_LOG asks for them
    os.environ.setdefault("RUST_LOG", "off")
    try:
        import rerun
    except ImportError as err:
        raise ImportError(
            'Rerun recordings need the rerun-sdk package: pip install -e ".[viz]" (or make install)'
        ) from err
    return rerun


@dataclass
class CameraView:
    """One camera at one instant: its model, its image (``H x W x 3`` uint8 RGB, or ``H x W`` grey), its
    distance ``maps`` (name -> ``H x W`` metres along each pixel's ray, 0 = no value; NaN, infinite and
    negative values count as none), optional ground truth (``H x W`` metres, 0 = none) and scores."""

    camera: CameraModel
    image: np.ndarray
    maps: Mapping[str, np.ndarray]
    ground_truth: np.ndarray | None = None
    scores: Mapping[str, float] = field(default_factory=dict)


class RecordingError(ValueError):
    """A recording that could not be written (the disk filled, a file-size limit): named by its path,
    with the cause where the folder's free space or the process's file-size limit tells it; nothing is
    left at it. ``why``: the cause alone, to name another path (a staging folder's final place)."""

    def __init__(self, path: Path, why: Exception | str) -> None:
        self.path, self.why = Path(path), why if isinstance(why, str) else write_failure(path, why)
        super().__init__(f"{path}: the recording could not be written ({self.why})")


def write_failure(path: Path, err: Exception) -> str:
    """Why the SDK's file writer stopped (it reports only that it did): no time left to finish
    (:data:`FLUSH_SECONDS`), no space left in the folder, or the process's file-size limit
    (``ulimit -f``); else its own words and both guesses."""
    import resource

    if "timed out" in str(err):
        return f"its writer did not finish within {FLUSH_SECONDS:g} s"
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    if disk_full(path):
        return f"no space left on device in {Path(path).parent}"
    if limit != resource.RLIM_INFINITY:
        return f"the file-size limit of this process, {limit} bytes (ulimit -f)"
    return f"{err}; a full disk or a file-size limit?"


def disk_full(path: Path) -> bool:
    """Under a megabyte left (for a non-root writer) in ``path``'s folder."""
    try:
        free = os.statvfs(Path(path).parent)
    except OSError:
        return False
    return free.f_bavail * free.f_frsize < 1 << 20


def at_a_limit(path: Path) -> bool:
    """The process has a file-size limit (``ulimit -f``), or ``path``'s disk is full: where a writer that
    has stopped growing its file has stopped for good."""
    import resource

    return resource.getrlimit(resource.RLIMIT_FSIZE)[0] != resource.RLIM_INFINITY or disk_full(path)


class RigRecorder:
    """Writes one ``.rrd`` recording (module docstring): :meth:`rig` once (or again with another
    ``name``), :meth:`instant` per instant, :meth:`close` at the end, or use it in a ``with`` block.

    The recording is written to a hidden temporary file beside ``path`` and put at ``path`` by
    :meth:`close`; an exception in the ``with`` block (or :meth:`discard`) removes it, so ``path`` holds a
    whole recording or nothing. An existing ``path`` is refused unless ``overwrite``.

    ``colour_range``: the ``(near, far)`` metres of the colourised maps; None: the 2nd and 98th
    percentiles of the first map recorded, kept for the whole recording (one colour, one distance)."""

    def __init__(
        self,
        path: Path,
        application: str = "fisheyedepth",
        points_per_image: int = 100_000,
        overwrite: bool = False,
    ):
        self.path = Path(path)
        if not is_whole(points_per_image) or points_per_image < 1:
            raise ValueError(f"points_per_image: {points_per_image!r}; a whole number, at least 1")
        if self.path.is_dir():
            raise ValueError(f"{self.path}: a folder; a recording is a file (OUT/recording.rrd)")
        if self.path.exists() and not overwrite:
            raise FileExistsError(f"{self.path} exists; pass overwrite=true to replace it")
        check_writable(self.path.parent, str(self.path))
        remove_stale_temporaries(self.path.parent, glob.escape(self.path.name))  # a killed writer's
        self.rr = import_rerun()
        self.points_per_image, self.overwrite = int(points_per_image), overwrite
        self.colour_range: tuple[float, float] | None = None
        self.rigs: dict[str, dict[str, np.ndarray]] = {}
        self.latest_rig: dict[str, np.ndarray] | None = None
        self.positions: dict[int, np.ndarray] = {}  # the body's position by instant index
        self.rng = np.random.default_rng(SEED)
        self._rays = RayCache()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._temporary = contextlib.ExitStack()  # the package's one temporary-beside-the-target
        self.tmp: Path | None = self._temporary.enter_context(temporary_beside(self.path))
        self.stream = self.rr.RecordingStream(application, recording_id=str(uuid.uuid4()))
        self.stream.set_log_time_enabled(False)  # the two timelines only: time and frame
        self.stream.save(str(self.tmp))

    # ------------------------------------------------------------------------------------ the rig
    def rig(self, cam_to_body: Mapping[str, np.ndarray], name: str = "rig") -> None:
        """Each camera's 4x4 pose in the body frame, static, under ``world/body/<name>/<camera>``; the
        rig :meth:`instant` uses when it is given none is the last one logged."""
        rr, poses = self.rr, {c: rigid_transform(T, f"cam_to_body[{c!r}]") for c, T in cam_to_body.items()}
        for camera, T in poses.items():
            entity = f"world/body/{name}/{camera}"
            self.stream.log(entity, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), static=True)
            self.stream.log(entity, rr.TransformAxes3D(AXIS_LENGTH), static=True)
            self.stream.log(f"{entity}/centre", rr.Points3D([[0.0, 0.0, 0.0]], labels=[camera]), static=True)
        self.rigs[name] = poses
        self.latest_rig = poses

    # ------------------------------------------------------------------------------- an instant
    def instant(
        self,
        timestamp_ns: int,
        index: int,
        views: Mapping[str, CameraView],
        body_to_world: np.ndarray | None = None,
        cam_to_body: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        """Every camera of ``views`` at one instant (module docstring). ``body_to_world``: the body's
        4x4 pose (None: identity); ``cam_to_body``: the cameras' poses on the body (None: the last
        :meth:`rig`, identity for a camera it does not name)."""
        for what, value in (("timestamp_ns", timestamp_ns), ("index", index)):
            if not is_whole(value) or not -(2**63) < value < 2**63:
                raise ValueError(f"{what}: {value!r}; a whole number within a signed 64-bit integer")
        for camera, view in views.items():
            for name, value in view.scores.items():
                if value is not None and not is_number(value):
                    raise ValueError(f"views[{camera!r}].scores[{name!r}]: {value!r}; a number or None")
        body = np.eye(4) if body_to_world is None else rigid_transform(body_to_world, "body_to_world")
        rig = cam_to_body if cam_to_body is not None else (self.latest_rig or {})
        extrinsics = {
            camera: rigid_transform(rig[camera], f"cam_to_body[{camera!r}]") if camera in rig else np.eye(4)
            for camera in views
        }
        with self._writing():
            self.stream.set_time("time", duration=np.timedelta64(int(timestamp_ns), "ns"))
            self.stream.set_time("frame", sequence=int(index))
            self._log_body(body, int(index))
            for camera, view in views.items():
                self._log_view(camera, view, body @ extrinsics[camera])

    def _log_body(self, body: np.ndarray, index: int) -> None:
        rr = self.rr
        self.stream.log("world/body", rr.Transform3D(translation=body[:3, 3], mat3x3=body[:3, :3]))
        self.positions[index] = body[:3, 3].copy()  # an instant logged again moves, not adds, its point
        path = np.array([self.positions[i] for i in sorted(self.positions)], np.float32)
        self.stream.log("world/trajectory", rr.LineStrips3D([path]))

    def _log_view(self, camera: str, view: CameraView, cam_to_world: np.ndarray) -> None:
        rr, size = self.rr, (view.camera.height, view.camera.width)
        rgb = image_rgb(view.image, size, camera)
        self.stream.log(f"images/{camera}/image", self.encoded(rgb))
        for name, values in view.maps.items():
            distance = checked_map(values, size, f"{camera}: map {name!r}")
            self._log_map(f"images/{camera}/{name}", distance)
            points, keep = self.points(view.camera, distance, cam_to_world)
            self.stream.log(f"world/points/{camera}/{name}", rr.Points3D(points, colors=rgb[keep]))
        if view.ground_truth is not None:
            truth = checked_map(view.ground_truth, size, f"{camera}: ground truth")
            self._log_map(f"images/{camera}/ground_truth", truth)
            points, _ = self.points(view.camera, truth, cam_to_world)
            self.stream.log(f"world/points/{camera}/ground_truth", rr.Points3D(points, colors=TRUTH_COLOUR))
        for name, value in view.scores.items():
            if value is not None and np.isfinite(value):
                self.stream.log(f"scores/{camera}/{name}", rr.Scalars(float(value)))

    def encoded(self, rgb: np.ndarray):
        """``rgb`` (``H x W x 3`` uint8) as a JPEG image of the recording."""
        return self.rr.EncodedImage(contents=jpeg(rgb), media_type="image/jpeg")

    def _log_map(self, entity: str, distance: np.ndarray) -> None:
        """``distance`` (0 = no value) colourised and as a depth image in metres."""
        if self.colour_range is None:
            self.colour_range = colour_range(distance)
        near, far = self.colour_range
        colours = colourise(distance, near, far)
        self.stream.log(
            f"{entity}/colour", self.rr.EncodedImage(contents=jpeg(colours), media_type="image/jpeg")
        )
        # float16: half the bytes of float32 (a recording's largest part with the points), 0.05 % of the
        # distance (4 cm at 80 m) for the viewer's hover and its 3-D projection
        self.stream.log(f"{entity}/metres", self.rr.DepthImage(distance.astype(np.float16), meter=1.0))

    # ------------------------------------------------------------------------------------ points
    def points(
        self, camera: CameraModel, distance: np.ndarray, cam_to_world: np.ndarray
    ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """World points ``[N, 3]`` float32 of ``distance``'s pixels with a value and a ray, at most
        ``points_per_image`` of them (module docstring), and their pixels ``(rows, columns)``."""
        rays, valid = (x.numpy() for x in self._rays.get(camera, dtype=torch.float64))
        rows, cols = np.nonzero(valid & (distance > 0))
        if len(rows) > self.points_per_image:
            chosen = np.sort(self.rng.choice(len(rows), self.points_per_image, replace=False))
            rows, cols = rows[chosen], cols[chosen]
        local = rays[rows, cols] * distance[rows, cols, None].astype(np.float64)
        world = local @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]
        return world.astype(np.float32), (rows, cols)

    # ------------------------------------------------------------------------------------ the file
    def close(self) -> None:
        """Finish the recording and put it at ``path`` (refused if a file took the name meanwhile and
        ``overwrite`` is off: FileExistsError, the temporary file removed)."""
        if self.tmp is None:
            return
        try:
            self._finish()
            if self.overwrite:
                os.replace(self.tmp, self.path)
            else:
                place_new(str(self.tmp), self.path)
        finally:
            self._temporary.close()
            self.tmp = None

    def discard(self) -> None:
        """Stop recording and remove the temporary file; nothing is written at ``path``."""
        if self.tmp is None:
            return
        with contextlib.suppress(Exception):
            self._finish()
        self._temporary.close()
        self.tmp = None

    def _finish(self) -> None:
        with self._writing():
            self._flush()
            self.rr.bindings.finalize_deferred_sinks(recording=self.stream.to_native())
            self.stream.disconnect()

    def _flush(self) -> None:
        """The SDK's flush, bounded by :data:`FLUSH_SECONDS`, in slices of a second: between them a
        writer whose file has not grown for :data:`STALLED_SECONDS` while the process is at a file-size
        limit or the disk is full has stopped, and is named as such at once (RuntimeError)."""
        import time

        def written() -> int:
            return os.stat(self.tmp).st_size if os.path.exists(self.tmp) else 0

        deadline = time.monotonic() + FLUSH_SECONDS
        size, since = written(), time.monotonic()
        while True:
            left = deadline - time.monotonic()
            try:
                self.stream.flush(timeout_sec=max(min(1.0, left), 0.01))
                return
            except RuntimeError as err:
                if "timed out" not in str(err) or left <= 1.0:
                    raise
            now_size = written()
            if now_size != size:
                size, since = now_size, time.monotonic()
            elif time.monotonic() - since >= STALLED_SECONDS and at_a_limit(self.path):
                raise RuntimeError(f"the writer stopped at {size} bytes")

    @contextlib.contextmanager
    def _writing(self):
        """The SDK's file writer stopping (a full disk, a file-size limit) as a :class:`RecordingError`,
        the stream disconnected: on a thread of its own, waited for :data:`STALLED_SECONDS` at most (the
        SDK's disconnect and its exit hook, like its flush, can wait for a stopped writer for ever)."""
        try:
            yield
        except RuntimeError as err:
            import threading

            def disconnect() -> None:
                with contextlib.suppress(Exception):
                    self.stream.disconnect()

            thread = threading.Thread(target=disconnect, name="rerun-disconnect", daemon=True)
            thread.start()
            thread.join(STALLED_SECONDS)
            if thread.is_alive():  # the SDK's exit hook would wait for the same writer: the process's
                self.rr.unregister_shutdown()  # exit must not (every recorder here flushes on close)
            raise RecordingError(self.path, err) from None

    def __enter__(self) -> RigRecorder:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.discard()

    def __del__(self) -> None:  # never left behind by an object dropped unclosed
        if getattr(self, "tmp", None) is not None:
            with contextlib.suppress(Exception):
                self.discard()


# ---------------------------------------------------------------------------------------- helpers
def checked_map(values: np.ndarray, size: tuple[int, int], what: str) -> np.ndarray:
    """``values`` (``H x W`` metres) as float32 with every non-finite or non-positive value 0."""
    values = np.asarray(values)
    if values.shape != size:
        raise ValueError(f"{what}: shape {values.shape}, but the camera is {size[1]}x{size[0]} (W x H)")
    values = values.astype(np.float32)
    return np.where(np.isfinite(values) & (values > 0), values, np.float32(0.0))


def image_rgb(image: np.ndarray, size: tuple[int, int], camera: str) -> np.ndarray:
    """``image`` (``H x W x 3`` RGB or ``H x W`` / ``H x W x 1`` grey, uint8) as ``H x W x 3`` RGB."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.shape[:2] != size or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise ValueError(
            f"{camera}: image of shape {image.shape}, expected {size[0]} x {size[1]} (x 3 for RGB)"
        )
    if image.dtype != np.uint8:
        raise ValueError(f"{camera}: image of type {image.dtype}, expected uint8")
    return np.repeat(image[..., None], 3, axis=2) if image.ndim == 2 else image


def jpeg(rgb: np.ndarray) -> bytes:
    ok, encoded = cv2.imencode(".jpg", rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError("the image could not be encoded as JPEG")
    return encoded.tobytes()


def colour_range(distance: np.ndarray) -> tuple[float, float]:
    """The 2nd and 98th percentiles of ``distance``'s values (0.5 to 80 m for a map without any)."""
    values = distance[distance > 0]
    if values.size == 0:
        return 0.5, 80.0
    near, far = np.percentile(values, [2, 98])
    return float(near), float(max(far, near * 1.01))


class InstantRecorder:
    """A multi-view run's 3-D recording (``fisheyedepth-multiview --rerun``): the images of one instant (its
    cameras' images within ``same_instant_ns`` of the first) logged together, each with its ``kept`` and
    ``filled`` maps, its ground truth and abs_rel where the recording has them; the body's pose from the
    odometry; the recorded rig, and the refined one beside it."""

    def __init__(self, path: Path, layout: RigLayout, recorded: dict, refinement: dict | None,
                 same_instant_ns: int = 1_000_000):  # fmt: skip
        self.layout, self.same_instant_ns = layout, same_instant_ns
        self.recorder = RigRecorder(path, "fisheyedepth-multiview")
        self.recorder.rig(recorded, name="rig")
        self.rig = {name: spec.cam_to_body for name, spec in layout.cameras.items()}
        if refinement is not None:
            self.recorder.rig(self.rig, name="refined")
        self.views: dict = {}
        self.at: tuple[str, Frame] | None = None
        self.index = 0

    def add(self, pairing: Pairing, image: np.ndarray, fused: Fused, truth, record: dict) -> None:
        if self.at is not None and (
            self.at[0] != pairing.sequence
            or pairing.frame.key - self.at[1].key > self.same_instant_ns
            or pairing.camera in self.views  # a camera's second image within the window: its own instant
        ):
            self.flush()
        if self.at is None:
            self.at = (pairing.sequence, pairing.frame)
        checked = (record.get("checked") or {}).get("abs_rel")
        self.views[pairing.camera] = CameraView(
            self.layout.cameras[pairing.camera].camera, image[..., ::-1],
            {"kept": fused.distance, "filled": fused.dense}, truth,
            {"abs_rel": checked} if isinstance(checked, float) else {},
        )  # fmt: skip

    def flush(self) -> None:
        if self.at is not None:
            frame = self.at[1]
            self.recorder.instant(frame.key, self.index, self.views, frame.pose, self.rig)
            self.index += 1
        self.views, self.at = {}, None

    def __enter__(self) -> InstantRecorder:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.flush()
            self.recorder.close()
        else:
            self.recorder.discard()
