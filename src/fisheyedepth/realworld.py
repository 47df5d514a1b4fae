"""Scores on real photographs: every real fisheye frame with metric ground truth, in one place.

The frames live outside the repository (``FISHEYEDEPTH_REALDATA``, default ``../shared/realdata``;
their README describes them):

- ``kitti360``: the left KITTI-360 fisheye (Mei model) against its Velodyne scan projected as
  Euclidean distances, inside the ego-vehicle body mask; scored under the ``full`` protocol (every
  point up to 80 m that the camera can see, the occlusion filter on), and the ``kitti360`` protocol
  (under 8 m) in the JSON record.
- ``scannetpp``: a ScanNet++ DSLR fisheye (Kannala-Brandt) against depth rendered from the laser scan.
- ``adt_{left,right}_{0,1}``: the two grey SLAM cameras of Aria Digital Twin (native Fisheye624)
  against the digital twin's rendered depth, frames 0 and 1; the grey image goes to the network as
  three equal channels.

The dense frames store z-depth in millimetres; :func:`z_to_distance` turns it into distance along each
pixel's ray with the frame's own calibration. Indoors the cap is the frame's ground-truth range
rounded up to a whole metre (:func:`indoor_cap`); outdoors it is 80 m.

Each frame is scored unscaled and median-scaled over its ground-truth pixels inside the camera's
valid domain, beside a constant map at the ground truth's median distance (:func:`constant_map`): the
score that knows nothing of the image, which any real-world score must beat. The network runs at its
checkpoint's input size on the image and camera resized alike, its distance upsampled to the frame's
size (:mod:`fisheyedepth.runtimes`). A frame whose files are absent is :class:`Missing`, named with
the path it lacks; a malformed file raises a ``ValueError`` naming the file and the field.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections.abc import Sequence
from functools import cached_property
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor

from .cameras import (
    CalibrationError,
    CameraModel,
    Fisheye624Camera,
    RayCache,
    camera_from_mapping,
    load_camera,
    load_json,
)
from .cameras.fisheye624 import ARIA_PARAMS
from .cameras.io import field
from .evaluation import PROTOCOLS, Evaluator, Protocol
from .images import read_image
from .metrics import DepthMetrics
from .runtimes import OnnxRuntime, TorchRuntime, TrainedDepthNet
from .utils import atomic_write_bytes, atomic_write_text
from .viz import panel

FRAME_SETS = ("kitti360", "scannetpp", "adt")  # what ``--frames`` chooses from; adt holds four frames
FOLDERS = {"kitti360": "kitti360_frame", "scannetpp": "scannetpp_frame", "adt": "adt_slam"}
ADT_FRAMES = (
    ("camera-slam-left", 0),
    ("camera-slam-left", 1),
    ("camera-slam-right", 0),
    ("camera-slam-right", 1),
)
OUTDOOR_VIEW = (0.5, 80.0)  # the colour scale of the pictures, metres
INDOOR_NEAR = 0.2
RAYS = RayCache(max_entries=16)  # every frame's camera at its native size, shared by all the scoring
# Published zero-shot metric distance on KITTI-360's fisheye frames, 80 m cap (abs_rel, a1; None where
# the paper gives none): what a real-world score is read against.
ANCHORS = (
    ("Depth Any Camera", 0.149, 0.822),
    ("UniDAC", 0.141, 0.836),
    ("Metric3D v2", 0.200, None),
    ("UniK3D", 0.244, None),
)


def default_root() -> Path:
    """``$FISHEYEDEPTH_REALDATA``, else ``../shared/realdata`` beside the project's root."""
    here = Path(__file__).resolve().parents[2]
    return Path(os.environ.get("FISHEYEDEPTH_REALDATA", here.parent / "shared" / "realdata"))


@dataclasses.dataclass(frozen=True)
class Missing:
    """A frame that cannot be scored because ``path`` (a file or folder it needs) is absent."""

    name: str
    path: Path


