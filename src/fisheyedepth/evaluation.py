"""Evaluation at the ground truth's native resolution, under named protocols, with an angle breakdown.

Every frame of the scored split is scored (no neighbour needed, no translation bound). The network runs
at its training resolution (the image and camera model resized alike); its distance is upsampled to the
ground truth's resolution in inverse-distance space, as the reference does. Metrics
are reported unscaled (real scale), per-image median-scaled, and optionally with DNet-style scale
recovery from the known camera height. The breakdown by angle of incidence (0-30, 30-60, 60-90, beyond
90 degrees) shows where fisheye geometry matters; the one by motion scores the pixels that see a moving
object (where the ground truth says so: the synthetic world's traffic) apart from the static rest, so a
method that is right on the road and wrong on cars cannot hide.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.nn import functional as F

from .cameras import CameraModel, RayCache
from .data.batch import SkippedBatch
from .data.kitti360 import OCCLUSION, occlusion_filter
from .files import atomic_write_png
from .metrics import NAMES, DepthMetrics
from .models.cost_volume import Sources
from .runtimes import as_runtime
from .viz import panel, to_uint8

log = logging.getLogger(__name__)

ANGLE_BINS = ((0, 30), (30, 60), (60, 90), (90, 180))
MOTION = ("static", "moving")


@dataclasses.dataclass(frozen=True)
class Protocol:
    """Which pixels are scored and on which quantity.

    ``quantity``: "distance" (Euclidean, along the ray) or "z" (depth along the optical axis).
    ``z_range``: keep ground truth whose z lies in this open interval (None: no z condition).
    ``max_range``: keep ground truth whose Euclidean distance is below this (None: no limit).
    ``cap``: (min, max) for ground truth validity and prediction clamping.
    ``occlusion``: LiDAR ground truth only: drop points farther than ``1 + occlusion`` times the
    nearest within 3 pixels (seen by the scanner around an edge the camera cannot see); None keeps
    every projected point. Rendered (dense) ground truth is never filtered.
    """

    name: str
    quantity: str = "distance"
    z_range: tuple[float, float] | None = None
    max_range: float | None = None
    cap: tuple[float, float] = (1e-3, 80.0)
    occlusion: float | None = None

    def describe(self) -> str:
        """The range of ground truth it scores, for messages: "distance 0.001-80 m", ..."""
        parts = [f"{self.quantity} {self.cap[0]:g}-{self.cap[1]:g} m"]
        if self.z_range is not None and (self.quantity, self.z_range) != ("z", self.cap):
            parts.append(f"z {self.z_range[0]:g}-{self.z_range[1]:g} m")
        if self.max_range is not None:
            parts.append(f"distance below {self.max_range:g} m")
        return ", ".join(parts)


PROTOCOLS = {
    # the reference implementation's (the paper's Table 1), exactly: one scan, z > 0, the nearest point
    # per pixel, no occlusion filter; scored where GT z is in (0.3, 60) m and the range below 8 m
    "kitti360": Protocol("kitti360", "distance", (0.3, 60.0), 8.0),
    "kitti360_z": Protocol("kitti360_z", "z", (0.3, 60.0), 8.0),
    # the project's: everything with ground truth up to 80 m, the periphery beyond 90 degrees included,
    # and LiDAR points hidden from the camera dropped
    "full": Protocol("full", "distance", None, None, occlusion=OCCLUSION),
    "full_z": Protocol("full_z", "z", (1e-3, 80.0), None, occlusion=OCCLUSION),
}


def dnet_scale(distance: Tensor, rays: Tensor, camera_height: float, up=(0.0, -1.0, 0.0)) -> float:
    """DNet's dense geometrical constraint: fit the ground from surface normals of the predicted points
    and rescale so the camera sits ``camera_height`` above it. ``distance [H, W]``, ``rays [H, W, 3]``."""
    X = rays * distance[..., None]
    du, dv = X[1:-1, 2:] - X[1:-1, :-2], X[2:, 1:-1] - X[:-2, 1:-1]
    n = F.normalize(torch.linalg.cross(du, dv), dim=-1)
    upv = torch.tensor(up, dtype=X.dtype, device=X.device)
    n = torch.where(((n @ upv) < 0)[..., None], -n, n)
    centre = X[1:-1, 1:-1]
    ground = ((n @ upv) > math.cos(math.radians(15))) & ((centre @ upv) < 0) & (distance[1:-1, 1:-1] > 0)
    if int(ground.sum()) < 20:
        return 1.0
    height = (-(centre[ground] * n[ground]).sum(-1)).median()  # distance of the camera above each patch
    return float(camera_height / height.clamp_min(1e-6))


class Evaluator:
    """Accumulates metrics over a split; ``scalings`` among "none", "median", "dnet".

    An image with no pixel in the protocol's range is counted (``unscored_images``) and named in a
    warning; a split with no scored pixel at all is an error, never a perfect score of zero images."""

    def __init__(
        self,
        protocol: Protocol,
        scalings=("none", "median"),
        camera_height: float | None = None,
        rays: RayCache | None = None,
    ):
        self.protocol, self.scalings, self.camera_height = protocol, tuple(scalings), camera_height
        # every scaling (median included) is applied here, one ratio per image, so that the angle bands
        # are scored with the ratio of the whole image and add up to the headline number
        self.metrics = {s: DepthMetrics(protocol.cap) for s in self.scalings}
        self.by_angle = {(s, b): DepthMetrics(protocol.cap) for s in self.scalings for b in ANGLE_BINS}
        self.by_camera: dict[tuple[str, str], DepthMetrics] = {}  # (scaling, camera name), when named
        self.by_motion = {(s, m): DepthMetrics(protocol.cap) for s in self.scalings for m in MOTION}
        self.ratios: dict[str, list[float]] = {s: [] for s in self.scalings}
        self.rays = rays if rays is not None else RayCache()
        # images fed, and the smallest positive and the largest ground truth on their usable pixels
        self.seen, self.smallest, self.largest = 0, math.inf, -math.inf
        self.unscored: list[str] = []  # images with no pixel in the protocol's range, with their largest

    def update(
        self,
        pred: Tensor,
        gt: Tensor,
        mask: Tensor,
        camera: CameraModel,
        name: str | None = None,
        source: str | None = None,
        frame: str | None = None,
        moving: Tensor | None = None,
    ) -> None:
        """One image: ``pred``/``gt`` ``[H, W]`` distances at the GT resolution, ``mask`` usable pixels;
        ``moving``: ``[H, W]`` bool, the pixels whose ground truth is a moving object (None: none is);
        ``name``: the rig's camera it came from, for the per-camera breakdown (mixed rigs); ``source``:
        "lidar" for a projected scan (the protocol's occlusion filter applies), "lidar_filtered" for
        one filtered already (refused by a protocol without the filter), else a dense map; ``frame``:
        the image's name in reports."""
        rays, valid = self.rays.get(camera, pred.device, pred.dtype)
        self._follow(pred.device)
        p = self.protocol
        gt_z = gt * rays[..., 2]
        keep = self._keep(gt, gt_z, mask, valid, source)
        angle = torch.rad2deg(torch.acos(rays[..., 2].clamp(-1, 1)))
        usable = gt[mask.bool() & valid & torch.isfinite(gt)]
        largest = float(usable.max()) if usable.numel() else 0.0
        self.seen, self.largest = self.seen + 1, max(self.largest, largest)
        if bool((usable > 0).any()):
            self.smallest = min(self.smallest, float(usable[usable > 0].min()))
        q0, g = (pred * rays[..., 2], gt_z) if p.quantity == "z" else (pred, gt)
        scored = keep & (g > p.cap[0]) & (g < p.cap[1])
        any_scored = bool(scored.any())
        if not any_scored:
            why = f"largest {largest:g} m" if largest > 0 else "no positive ground truth"
            self.unscored.append(f"{frame or f'image {self.seen}'} ({why})")
        for scaling in self.scalings:
            q = q0
            if not any_scored:
                ratio = None
            elif scaling == "median":
                ratio = float(g[scored].median() / q[scored].median().clamp_min(1e-12))
            elif scaling == "dnet":
                if self.camera_height is None:
                    raise ValueError("dnet scaling needs camera_height")
                ratio = dnet_scale(pred, rays, self.camera_height)
            else:
                ratio = 1.0
            if ratio is not None:  # an image without a scored pixel has no ratio to average
                q = q * ratio
                self.ratios[scaling].append(ratio)
            self.metrics[scaling].update(q[None], g[None], keep[None])
            if name is not None:
                if (scaling, name) not in self.by_camera:  # built once, on the images' device
                    self.by_camera[(scaling, name)] = DepthMetrics(p.cap).to(pred.device)
                self.by_camera[(scaling, name)].update(q[None], g[None], keep[None])
            for lo, hi in ANGLE_BINS:
                self.by_angle[(scaling, (lo, hi))].update(
                    q[None], g[None], (keep & (angle >= lo) & (angle < hi))[None]
                )
            moves = torch.zeros_like(keep) if moving is None else moving.bool()
            self.by_motion[(scaling, "static")].update(q[None], g[None], (keep & ~moves)[None])
            self.by_motion[(scaling, "moving")].update(q[None], g[None], (keep & moves)[None])

    def _keep(self, gt: Tensor, gt_z: Tensor, mask: Tensor, valid: Tensor, source: str | None) -> Tensor:
        """The pixels with ground truth the protocol keeps, before its cap (see :meth:`update`)."""
        p = self.protocol
        keep = mask.bool() & valid & (gt > 0)
        if source == "lidar_filtered" and p.occlusion is None:
            raise ValueError(
                f"the {p.name} protocol scores every projected LiDAR point, but this ground truth was "
                "occlusion-filtered: read it with lidar_occlusion=None (FisheyeDataModule.scoring_loader)"
            )
        if source in ("lidar", "lidar_filtered") and p.occlusion is not None:
            keep &= ~occlusion_filter(gt, p.occlusion)
        if p.z_range is not None:
            keep &= (gt_z > p.z_range[0]) & (gt_z < p.z_range[1])
        if p.max_range is not None:
            keep &= gt < p.max_range
        return keep

    def scored(self, gt: Tensor, mask: Tensor, camera: CameraModel, source: str | None = None) -> Tensor:
        """``[H, W]`` bool: the pixels of one image that :meth:`update` scores (its arguments, less the
        prediction): usable, with a ray, kept by the protocol and inside its cap."""
        rays, valid = self.rays.get(camera, gt.device, gt.dtype)
        gt_z = gt * rays[..., 2]
        g = gt_z if self.protocol.quantity == "z" else gt
        cap = self.protocol.cap
        return self._keep(gt, gt_z, mask, valid, source) & (g > cap[0]) & (g < cap[1])

    def _follow(self, device: torch.device) -> None:
        """Keep every metric's state on the device of the images it is fed (``eval.py device=cuda``)."""
        groups = (self.metrics, self.by_angle, self.by_camera, self.by_motion)
        for metric in (m for group in groups for m in group.values()):
            if metric.device != device:
                metric.to(device)

    def compute(self, where: str = "the scored images") -> dict[str, Any]:
        """The results; a ``ValueError`` naming ``where`` (the split) when no pixel of it was scored."""
        p, n = self.protocol, self.seen
        if n == len(self.unscored):
            if n == 0:
                raise ValueError(f"{where}: no image to score")
            hint = ": millimetres?" if self.smallest >= p.cap[1] else ""  # every distance out of reach
            if self.largest <= 0:
                hint = ": no positive distance; 0 marks a pixel without ground truth"
            raise ValueError(
                f"{where}: no pixel of the {n} images' ground truth lies in the {p.name} protocol's range "
                f"({p.describe()}) (largest ground truth value {self.largest:g}{hint})"
            )
        if self.unscored:
            log.warning(
                "%s: %d of %d images have no ground truth in the %s protocol's range (%s) and are not "
                "scored (unscored_images): %s",
                where,
                len(self.unscored),
                n,
                p.name,
                p.describe(),
                ", ".join(self.unscored[:3]) + (", ..." if len(self.unscored) > 3 else ""),
            )
        out: dict[str, Any] = {"protocol": dataclasses.asdict(p), "unscored_images": len(self.unscored)}
        for scaling in self.scalings:
            out[scaling] = _summary(self.metrics[scaling])
            if scaling != "none" and self.ratios[scaling]:
                out[scaling]["scale_ratio"] = float(sum(self.ratios[scaling]) / len(self.ratios[scaling]))
            out[f"{scaling}_by_angle"] = {
                f"{lo}-{hi}": _summary(self.by_angle[(scaling, (lo, hi))]) for lo, hi in ANGLE_BINS
            }
            out[f"{scaling}_by_motion"] = {m: _summary(self.by_motion[(scaling, m)]) for m in MOTION}
            cameras = sorted(n for s, n in self.by_camera if s == scaling)
            if cameras:
                out[f"{scaling}_by_camera"] = {n: _summary(self.by_camera[(scaling, n)]) for n in cameras}
        return out


def _summary(metrics: DepthMetrics) -> dict[str, float | int | None]:
    """One group's metrics as plain numbers, with the number of images that had pixels in it; a group
    without any (an angle band that no scored pixel falls in) has None for each metric, never 0."""
    if int(metrics.images) == 0:
        return dict.fromkeys(NAMES) | {"images": 0}
    return {k: float(v) for k, v in metrics.compute().items()} | {"images": int(metrics.images)}


@torch.no_grad()
def evaluate(
    model,
    loader,
    train_size: tuple[int, int] | None,
    protocols: list[str],
    scalings=("none", "median"),
    camera_height: float | None = None,
    pictures: Path | None = None,
    n_pictures: int = 4,
    where: str = "the scored split",
    recording: ScoredRecording | None = None,
) -> dict[str, Any]:
    """Run ``model`` over a loader of native-resolution samples with ground truth ``distance``. ``model``:
    a trained module (run in float32 at ``train_size``) or a runtime of :mod:`fisheyedepth.runtimes`
    (an exported file, bf16), which brings its own input size. ``where`` names the split in messages; a
    split of which no pixel could be scored is a ``ValueError``, never a perfect score. ``recording``:
    every image also goes into it, scored by the first protocol (``eval.py rerun=true``)."""
    model = as_runtime(model, train_size)
    rays = RayCache()  # one per run, shared by the protocols
    evaluators = {name: Evaluator(PROTOCOLS[name], scalings, camera_height, rays) for name in protocols}
    written, skipped = 0, []
    for batch in loader:
        skipped += batch.skipped_frames  # frames that could not be read (skip_bad_frames)
        if isinstance(batch, SkippedBatch):
            continue
        if batch.distance is None:
            raise ValueError("the evaluation split has no ground truth (distance maps or LiDAR)")
        views = Sources.of(batch) if model.sources else None  # a multi-view network's frames to match
        pred = model.distance(batch.image, batch.camera, views).float()
        gt, mask = batch.distance.to(pred), batch.mask.to(pred) > 0.5
        names = batch.camera_name or [None] * len(batch)
        sources = batch.distance_source or [None] * len(batch)
        frames = batch.frame or [None] * len(batch)
        moving = batch.moving.to(pred.device) > 0.5 if batch.moving is not None else [None] * len(batch)
        for i, cam in enumerate(batch.camera):
            moves = None if moving[i] is None else moving[i][0]
            for ev in evaluators.values():
                ev.update(pred[i, 0], gt[i, 0], mask[i, 0], cam, names[i], sources[i], frames[i], moves)
            if recording is not None:
                recording.add(batch, i, pred[i, 0], evaluators[protocols[0]])
            if pictures is not None and written < n_pictures:
                pictures.mkdir(parents=True, exist_ok=True)
                scored = batch.distance[i] * (batch.mask[i] > 0.5)  # no error shown on the ego body
                pic = panel(batch.image[i], pred[i].cpu(), scored, 0.5, 80.0)
                atomic_write_png(pictures / f"panel_{written:03d}.png", pic[..., ::-1])
                written += 1
    if skipped:
        log.warning(
            "%d frame(s) of the split could not be read and are not scored: %s", len(skipped), skipped[:3]
        )
        if not any(ev.seen for ev in evaluators.values()):
            raise ValueError(f"{where}: none of its {len(skipped)} frame(s) could be read: {skipped[0]}")
    return {name: ev.compute(where) | {"skipped_frames": len(skipped)} for name, ev in evaluators.items()}


@contextlib.contextmanager
def scored_recording(path: Path | None):
    """A :class:`ScoredRecording` into ``path`` (a :class:`fisheyedepth.rerun3d.RigRecorder`: put in place
    whole when the block ends, not at all when it fails); None without a path."""
    if path is None:
        yield None
        return
    from .rerun3d import RigRecorder

    with RigRecorder(path, "fisheyedepth-eval") as recorder:
        yield ScoredRecording(recorder)


class ScoredRecording:
    """The scored images of an evaluation as instants of a Rerun recording
    (:class:`fisheyedepth.rerun3d.RigRecorder`), each logged as it is scored: the images of one frame
    (``<sequence>/<camera>/<key>``: every camera of the rig at that key, whatever order the split
    gives them in) make one instant, their cameras placed on the body by the layout's ``cam_to_body``
    (the body at the identity: a split has no world pose), each with its ``distance``, its
    ``ground_truth`` where the protocol scores it, and its unscaled ``abs_rel`` there. ``frame``: the
    instant's index, in the order frames first appear; ``time``: the frame's key where it is a whole
    number (a rig's timestamp in nanoseconds, a KITTI-360 frame's number), else that index."""

    def __init__(self, recorder):
        self.recorder = recorder
        self.instants: dict[tuple[str, str], int] = {}  # (sequence, key) -> instant index
        self.images = 0

    def add(self, batch, i: int, pred: Tensor, evaluator: Evaluator) -> None:
        """Image ``i`` of ``batch`` and its prediction ``pred`` (``[H, W]`` metres), its ground truth where
        ``evaluator`` scores it."""
        from .rerun3d import CameraView

        camera = batch.camera[i]
        frame, named = (batch.frame[i] if batch.frame else None), batch.camera_name
        sequence, name, key = _frame_parts(frame, named[i] if named else None, self.images)
        self.images += 1
        index = self.instants.setdefault((sequence, key), len(self.instants))
        source = batch.distance_source[i] if batch.distance_source else None
        gt = batch.distance[i, 0].to(pred)
        scored = evaluator.scored(gt, batch.mask[i, 0].to(pred) > 0.5, camera, source)
        distance, truth = pred.cpu().numpy(), (gt * scored).cpu().numpy()
        scores = {"abs_rel": abs_rel(distance, truth)}
        view = CameraView(camera, to_uint8(batch.image[i]), {"distance": distance}, truth, scores)
        extrinsic = batch.cam_to_body[i].double().numpy() if batch.cam_to_body is not None else np.eye(4)
        time_ns = int(key) if key.isdigit() else index
        self.recorder.instant(time_ns, index, {name: view}, cam_to_body={name: extrinsic})


def _frame_parts(frame: str | None, camera_name: str | None, index: int) -> tuple[str, str, str]:
    """``(sequence, camera, key)`` of a frame named ``<sequence>/<camera>/<key>`` (the camera as the
    dataset names it where it does); an unnamed image is its own instant."""
    parts = (frame or "").split("/")
    if len(parts) >= 3:
        return "/".join(parts[:-2]), camera_name or parts[-2], parts[-1]
    return "", camera_name or "camera", f"image{index}"


def abs_rel(distance: np.ndarray, truth: np.ndarray) -> float:
    """Mean ``|distance - truth| / truth`` over the pixels with both (NaN where none has)."""
    both = (truth > 0) & np.isfinite(distance) & (distance > 0)
    if not both.any():
        return float("nan")
    return float((np.abs(distance[both] - truth[both]) / truth[both]).mean())
