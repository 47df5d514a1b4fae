"""Estimating a camera's vehicle-body mask from a recording (KITTI-360 ships none).

The ego vehicle's body is fixed to the camera, so its pixels barely change while the world moves past:
the per-pixel temporal standard deviation of the exposure-normalised images is low on the body and high
elsewhere. Two other kinds of pixel are just as still and are *not* the body:

- pixels without a ray (outside the fisheye's image circle): the camera model says which; they are
  written as usable (255), as the synthetic world's exact masks are;
- a smooth, cloudless sky, whose colour depends only on the ray's elevation: a still pixel whose ray
  points more than ``sky_elevation`` degrees above the body's horizon is sky (a vehicle's own cameras
  see its body below their horizon).

The split between still and moving pixels is a threshold on the log standard deviation, by default
Kittler and Illingworth's minimum-error threshold over the pixels that can be body: unlike Otsu's, it
stays beside the narrow mode of the body's pixels instead of cutting into the broad mode of the world's,
where distant scenery near the direction of travel is also fairly still. Components of either class
smaller than ``min_area`` are then removed. The mask is written where the layout reads it:

    fisheyedepth-estimate-mask --root data/kitti360 --sequence 2013_05_28_drive_0000_sync --camera image_02
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from ..cameras import CameraModel, compute_rays
from ..files import atomic_write_bytes
from .files import read_checked
from .kitti360 import Kitti360Layout
from .layouts import RigLayout

MIN_FRAMES = 10  # fewer frames give no meaningful temporal statistics
KITTI360_UP = (0.0, 0.0, -1.0)  # KITTI-360's pose frame is x forward, y right, z down
WORLD_UP = np.array([0.0, 0.0, 1.0])  # odometry worlds are gravity-aligned, z up (ROS REP 105, Aria)
LOG_FLOOR = 1e-4  # added to the std before the log (a perfectly still pixel has std 0)
# Frames whose 90th percentile of temporal std (exposure-normalised) lies below this do not move: one grey
# level of jitter at mid-grey. A moving recording's is well above (the synthetic worlds': 0.14 or more).
STILL_STD = 0.01

Layout = Kitti360Layout | RigLayout


@dataclasses.dataclass(frozen=True)
class BodyMask:
    usable: np.ndarray  # bool [H, W]; False = the ego vehicle's body (pixels without a ray are usable)
    has_ray: np.ndarray  # bool [H, W]
    std: np.ndarray  # float [H, W]: temporal std of the exposure-normalised images
    threshold: float  # the std below which a pixel that can be body is body
    frames: int  # images the statistics were taken over

    @property
    def body_fraction(self) -> float:
        """Fraction of the pixels with a ray that are body."""
        return float((~self.usable & self.has_ray).sum() / max(int(self.has_ray.sum()), 1))


# ------------------------------------------------------------------------------------ the statistics
def normalise_exposure(image: np.ndarray, has_ray: np.ndarray) -> np.ndarray:
    """``image`` ([H, W] or [H, W, C]) in float64, divided by its mean over the pixels with a ray: a change
    of exposure (a global gain) then changes nothing, and is not taken for motion."""
    values = np.asarray(image, dtype=np.float64)
    return values / max(float(values[has_ray].mean()), 1e-6)


def temporal_statistics(images: Iterable[np.ndarray], has_ray: np.ndarray) -> tuple[np.ndarray, int]:
    """Per-pixel temporal std of the exposure-normalised ``images`` (colour channels pooled as
    ``sqrt(mean_c var_c)``) and the number of images. Streams: memory does not grow with their number."""
    count, total, squares = 0, 0.0, 0.0
    for image in images:
        x = normalise_exposure(image, has_ray)
        total, squares, count = total + x, squares + x * x, count + 1
    if count == 0:
        raise ValueError("no images to take temporal statistics over")
    mean = total / count
    var = np.maximum(squares / count - mean * mean, 0.0)
    if var.ndim == 3:
        var = var.mean(axis=2)
    return np.sqrt(var), count


def ray_elevation(
    camera: CameraModel, cam_to_body: np.ndarray, up: Sequence[float]
) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's ray elevation above the body's horizon (radians, [H, W]), and whether it has a ray.

    A ray ``d`` of the camera frame is ``R d`` in the body frame (``R``: the rotation of
    ``cam_to_body``), at elevation ``asin(R d . up)`` with ``up`` the body frame's up direction."""
    rays = compute_rays(camera, dtype=torch.float64)
    d = rays.rays.numpy() @ np.asarray(cam_to_body, dtype=np.float64)[:3, :3].T
    up = np.asarray(up, dtype=np.float64)
    return np.arcsin(np.clip(d @ (up / np.linalg.norm(up)), -1.0, 1.0)), rays.valid.numpy()