@dataclasses.dataclass(frozen=True, eq=False)
class RealFrame:
    """One real image with metric ground truth, at its native size."""

    name: str
    image: Tensor  # [1, 3, H, W] RGB in [0, 1]
    camera: CameraModel
    distance: Tensor  # [H, W] metres along the ray, 0 without ground truth
    mask: Tensor  # [H, W] bool: usable pixels (not the ego body)
    protocols: tuple[Protocol, ...]  # the first is the one the table shows
    files: tuple[Path, ...]  # what it was read from
    source: str | None = None  # "lidar" for a projected scan, None for a dense map
    view: tuple[float, float] = OUTDOOR_VIEW

    @property
    def protocol(self) -> Protocol:
        return self.protocols[0]

    @cached_property
    def scored(self) -> Tensor:
        """``[H, W]`` bool: the pixels the first protocol scores."""
        return Evaluator(self.protocol, rays=RAYS).scored(self.distance, self.mask, self.camera, self.source)


# ------------------------------------------------------------------ reading the files
def _need(path: Path, name: str) -> Missing | None:
    return None if path.exists() else Missing(name, path)


def read_uint16(path: Path, unit: str) -> np.ndarray:
    """A one-channel 16-bit PNG (``unit``: what a value means, for the message); errors name the file."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found")
    data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None or data.dtype != np.uint16 or data.ndim != 2:
        kind = "unreadable" if data is None else f"{data.dtype} with shape {data.shape}"
        raise ValueError(f"{path}: expected a one-channel uint16 PNG ({unit}), got {kind}")
    return data


def read_rgb(path: Path) -> Tensor:
    """``[1, 3, H, W]`` float RGB in [0, 1]; a grey file becomes three equal channels."""
    bgr = read_image(path).bgr
    return torch.from_numpy(np.ascontiguousarray(bgr[..., ::-1])).permute(2, 0, 1).float()[None] / 255.0


def read_json(path: Path) -> dict[str, Any]:
    try:
        data = load_json(path.read_bytes(), path)  # not JSON, not text, nested too deeply: names the file
    except OSError as err:
        raise CalibrationError(path, None, f"not readable JSON ({err})") from None
    if not isinstance(data, dict):
        raise CalibrationError(path, None, f"expected a JSON object, got {type(data).__name__}")
    return data


def _number(value: Any, key: str, path: Path) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise CalibrationError(path, key, f"expected a number, got {value!r}")
    return float(value)


def _numbers(values: Any, count: int, key: str, path: Path) -> list[float]:
    """``values`` as ``count`` finite numbers; a CalibrationError naming ``key`` otherwise."""
    if not isinstance(values, list) or len(values) != count:
        got = f"{len(values)} values" if isinstance(values, list) else repr(values)
        raise CalibrationError(path, key, f"expected a list of {count} numbers, got {got}")
    return [_number(v, f"{key}[{i}]", path) for i, v in enumerate(values)]


def _pixels(value: float, key: str, path: Path) -> int:
    if not value.is_integer() or value <= 0:
        raise CalibrationError(path, key, f"expected a positive whole number of pixels, got {value:g}")
    return int(value)


def _check_size(path: Path, array: np.ndarray | Tensor, camera: CameraModel, calibration: Path) -> None:
    h, w = array.shape[-2:]
    if (w, h) != (camera.width, camera.height):
        raise ValueError(f"{path}: {w}x{h}, but {calibration.name} says {camera.width}x{camera.height}")


def z_to_distance(z: Tensor, camera: CameraModel) -> Tensor:
    """Z-depth ``[H, W]`` (along the optical axis, 0 = unknown) as distance along each pixel's ray,
    ``z |ray| / ray_z``; 0 where z is 0 or the pixel has no ray in front of the camera. The rays are
    the evaluation's (float32, correctly rounded from float64), the division in float64."""
    rays, valid = RAYS.get(camera)
    rays = rays.double()
    front = valid & (rays[..., 2] > 1e-9)
    ratio = rays.norm(dim=-1) / torch.where(front, rays[..., 2], torch.ones_like(rays[..., 2]))
    zd = z.to(torch.float64)
    return torch.where(front & (zd > 0), zd * ratio, torch.zeros_like(zd)).to(z.dtype)


