"""Inference: metric distance for any image of a calibrated camera, its outputs, and an exportable graph.

``DistancePredictor`` resizes images (and the camera model) to the network's input size, runs the network
with the camera's ``depth_scale`` and returns distance at the image's own resolution (upsampled in
inverse-distance space). ``ExportableNet`` freezes one input size and camera into a plain
``image -> distance`` module for TorchScript and ONNX.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor, nn

from .cameras import CameraModel, RayCache, compute_rays
from .files import atomic_write_bytes, atomic_write_npy, atomic_write_png
from .rerun3d import RecordingError  # rerun itself is imported only when recording
from .runtimes import TorchRuntime, as_runtime
from .viz import colourise

PNG_SCALES = {"mm": 1000.0, "256": 256.0}  # uint16 PNG value per metre
log = logging.getLogger(__name__)


class ExportableNet(nn.Module):
    """``image [B, 3, H, W]`` (float RGB in [0, 1], the fixed export size) -> ``distance [B, 1, H, W]``."""

    def __init__(self, depth_net: nn.Module, depth_scale: float = 1.0):
        super().__init__()
        self.depth_net = depth_net
        self.depth_scale = float(depth_scale)

    def forward(self, image: Tensor) -> Tensor:
        return self.depth_net(image, self.depth_scale, scales=(0,))["distance"][0]


class DistancePredictor:
    """Distance for images of one camera at the camera's own size, by a trained module (run by a
    :class:`~fisheyedepth.runtimes.TorchRuntime`) or any runtime (an exported ONNX file)."""

    def __init__(
        self,
        model,
        camera: CameraModel,
        input_size: tuple[int, int] | None = None,
        device="cpu",
        precision: str = "fp32",
    ):
        self.runtime = as_runtime(model, input_size, precision, device)
        size = self.runtime.input_size or (camera.width, camera.height)
        self.input_size = (int(size[0]), int(size[1]))
        self.camera = camera
        self.has_ray = compute_rays(camera, torch.device("cpu")).valid  # [H, W]: pixels the model gives a ray
        if self.runtime.sources:  # a multi-view network, here without its source frames
            log.warning(
                "a multi-view checkpoint (net.cost_volume) predicts single images here, without the source "
                "frames and poses it was trained to match: its one-image mode (as with sources withheld)"
            )

    def __call__(self, images: Tensor) -> Tensor:
        """``[B, 3, H, W]`` float RGB at the camera's size -> distance ``[B, 1, H, W]`` in metres; NaN at
        pixels without a ray in the camera model (outside a fisheye's image circle)."""
        H, W = images.shape[-2:]
        if (W, H) != (self.camera.width, self.camera.height):
            raise ValueError(f"images are {W}x{H}, the camera is {self.camera.width}x{self.camera.height}")
        distance = self.runtime.distance(images, [self.camera] * images.shape[0]).cpu()
        return distance.masked_fill(~self.has_ray, float("nan"))

    def exportable(self) -> ExportableNet:
        """The network at ``input_size`` with this camera's ``depth_scale`` frozen in."""
        if not isinstance(self.runtime, TorchRuntime):
            raise TypeError("exportable: only a PyTorch module can be exported")
        net = self.runtime.module.depth_net
        return ExportableNet(net, float(net.depth_scale([self.camera.resize(*self.input_size)])[0])).eval()


def distance_png(distance: np.ndarray, scale: str = "mm") -> np.ndarray:
    """uint16 PNG values: millimetres (``"mm"``, up to 65.535 m) or metres * 256 (``"256"``, KITTI style);
    0 = no value (NaN, pixels without a ray), and a positive distance is at least 1."""
    factor = PNG_SCALES[scale]
    known = np.isfinite(distance) & (distance > 0)
    values = np.clip(np.round(np.where(known, distance, 0.0) * factor), 1, 65535)
    return np.where(known, values, 0).astype(np.uint16)


def colour_bar(image: np.ndarray, vmin: float, vmax: float, height: int | None = None) -> np.ndarray:
    """Append a labelled log-scale colour bar (near = warm) to the right of a colourised image."""
    h = height or image.shape[0]
    ramp = np.exp(np.linspace(np.log(vmin), np.log(vmax), h))[:, None].repeat(24, 1)
    bar = colourise(ramp, vmin, vmax)
    panel = np.full((h, 70, 3), 255, np.uint8)
    panel[:, :24] = bar
    for frac in (0.0, 0.5, 1.0):
        y = int(frac * (h - 1))
        value = float(ramp[y, 0])
        cv2.putText(
            panel,
            f"{value:.0f}m" if value >= 10 else f"{value:.1f}m",
            (26, min(max(y + 4, 10), h - 3)),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.35,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
    return np.concatenate((image, panel), axis=1)


def point_cloud(
    distance: Tensor, camera: CameraModel, rgb: np.ndarray | None = None, rays: RayCache | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """3-D points (camera frame, metres) of every pixel with a ray and a finite positive distance, and
    colours.
    Pass the caller's ``rays`` cache when converting many frames of one camera."""
    rays, valid = (rays or RayCache()).get(camera, dtype=torch.float64)
    d = distance.double().reshape(camera.height, camera.width)
    keep = valid & torch.isfinite(d) & (d > 0)
    points = (rays * d[..., None])[keep].numpy().astype(np.float32)
    colours = rgb[keep.numpy()] if rgb is not None else np.full((len(points), 3), 200, np.uint8)
    return points, colours


def write_ply(path: str | os.PathLike, points: np.ndarray, colours: np.ndarray) -> None:
    """Binary little-endian PLY with float xyz and uchar rgb, written atomically."""
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    ).encode()
    rec = np.empty(len(points), dtype=[("p", "<f4", 3), ("c", "u1", 3)])
    rec["p"], rec["c"] = points, colours
    atomic_write_bytes(path, header + rec.tobytes())


def read_ply(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    rec = np.frombuffer(data[end:], dtype=[("p", "<f4", 3), ("c", "u1", 3)])
    return rec["p"].copy(), rec["c"].copy()


class PredictionWriter:
    """Writes the outputs of one frame: ``_distance.npy`` (float32 metres, NaN without a ray),
    ``_distance.png`` (uint16, 0 without a ray), ``_colour.png``, and on request ``_z.npy`` and ``.ply``.
    Without ``overwrite`` no existing file is replaced: a clash raises before anything of that frame
    is written."""

    def __init__(
        self,
        out: str | os.PathLike,
        z_depth: bool = False,
        point_cloud: bool = False,
        png_scale: str = "mm",
        vmin: float = 0.5,
        vmax: float = 80.0,
        overwrite: bool = False,
    ):
        if png_scale not in PNG_SCALES:
            raise ValueError(f"png_scale: {png_scale!r} is not one of {sorted(PNG_SCALES)}")
        self.out, self.png_scale, self.vmin, self.vmax = Path(out), png_scale, vmin, vmax
        self.z_depth, self.point_cloud, self.overwrite = z_depth, point_cloud, overwrite
        self.suffixes = ["_distance.npy", "_distance.png", "_colour.png"]
        self.suffixes += ["_z.npy"] if z_depth else []
        self.suffixes += [".ply"] if point_cloud else []
        self.rays = RayCache()

    def outputs(self, name: str) -> list[Path]:
        return [self.out / f"{name}{suffix}" for suffix in self.suffixes]

    def check_free(self, names) -> None:
        """Raise ``FileExistsError`` naming the first output of ``names`` that exists (unless overwrite)."""
        if self.overwrite:
            return
        for name in names:
            for path in self.outputs(name):
                if path.exists():
                    raise FileExistsError(f"{path} exists; pass overwrite=true to replace outputs")

    def write(self, name: str, distance: Tensor, rgb: np.ndarray, camera: CameraModel) -> None:
        """``distance`` ``[H, W]`` metres (NaN without a ray) of the image ``rgb`` ``[H, W, 3]``."""
        self.check_free([name])
        self.out.mkdir(parents=True, exist_ok=True)
        d = distance.detach().float().cpu().numpy()
        atomic_write_npy(self.out / f"{name}_distance.npy", d)
        atomic_write_png(self.out / f"{name}_distance.png", distance_png(d, self.png_scale))
        vis = colour_bar(colourise(d, self.vmin, self.vmax), self.vmin, self.vmax)
        atomic_write_png(self.out / f"{name}_colour.png", vis[..., ::-1])
        if self.z_depth:
            rays, _ = self.rays.get(camera, dtype=torch.float64)
            atomic_write_npy(self.out / f"{name}_z.npy", (d * rays[..., 2].numpy()).astype(np.float32))
        if self.point_cloud:
            write_ply(self.out / f"{name}.ply", *point_cloud(distance.cpu(), camera, rgb, self.rays))


MIN_IMAGE_SIDE = 32


def check_aspect(frame_path: Path, size: tuple[int, int], camera: CameraModel, calibration) -> None:
    """A calibration is resized to the images only when both have one aspect ratio, and an image has at
    least :data:`MIN_IMAGE_SIDE` pixels a side (the network's coarsest features are a 32nd of its input:
    a smaller image holds less than one of them, and its distance would be the network's guess)."""
    (w, h), (cw, ch) = size, (camera.width, camera.height)
    if min(w, h) < MIN_IMAGE_SIDE:
        raise ValueError(
            f"{frame_path}: image is {w}x{h}; at least {MIN_IMAGE_SIDE} pixels a side are needed"
        )
    if abs(w * ch - h * cw) > 0.01 * w * ch:
        raise ValueError(
            f"{frame_path}: image is {w}x{h} but the calibration {calibration} is {cw}x{ch}, another "
            "aspect ratio; resizing the camera model would stretch it (crop the images or recalibrate)"
        )


class FramePrediction:
    """Frames of one source -> files: frames are batched while they share one size, each size gets a
    :class:`DistancePredictor` with the calibration resized to it, and a :class:`PredictionWriter`
    writes every frame. ``add`` frames, then ``flush`` once at the end; ``written`` counts frames.
    ``runtime``: a :class:`~fisheyedepth.runtimes.TorchRuntime` or an ``OnnxRuntime``.
    ``batch_size`` 1 writes each frame as soon as it is decoded (a live camera); ``recording``: each
    written frame also goes into it (``predict.py rerun=true``)."""

    def __init__(
        self,
        runtime,
        camera: CameraModel,
        calibration: str | os.PathLike,
        writer: PredictionWriter,
        batch_size: int = 4,
        recording: FrameRecording | None = None,
    ):
        self.runtime, self.camera, self.calibration, self.writer = runtime, camera, calibration, writer
        self.batch_size, self.recording = batch_size, recording
        self.predictors: dict[tuple[int, int], DistancePredictor] = {}
        self.pending: list = []
        self.written = 0
        self.recording_error: str | None = None  # why the recording stopped, if it did

    def predictor(self, frame) -> DistancePredictor:
        h, w = frame.bgr.shape[:2]
        if (w, h) not in self.predictors:
            check_aspect(frame.path, (w, h), self.camera, self.calibration)
            same = (w, h) == (self.camera.width, self.camera.height)
            camera = self.camera if same else self.camera.resize(w, h)
            self.predictors[(w, h)] = DistancePredictor(self.runtime, camera)
        return self.predictors[(w, h)]

    def add(self, frame) -> None:
        """Queue a decoded frame (``images.Frame``); a full batch, or a change of size, runs the network."""
        if self.pending and frame.bgr.shape != self.pending[0].bgr.shape:
            self.flush()
        self.pending.append(frame)
        if len(self.pending) >= self.batch_size:
            self.flush()

    def flush(self) -> None:
        if not self.pending:
            return
        predictor = self.predictor(self.pending[0])
        rgb = np.stack([f.bgr[..., ::-1] for f in self.pending])
        images = torch.from_numpy(rgb.copy()).permute(0, 3, 1, 2).float() / 255.0
        distance = predictor(images).cpu()
        frames, self.pending = self.pending, []  # an interrupt while writing loses no frame twice
        for frame, d, colour in zip(frames, distance[:, 0], rgb, strict=True):
            self.writer.write(frame.name, d, colour, predictor.camera)
            self.written += 1
            if self.recording is not None:
                try:
                    self.recording.add(frame.name, d.numpy(), colour, predictor.camera)
                except RecordingError as err:  # a full disk: the frames go on, the recording stops
                    self.recording.recorder.discard()
                    self.recording_error, self.recording = str(err), None
                    log.warning("%s; the frames go on without it", err)


@contextlib.contextmanager
def frame_recording(path: Path | None, source, overwrite: bool = False, bag_out: Path | None = None):
    """A :class:`FrameRecording` of ``source``'s frames (an ``images.FrameSource``) into the Rerun
    recording ``path`` and the ROS 2 bag ``bag_out`` (:class:`~.rosout.BagRecorder`), either or both
    (each refused at once if it exists, without ``overwrite``; put in place whole when the block ends,
    not at all when it fails); None without either."""
    if path is None and bag_out is None:
        yield None
        return
    odometry = None if source.live or source.files is None else layout_odometry(source.source)
    with contextlib.ExitStack() as stack:
        recorder = bag = None
        if bag_out is not None:
            from .rosout import BagRecorder, BagWriter

            cam_to_body = {"camera": np.eye(4) if odometry is None else odometry[1]}
            bag = BagRecorder(stack.enter_context(BagWriter(bag_out, overwrite)), {}, cam_to_body)
        if path is not None:
            from .rerun3d import RigRecorder

            recorder = stack.enter_context(RigRecorder(path, "fisheyedepth-predict", overwrite=overwrite))
        yield FrameRecording(recorder, source.live, video_fps(source), odometry, bag)


def video_fps(source) -> float:
    """The frame rate a video file states (0 where it states none, or for another source)."""
    if source.live or source.files is not None:
        return 0.0
    video = cv2.VideoCapture(str(source.source))
    try:
        return float(video.get(cv2.CAP_PROP_FPS) or 0.0)
    finally:
        video.release()


class FrameRecording:
    """The frames of one prediction run as instants of a Rerun recording
    (:class:`fisheyedepth.rerun3d.RigRecorder`, camera ``camera``, map ``distance``): each frame is an
    instant, ``frame`` its index. ``time``: for an image of a rig layout (``<timestamp_ns>.png`` with
    ``odometry``), its timestamp; for a live camera, the nanoseconds since its first frame was
    recorded; else the frame's index over ``fps`` (a video's own rate; 10 for a folder of images).
    ``odometry``: frame name -> 4x4 body-to-world pose and the camera's ``cam_to_body``
    (:func:`layout_odometry`); without it the body stays at the identity. ``bag``: a
    :class:`~.rosout.BagRecorder` each frame also goes into, stamped with the same ``time`` (camera
    ``camera``: topics ``/camera/distance``, ``/camera/camera_info``, ``/camera/points``; no confidence,
    which the network does not give). Either ``recorder`` or ``bag`` may be None."""

    def __init__(
        self,
        recorder,
        live: bool = False,
        fps: float = 10.0,
        odometry: tuple[dict[str, np.ndarray], np.ndarray] | None = None,
        bag=None,
    ):
        self.recorder, self.live, self.fps = recorder, live, fps if fps and fps > 0 else 10.0
        self.poses, cam_to_body = odometry if odometry is not None else ({}, np.eye(4))
        if self.recorder is not None:
            self.recorder.rig({"camera": cam_to_body})
        self.bag = bag
        self.count, self.start = 0, None

    def time_ns(self, name: str) -> int:
        if name in self.poses:  # a rig layout's image: named by its timestamp
            return int(name)
        if self.live:
            now = time.monotonic_ns()
            self.start = now if self.start is None else self.start
            return now - self.start
        return round(self.count * 1e9 / self.fps)

    def add(self, name: str, distance: np.ndarray, rgb: np.ndarray, camera: CameraModel) -> None:
        """One frame: ``distance`` ``[H, W]`` metres (NaN without a ray), ``rgb`` ``[H, W, 3]`` uint8."""
        from .rerun3d import CameraView

        stamp, pose = self.time_ns(name), self.poses.get(name)
        if self.recorder is not None:
            view = CameraView(camera, rgb, {"distance": distance})
            self.recorder.instant(stamp, self.count, {"camera": view}, pose)
        if self.bag is not None:
            self.bag.add("camera", stamp, np.ascontiguousarray(rgb[..., ::-1]), distance, None, pose, camera)
        self.count += 1


def layout_odometry(folder: str | os.PathLike) -> tuple[dict[str, np.ndarray], np.ndarray] | None:
    """Body poses of the images of a rig layout's camera folder (``ROOT/<sequence>/images/<camera>``,
    docs/data-format.md), by image name, and the camera's ``cam_to_body``; None for any other input (or a
    layout that does not load: the recording then keeps the body at the identity, and says so)."""
    folder = Path(folder)
    root, sequence, camera = folder.parent.parent.parent, folder.parent.parent.name, folder.name
    if folder.parent.name != "images" or not (root / "rig.yaml").is_file():
        return None
    from .data.layouts import RigLayout

    try:
        layout = RigLayout(root, cameras=[camera], expect_masks=False)
        frames = layout.frames(sequence, camera)
    except (OSError, ValueError) as err:
        log.warning("%s: no odometry for the recording (%s); the body stays at the identity", folder, err)
        return None
    return {str(f.key): f.pose for f in frames}, layout.cameras[camera].cam_to_body