def minimum_error_threshold(values: np.ndarray, bins: int = 256) -> float:
    """Kittler and Illingworth's minimum-error threshold of ``values`` (1-D): the cut ``t`` that best
    explains the histogram as two Gaussians, each with its own spread, by minimising
    ``P0 log var0 + P1 log var1 - 2 (P0 log P0 + P1 log P1)`` (class ``0``: values up to ``t``)."""
    hist, edges = np.histogram(values, bins=bins)
    centres = (edges[:-1] + edges[1:]) / 2
    floor = (edges[1] - edges[0]) ** 2 / 12  # a class within one bin has that bin's variance
    p = hist / hist.sum()
    p0, m0, s0 = np.cumsum(p), np.cumsum(p * centres), np.cumsum(p * centres**2)
    p1, m1, s1 = 1 - p0, m0[-1] - m0, s0[-1] - s0
    with np.errstate(divide="ignore", invalid="ignore"):
        var0 = np.maximum(s0 / p0 - (m0 / p0) ** 2, floor)
        var1 = np.maximum(s1 / p1 - (m1 / p1) ** 2, floor)
        cost = p0 * np.log(var0) + p1 * np.log(var1) - 2 * (p0 * np.log(p0) + p1 * np.log(p1))
    cost[(p0 <= 0) | (p1 <= 1e-12)] = np.inf  # both classes must hold values
    return float(edges[1:][np.argmin(cost)])


def remove_small_components(mask: np.ndarray, min_area: int) -> np.ndarray:
    """``mask`` without its 8-connected components of fewer than ``min_area`` pixels."""
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_area
    keep[0] = False  # label 0 is what lies outside the mask
    return keep[labels]


def estimate_body_mask(
    images: Iterable[np.ndarray],
    camera: CameraModel,
    cam_to_body: np.ndarray,
    up: Sequence[float] = KITTI360_UP,
    threshold: float | None = None,
    sky_elevation: float = 5.0,
    min_area: float = 0.002,
    source: str = "the images",
) -> BodyMask:
    """The ego body in ``camera``'s ``images`` (ideally many, spread over a recording), as seen from
    ``cam_to_body`` with the body frame's ``up`` direction.

    A pixel is body when it has a ray that points at most ``sky_elevation`` degrees above the horizon
    (it can be body) and a temporal std (:func:`temporal_statistics`) below ``threshold`` (default: the
    minimum-error threshold of the log std over the pixels that can be body). Body components and holes
    in the body smaller than ``min_area`` (a fraction of the pixels with a ray) are then removed.
    Frames that do not change over time (a parked camera, one frame repeated) are refused: every pixel
    would look like body. ``source`` names them in that error.
    """
    elevation, has_ray = ray_elevation(camera, cam_to_body, up)
    std, count = temporal_statistics(images, has_ray)
    if not np.percentile(std[has_ray], 90) >= STILL_STD:
        raise ValueError(
            f"the {count} frames of {source} do not change over time (9 pixels in 10 vary by less than "
            f"{STILL_STD:.0%} of the mean brightness): a body mask needs a moving camera"
        )
    can_be_body = has_ray & (elevation <= np.deg2rad(sky_elevation))
    if not can_be_body.any():
        raise ValueError(
            f"no pixel has a ray below {sky_elevation} degrees of elevation: nothing can be body"
        )
    if threshold is None:
        threshold = float(np.exp(minimum_error_threshold(np.log(std[can_be_body] + LOG_FLOOR)))) - LOG_FLOOR
    area = max(1, round(min_area * int(has_ray.sum())))
    body = remove_small_components(can_be_body & (std < threshold), area)
    body = has_ray & ~remove_small_components(has_ray & ~body, area)  # fill the small holes
    return BodyMask(~body, has_ray, std, threshold, count)


# ---------------------------------------------------------------------------------- from a layout
def sample_evenly(count: int, frames: int) -> list[int]:
    """``frames`` indices spread evenly over ``range(count)`` (all of them when there are fewer)."""
    return sorted({int(i) for i in np.linspace(0, count - 1, min(frames, count)).round()})