def indoor_cap(distance: Tensor, mask: Tensor | None = None) -> float:
    """The frame's ground-truth range rounded up to a whole metre: the largest distance's floor + 1."""
    usable = distance[(distance > 0) if mask is None else (distance > 0) & mask]
    if usable.numel() == 0:
        raise ValueError("no positive ground truth")
    return float(math.floor(float(usable.max())) + 1)


def _indoor(name: str, distance: Tensor, camera: CameraModel, path: Path) -> tuple[Protocol, ...]:
    rays_valid = RAYS.get(camera)[1]
    try:
        cap = indoor_cap(distance, rays_valid)
    except ValueError:
        raise ValueError(
            f"{path}: no pixel with a positive depth inside the camera's field of view"
        ) from None
    return (Protocol(name, "distance", None, None, cap=(1e-3, cap)),)


def load_kitti360(folder: Path, camera: str = "image_02") -> RealFrame | Missing:
    """``folder``/``camera``.yaml, ``camera``_rgb.png, ``camera``_body_mask.png and
    ``camera``_lidar_distance.png (uint16, metres * 256, 0 = no return), checked against each other."""
    calibration = folder / f"{camera}.yaml"
    paths = {k: folder / f"{camera}_{k}.png" for k in ("rgb", "body_mask", "lidar_distance")}
    for path in (folder, calibration, *paths.values()):
        if (gone := _need(path, "kitti360")) is not None:
            return gone
    cam = load_camera(calibration)
    image = read_rgb(paths["rgb"])
    mask = cv2.cvtColor(read_image(paths["body_mask"]).bgr, cv2.COLOR_BGR2GRAY) > 127
    lidar = read_uint16(paths["lidar_distance"], "metres * 256").astype(np.float32) / 256.0
    for key, array in (("rgb", image), ("body_mask", mask), ("lidar_distance", lidar)):
        _check_size(paths[key], array, cam, calibration)
    return RealFrame(
        "kitti360",
        image,
        cam,
        torch.from_numpy(lidar),
        torch.from_numpy(mask),
        (PROTOCOLS["full"], PROTOCOLS["kitti360"]),
        (calibration, *paths.values()),
        source="lidar",
    )


def scannetpp_camera(path: Path) -> CameraModel:
    """``calibration.json``: OpenCV fisheye (Kannala-Brandt) ``width height fx fy cx cy k1..k4``."""
    data = read_json(path)
    keys = ("width", "height", "fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")
    values: dict[str, Any] = {key: _number(field(data, key, path), key, path) for key in keys}
    for key in ("width", "height"):
        values[key] = _pixels(values[key], key, path)
    return camera_from_mapping({"model": "kannala_brandt", **values}, path)


def load_scannetpp(folder: Path) -> RealFrame | Missing:
    """``folder``/rgb.jpg, calibration.json (Kannala-Brandt) and depth_z_mm.png (uint16 z-depth in mm)."""
    calibration, rgb, depth = folder / "calibration.json", folder / "rgb.jpg", folder / "depth_z_mm.png"
    for path in (folder, calibration, rgb, depth):
        if (gone := _need(path, "scannetpp")) is not None:
            return gone
    return z_depth_frame("scannetpp", rgb, depth, scannetpp_camera(calibration), calibration)


def z_depth_frame(
    name: str, image_path: Path, depth_path: Path, cam: CameraModel, calibration: Path
) -> RealFrame:
    """An indoor frame: the image, and its uint16 z-depth in millimetres turned into distance along each
    pixel's ray (every pixel with depth scored, capped at the frame's range)."""
    image = read_rgb(image_path)
    z = read_uint16(depth_path, "millimetres of z-depth")
    _check_size(image_path, image, cam, calibration)
    _check_size(depth_path, z, cam, calibration)
    distance = z_to_distance(torch.from_numpy(z.astype(np.float32) / 1000.0), cam)
    mask = torch.ones_like(distance, dtype=torch.bool)
    protocols = _indoor(name, distance, cam, depth_path)
    return RealFrame(
        name,
        image,
        cam,
        distance,
        mask,
        protocols,
        (calibration, image_path, depth_path),
        view=(INDOOR_NEAR, protocols[0].cap[1]),
    )


def adt_camera(path: Path, name: str) -> CameraModel:
    """Camera ``name`` of ``adt_sample.json``: ``cameras.<name>.projection_params`` (Fisheye624,
    ``[f, cx, cy, k0..k5, p0, p1, s0..s3]``) and ``image_size`` ``[W, H]``."""
    data = read_json(path)
    key = f"cameras.{name}"
    params_key, size_key = f"{key}.projection_params", f"{key}.image_size"
    params = _numbers(field(data, params_key, path), len(ARIA_PARAMS), params_key, path)
    width, height = (
        _pixels(v, size_key, path) for v in _numbers(field(data, size_key, path), 2, size_key, path)
    )
    values = dict(zip(ARIA_PARAMS, params, strict=True))
    focal = values.pop("f")
    keys = {p: f"{params_key}[{i}]" for i, p in enumerate(ARIA_PARAMS)}
    source = {**keys, "fx": keys["f"], "fy": keys["f"], "width": size_key, "height": size_key}
    mapping = {
        "model": Fisheye624Camera.model_name,
        "width": width,
        "height": height,
        "fx": focal,
        "fy": focal,
    }
    return camera_from_mapping({**mapping, **values, "_source_keys": source}, path)


def _one(folder: Path, pattern: str) -> Path | None:
    found = sorted(folder.glob(pattern))
    if len(found) > 1:
        raise ValueError(
            f"{folder}: {len(found)} files match {pattern} ({found[0].name}, {found[1].name}); expected one"
        )
    return found[0] if found else None


def load_adt(folder: Path) -> list[RealFrame | Missing]:
    """The four Aria Digital Twin SLAM frames with depth: ``{camera}_{i}_<t_ns>.png`` (grey) and
    ``depthskel_{camera}_{i}_<t_ns>.png`` (uint16 z-depth in mm) for each of :data:`ADT_FRAMES`."""
    calibration = folder / "adt_sample.json"
    frames: list[RealFrame | Missing] = []
    cameras: dict[str, CameraModel] = {}
    for camera, index in ADT_FRAMES:
        name = f"adt_{camera.rsplit('-', 1)[1]}_{index}"
        if (gone := _need(folder, name) or _need(calibration, name)) is not None:
            frames.append(gone)
            continue
        image_path = _one(folder, f"{camera}_{index}_*.png")
        depth_path = _one(folder, f"depthskel_{camera}_{index}_*.png")
        if image_path is None or depth_path is None:
            pattern = f"{camera}_{index}_*.png" if image_path is None else f"depthskel_{camera}_{index}_*.png"
            frames.append(Missing(name, folder / pattern))
            continue
        if camera not in cameras:
            cameras[camera] = adt_camera(calibration, camera)
        frames.append(z_depth_frame(name, image_path, depth_path, cameras[camera], calibration))
    return frames


def load_frames(root: Path | None = None, sets: Sequence[str] = FRAME_SETS) -> list[RealFrame | Missing]:
    """Every frame of ``sets`` (see :data:`FRAME_SETS`) under ``root``, in that order; a frame whose
    files are absent as :class:`Missing`."""
    root = default_root() if root is None else Path(root)
    out: list[RealFrame | Missing] = []
    for name in sets:
        if name not in FOLDERS:
            raise ValueError(f"frames: {name!r} is not one of {', '.join(FRAME_SETS)}")
        folder = root / FOLDERS[name]
        if name == "kitti360":
            out.append(load_kitti360(folder))
        elif name == "scannetpp":
            out.append(load_scannetpp(folder))
        else:
            out.extend(load_adt(folder))
    return out