def body_up(layout: Layout, sequence: str, camera: str) -> np.ndarray:
    """The body frame's up direction: KITTI-360's pose frame is z down; a rig's body frame is its own,
    so its up is the world's ``z`` seen from the body, averaged over the sequence's poses."""
    if isinstance(layout, Kitti360Layout):
        return np.array(KITTI360_UP)
    up = np.mean([frame.pose[:3, :3].T @ WORLD_UP for frame in layout.frames(sequence, camera)], axis=0)
    return up / np.linalg.norm(up)


def default_mask_path(layout: Layout, camera: str) -> Path:
    """Where ``layout`` reads ``camera``'s body mask (KITTI-360: ``calibration/body_mask_<camera>.png``;
    a rig: the ``mask:`` in ``rig.yaml``), or ``masks/<camera>.png`` for a rig camera that names none
    (``rig.yaml`` must then name it)."""
    return layout.mask_paths[camera] or layout.root / "masks" / f"{camera}.png"


def read_frames(paths: Sequence[Path], camera: CameraModel, progress: bool = True) -> Iterator[np.ndarray]:
    """The images at ``paths`` (BGR), each checked to be ``camera``'s size; errors name the file."""
    for path in tqdm(paths, desc="reading frames", unit="frame", disable=not progress):
        yield read_checked(path, (camera.width, camera.height))


def write_body_mask(
    layout: Layout,
    sequence: str,
    camera: str,
    frames: int = 200,
    out: str | os.PathLike | None = None,
    threshold: float | None = None,
    sky_elevation: float = 5.0,
    up: Sequence[float] | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> dict:
    """Estimate ``camera``'s body mask from ``frames`` images spread evenly over ``sequence`` and write it
    as a PNG (255 = usable, 0 = body) to ``out`` (default: where ``layout`` reads it), atomically. An
    existing file is kept unless ``overwrite``. ``up``: the body frame's up (default: :func:`body_up`).
    Returns a summary: the file, the body fraction, the threshold, the frames and the up direction."""
    if frames < MIN_FRAMES:
        raise ValueError(f"frames: {frames}, need at least {MIN_FRAMES} for temporal statistics")
    if camera not in layout.cameras:
        raise KeyError(f"{layout.root}: no camera {camera!r}; cameras: {sorted(layout.cameras)}")
    out = Path(out) if out is not None else default_mask_path(layout, camera)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists; pass --overwrite (overwrite=True) to replace it")
    recording = layout.frames(sequence, camera)
    if len(recording) < MIN_FRAMES:
        raise ValueError(
            f"{layout.root}: sequence {sequence!r} has {len(recording)} frames of camera {camera!r}, "
            f"need at least {MIN_FRAMES} for temporal statistics"
        )
    spec = layout.cameras[camera]
    up = np.asarray(up if up is not None else body_up(layout, sequence, camera), dtype=np.float64)
    if up.shape != (3,) or not np.linalg.norm(up) > 0:
        raise ValueError(f"up: {up.tolist()}, expected a non-zero 3-vector (the body frame's up)")
    paths = [layout.image(sequence, camera, recording[i]) for i in sample_evenly(len(recording), frames)]
    mask = estimate_body_mask(
        read_frames(paths, spec.camera, progress),
        spec.camera,
        spec.cam_to_body,
        up,
        threshold,
        sky_elevation,
        source=f"camera {camera!r} in {paths[0].parent}",
    )
    ok, png = cv2.imencode(".png", np.where(mask.usable, 255, 0).astype(np.uint8))
    if not ok:
        raise OSError(f"{out}: could not encode the mask as PNG")
    atomic_write_bytes(out, png.tobytes())
    return {
        "mask": str(out),
        "camera": camera,
        "body_fraction": round(mask.body_fraction, 4),
        "threshold": float(f"{mask.threshold:.6g}"),
        "frames": mask.frames,
        "up": [round(float(v), 4) for v in up],
    }


def open_layout(kind: str, root: Path, camera: str) -> Layout:
    """The layout at ``root`` with ``camera`` alone, not expecting its mask: this command may be about
    to write it."""
    layout = RigLayout if kind == "rig" else Kitti360Layout
    return layout(root, cameras=[camera], expect_masks=False)