# ------------------------------------------------------------------ scoring
def median_distance(frame: RealFrame) -> float:
    """The median of the ground truth on the scored pixels (the mean of the middle two for an even count)."""
    return float(torch.quantile(frame.distance[frame.scored].double(), 0.5))


def constant_map(frame: RealFrame) -> dict[str, Any]:
    """The baseline: every pixel at the ground truth's median distance, scored like a prediction on the
    pixels the frame scores (its median scaling would change nothing); ``{"distance": m, "pixels": n,
    "none": metrics}``."""
    value = median_distance(frame)
    metrics = DepthMetrics(frame.protocol.cap)
    metrics.update(torch.full_like(frame.distance, value)[None], frame.distance[None], frame.scored[None])
    summary = {k: float(v) for k, v in metrics.compute().items()}
    return {"distance": value, "pixels": int(frame.scored.sum()), "none": summary | {"images": 1}}


def predict(runtime, frame: RealFrame) -> Tensor:
    """``runtime`` (anything with ``distance(images, cameras)``) on the frame: distance ``[H, W]``."""
    return runtime.distance(frame.image, [frame.camera]).float()[0, 0]


def score(runtime, frame: RealFrame) -> tuple[dict[str, Any], Tensor]:
    """The frame scored under each of its protocols, unscaled and median-scaled
    (``{protocol: Evaluator.compute()}``), and the predicted distance ``[H, W]``."""
    pred = predict(runtime, frame)
    results = {}
    for protocol in frame.protocols:
        evaluator = Evaluator(protocol, ("none", "median"), rays=RAYS)
        evaluator.update(
            pred,
            frame.distance.to(pred),
            frame.mask.to(pred.device),
            frame.camera,
            source=frame.source,
            frame=frame.name,
        )
        results[protocol.name] = evaluator.compute(frame.name)
    return results, pred


def picture(frame: RealFrame, pred: Tensor, width: int = 350) -> np.ndarray:
    """Input | prediction | ground truth (the scored pixels; a sparse scan's nearest point per block, so
    it stays visible) | relative error, ``width`` px a tile, BGR uint8."""
    H, W = pred.shape
    size = (width, round(H * width / W))
    image = cv2.resize(frame.image[0].permute(1, 2, 0).numpy(), size, interpolation=cv2.INTER_AREA)
    has_ray = RAYS.get(frame.camera)[1].numpy().astype(np.uint8)
    small = cv2.resize(pred.cpu().numpy(), size, interpolation=cv2.INTER_AREA)
    small[cv2.resize(has_ray, size, interpolation=cv2.INTER_NEAREST) == 0] = 0
    gt = torch.where(frame.scored, frame.distance, torch.full_like(frame.distance, np.inf))
    k = max(1, W // width)
    near = -torch.nn.functional.max_pool2d(-gt[None, None], k, k)[0, 0]
    near = cv2.resize(near.numpy(), size, interpolation=cv2.INTER_NEAREST)
    near[~np.isfinite(near)] = 0
    tiles = panel(
        torch.from_numpy(image).permute(2, 0, 1),
        torch.from_numpy(small)[None],
        torch.from_numpy(near)[None],
        *frame.view,
    )
    return np.ascontiguousarray(tiles[..., ::-1])


# ------------------------------------------------------------------ models, names, the table, the record
def load_model(path: Path, post_process: str = "none"):
    """A runtime for ``path``: an exported ``.onnx`` file (:class:`OnnxRuntime`), else a checkpoint
    (:class:`TorchRuntime`, float32 on the CPU, at the checkpoint's input size)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such checkpoint or exported file")
    if path.suffix.lower() == ".onnx":
        return OnnxRuntime(path, post_process=post_process)
    if path.suffix.lower() in (".pt", ".ts"):
        raise ValueError(
            f"{path}: a TorchScript file has no runtime here; score its checkpoint or an ONNX export"
        )
    return TorchRuntime(TrainedDepthNet.from_checkpoint(path), post_process=post_process)


def model_names(paths: Sequence[Path]) -> list[str]:
    """A short unique name per model file: a run's folder for ``RUN/checkpoints/last.ckpt``
    (``RUN_best-000`` for another checkpoint of it), else the file's stem; on a repeat the file's
    suffix is added (``model_onnx``), then ``_2``, ``_3``."""
    names: list[str] = []
    for path in map(Path, paths):
        if path.parent.name == "checkpoints":
            name = path.parent.parent.name + ("" if path.stem == "last" else f"_{path.stem}")
        else:
            name = path.stem
        if name in names and path.suffix:
            name = f"{name}_{path.suffix.lstrip('.').lower()}"
        base, n = name, 1
        while name in names:
            n += 1
            name = f"{base}_{n}"
        names.append(name)
    return names


HEADER = (
    "| model | frame | scored pixels | cap | abs_rel, a1, rmse | median-scaled: abs_rel, a1, rmse (ratio) "
    "| constant map: abs_rel, a1, rmse (at) |"
)


def _cell(metrics: dict[str, Any]) -> str:
    return f"{metrics['abs_rel']:.3f}, {metrics['a1']:.3f}, {metrics['rmse']:.2f}"


def row(
    model: str, frame: RealFrame | Missing, results: dict | None = None, constant: dict | None = None
) -> str:
    """One line of the table: the frame's first protocol, unscaled, median-scaled and its constant map."""
    if isinstance(frame, Missing):
        return f"| {model} | {frame.name} | missing: {frame.path} | | | | |"
    r = results[frame.protocol.name]
    return (
        f"| {model} | {frame.name} | {constant['pixels']:,} | {frame.protocol.cap[1]:g} m "
        f"| {_cell(r['none'])} "
        f"| {_cell(r['median'])} (x{r['median']['scale_ratio']:.2f}) "
        f"| {_cell(constant['none'])} ({constant['distance']:.2f} m) |"
    )


def records_table(paths: Sequence[Path], sets: Sequence[str] = FRAME_SETS) -> list[str]:
    """The scores kept in run records (``docs/records``: files, or folders searched for ``*.json``) that
    hold a ``real_world`` entry, one row per record and frame of ``sets`` (its first protocol), nothing
    re-scored."""
    files: list[Path] = []
    for path in map(Path, paths):
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such run record or folder")
        files += [path] if path.is_file() else sorted(path.rglob("*.json"))
    lines = [
        "| run | frame | abs_rel, a1, rmse | median-scaled: abs_rel, a1, rmse (ratio) "
        "| constant map: abs_rel, a1, rmse (at) |",
        "|---|---|---|---|---|",
    ]
    for file in files:
        real = load_json(file.read_bytes(), file).get("real_world")
        if real is None:
            continue
        for frame, r in real["frames"].items():
            if "/" in frame or not frame.startswith(tuple(sets)):  # "/": a second protocol, the JSON only
                continue
            c = real["constant_map"][frame]
            lines.append(
                f"| {file.stem} | {frame} | {_cell(r['none'])} "
                f"| {_cell(r['median'])} (x{r['median']['scale_ratio']:.2f}) "
                f"| {_cell(c)} ({c['distance']:.2f} m) |"
            )
    if len(lines) == 2:
        raise ValueError(f"{', '.join(map(str, paths))}: no run record with real-world scores")
    return lines


def anchors_table() -> list[str]:
    """The published anchors as printed beside the scores (and in the README, "Real photographs")."""
    lines = ["| published, zero-shot on KITTI-360 fisheyes (80 m) | abs_rel | a1 |", "|---|---|---|"]
    for method, abs_rel, a1 in ANCHORS:
        lines.append(f"| {method} | {abs_rel:.3f} | {'-' if a1 is None else f'{a1:.3f}'} |")
    return lines


def _frame_record(frame: RealFrame | Missing, constant: dict | None) -> dict[str, Any]:
    if isinstance(frame, Missing):
        return {"missing": str(frame.path)}
    return {
        "files": [str(p) for p in frame.files],
        "camera": frame.camera.to_dict(),
        "protocols": [dataclasses.asdict(p) for p in frame.protocols],
        "constant_map": constant,
    }


def outputs(
    pictures: Path | None, json_out: Path | None, models: Sequence[str], frames, force: bool
) -> list[Path]:
    """The files a run writes; a FileExistsError before any work when one exists and not ``force``."""
    paths = [Path(json_out)] if json_out is not None else []
    if pictures is not None:
        paths += [
            Path(pictures) / f"{m}_{f.name}.png" for m in models for f in frames if isinstance(f, RealFrame)
        ]
    if not force:
        taken = [p for p in paths if p.exists()]
        if taken:
            raise FileExistsError(f"{taken[0]} exists; pass --force to replace it (or choose another path)")
    return paths


def score_models(
    model_paths: Sequence[Path],
    root: Path | None = None,
    sets: Sequence[str] = FRAME_SETS,
    pictures: Path | None = None,
    json_out: Path | None = None,
    force: bool = False,
    post_process: str = "none",
    echo=print,
    more=None,
) -> dict[str, Any]:
    """Every model on every frame of ``sets``: the table through ``echo`` line by line, pictures
    ``<model>_<frame>.png`` into ``pictures``, the record (returned) into ``json_out`` when given.
    ``more(record, predictions)``: further scores added to the record before it is written, given each
    model's predicted distance per frame (``{model: {frame: [H, W]}}``)."""
    root = default_root() if root is None else Path(root)
    for path in map(Path, model_paths):  # before the frames are read
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such checkpoint or exported file")
    frames = load_frames(root, sets)
    names = model_names(model_paths)
    outputs(pictures, json_out, names, frames, force)
    constants = {f.name: constant_map(f) for f in frames if isinstance(f, RealFrame)}
    present = sum(isinstance(f, RealFrame) for f in frames)
    echo(f"Real frames under {root}: {present} with ground truth, {len(frames) - present} missing")
    echo(HEADER)
    echo("|---|---|---|---|---|---|---|")
    record: dict[str, Any] = {
        "format": 1,
        "root": str(root),
        "written": time.strftime("%Y-%m-%d %H:%M:%S"),
        "post_process": post_process,
        "frames": {f.name: _frame_record(f, constants.get(f.name)) for f in frames},
        "models": {},
        "anchors": [{"method": m, "abs_rel": a, "a1": b} for m, a, b in ANCHORS],
    }
    predictions: dict[str, dict[str, Tensor]] = {}
    for path, name in zip(model_paths, names, strict=True):
        runtime = load_model(Path(path), post_process)
        entry = {"file": str(path), "model": runtime.describe(), "frames": {}}
        predictions[name] = {}
        for frame in frames:
            if isinstance(frame, Missing):
                entry["frames"][frame.name] = {"missing": str(frame.path)}
                echo(row(name, frame))
                continue
            results, pred = score(runtime, frame)
            predictions[name][frame.name] = pred
            entry["frames"][frame.name] = results
            echo(row(name, frame, results, constants[frame.name]))
            if pictures is not None:
                ok, encoded = cv2.imencode(".png", picture(frame, pred))
                if not ok:
                    raise OSError(f"{pictures}: could not encode the picture of {frame.name}")
                atomic_write_bytes(Path(pictures) / f"{name}_{frame.name}.png", encoded.tobytes())
        record["models"][name] = entry
    echo("")
    for line in anchors_table():
        echo(line)
    if more is not None:
        more(record, predictions)
    if json_out is not None:
        atomic_write_text(json_out, json.dumps(record, indent=1) + "\n")
    return record
