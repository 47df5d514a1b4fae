"""Multi-camera calibration files written by calibration tools: Kalibr's camchain and Basalt's JSON.

Each reader returns one :class:`CalibratedCamera` per camera of the file: its name, its
:class:`~fisheyedepth.cameras.base.CameraModel` and its 4x4 camera -> body transform (numpy float64).

**Kalibr** ``camchain.yaml`` / ``camchain-imucam.yaml`` (:func:`read_kalibr`): keys ``cam0``, ``cam1``, ...
with ``camera_model``, ``distortion_model``, ``intrinsics``, ``distortion_coeffs``, ``resolution``
``[width, height]`` and optionally ``T_cn_cnm1`` (previous camera -> this camera), ``T_cam_imu``
(IMU -> camera) and ``rostopic``. The supported combinations (:data:`KALIBR_MODELS`):

=====================  ==================================  ============================================
Kalibr                 intrinsics + distortion_coeffs      camera (fields)
=====================  ==================================  ============================================
pinhole + radtan       [fu fv pu pv] + [k1 k2 r1 r2]       ``opencv`` (fx fy cx cy k1 k2 p1 p2)
pinhole + equidistant  [fu fv pu pv] + [k1 k2 k3 k4]       ``kannala_brandt`` (fx fy cx cy k1..k4)
pinhole + fov          [fu fv pu pv] + [w]                 ``fov`` (fx fy cx cy w)
pinhole + none         [fu fv pu pv]                       ``pinhole`` (fx fy cx cy)
omni + radtan / none   [xi fu fv pu pv] (+ [k1 k2 r1 r2])  ``mei`` (xi gamma1 gamma2 u0 v0 k1 k2 p1 p2)
ds + none              [xi alpha fu fv pu pv]              ``double_sphere`` (xi alpha fx fy cx cy)
eucm + none            [alpha beta fu fv pu pv]            ``eucm`` (alpha beta fx fy cx cy)
=====================  ==================================  ============================================

The body frame is the IMU when ``cam0`` has ``T_cam_imu`` (``cam_to_body = inv(T_cam_imu)``; a later
camera without its own ``T_cam_imu`` is chained to the previous one by ``T_cn_cnm1``); otherwise it is
``cam0``, and ``T_cn_cnm1`` chains each camera to it: ``T_cn_c0 = T_cn_cnm1 @ T_cnm1_c0``.

**Basalt** calibration JSON (:func:`read_basalt`): ``{"value0": {"T_imu_cam": [{px, py, pz, qx, qy, qz,
qw}, ...], "intrinsics": [{"camera_type": ..., "intrinsics": {fx, fy, cx, cy, ...}}, ...],
"resolution": [[w, h], ...], ...}}``. ``camera_type`` ``kb4`` (k1..k4) -> ``kannala_brandt``, ``ds``
(xi, alpha) -> ``double_sphere``, ``eucm`` (alpha, beta) -> ``eucm``, ``ucm`` (alpha) -> ``ucm``,
``fov`` (w) -> ``fov``, ``pinhole-radtan8`` (k1 k2 p1 p2 k3 k4 k5 k6) -> ``opencv``, ``pinhole`` ->
``pinhole``: every Basalt parameter has the project's name. ``pinhole-radtan8``'s ``rpmax`` (the radius
where Basalt stops trusting the polynomial) is ignored. The body frame is the IMU (``cam_to_body =
T_imu_cam``, quaternion in x, y, z, w order); cameras are named ``cam0``, ``cam1``, ... by position.

:func:`read_calibration` reads either, by content. Every problem raises
:class:`~fisheyedepth.cameras.io.CalibrationError` naming the file, the camera and the field: an
unsupported model combination, a wrong number of intrinsics or coefficients, a missing resolution, a
transform that is not rigid, a parameter the camera model refuses, a calibration that cannot be a real
camera's (:func:`~fisheyedepth.cameras.base.check_plausible`), a file nested too deeply to parse.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from ..geometry.se3 import rigid_problem
from .base import CameraModel
from .io import CalibrationError, camera_from_mapping, load_json, load_yaml

log = logging.getLogger(__name__)

_FOCAL = ("fx", "fy", "cx", "cy")
# (camera_model, distortion_model) -> (our model, our fields for `intrinsics`, for `distortion_coeffs`)
KALIBR_MODELS: dict[tuple[str, str], tuple[str, tuple[str, ...], tuple[str, ...]]] = {
    ("pinhole", "radtan"): ("opencv", _FOCAL, ("k1", "k2", "p1", "p2")),
    ("pinhole", "equidistant"): ("kannala_brandt", _FOCAL, ("k1", "k2", "k3", "k4")),
    ("pinhole", "fov"): ("fov", _FOCAL, ("w",)),
    ("pinhole", "none"): ("pinhole", _FOCAL, ()),
    ("omni", "radtan"): ("mei", ("xi", "gamma1", "gamma2", "u0", "v0"), ("k1", "k2", "p1", "p2")),
    ("omni", "none"): ("mei", ("xi", "gamma1", "gamma2", "u0", "v0"), ()),
    ("ds", "none"): ("double_sphere", ("xi", "alpha", *_FOCAL), ()),
    ("eucm", "none"): ("eucm", ("alpha", "beta", *_FOCAL), ()),
}
# The names Kalibr's documentation gives the file's entries (for error messages).
_KALIBR_NAMES = {"gamma1": "fu", "gamma2": "fv", "u0": "pu", "v0": "pv", "fx": "fu", "fy": "fv", "cx": "pu",
                 "cy": "pv", "p1": "r1", "p2": "r2"}  # fmt: skip
# camera_type -> (our model, the parameters besides fx fy cx cy; Basalt's names are the project's)
BASALT_MODELS: dict[str, tuple[str, tuple[str, ...]]] = {
    "kb4": ("kannala_brandt", ("k1", "k2", "k3", "k4")),
    "ds": ("double_sphere", ("xi", "alpha")),
    "eucm": ("eucm", ("alpha", "beta")),
    "ucm": ("ucm", ("alpha",)),
    "fov": ("fov", ("w",)),
    "pinhole-radtan8": ("opencv", ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
    "pinhole": ("pinhole", ()),
}
_BASALT_IGNORED = {"pinhole-radtan8": {"rpmax"}}
# T_cam_imu and T_cn_cnm1 derived from one estimate agree to print precision; beyond this, warn.
_CHAIN_TOLERANCE_M, _CHAIN_TOLERANCE_RAD = 1e-3, 1e-3


@dataclasses.dataclass(frozen=True, eq=False)
class CalibratedCamera:
    """One camera of a multi-camera calibration file."""

    name: str  # Kalibr: the file's key (cam0, ...); Basalt: cam<i> by position
    camera: CameraModel  # at the calibration's resolution
    cam_to_body: np.ndarray  # 4x4 float64, camera -> body
    body: str  # the body frame: "imu", or "cam0" for a Kalibr camchain without T_cam_imu
    topic: str | None = None  # Kalibr's rostopic
    source: str = ""  # "FILE: cam1 (pinhole-radtan)", for messages


# ------------------------------------------------------------------------------------------- helpers
def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _numbers(value, count: int, path, key: str, what: str) -> list[float]:
    """``value`` as a list of ``count`` finite numbers, else an error naming ``key`` and ``what``."""
    if not isinstance(value, list | tuple) or len(value) != count:
        got = f"{len(value)}" if isinstance(value, list | tuple) else repr(value)
        raise CalibrationError(path, key, f"expected {count} numbers {what}, got {got}")
    for i, v in enumerate(value):
        if not _is_number(v):
            raise CalibrationError(path, f"{key}[{i}]", f"expected a finite number, got {v!r}")
    return [float(v) for v in value]


def _resolution(value, path, key: str) -> tuple[int, int]:
    if value is None:
        raise CalibrationError(path, key, "missing (expected [width, height] in pixels)")
    if not isinstance(value, list | tuple) or len(value) != 2:
        raise CalibrationError(path, key, f"expected [width, height] in pixels, got {value!r}")
    for axis, v in zip(("width", "height"), value, strict=True):
        if not _is_number(v) or not float(v).is_integer() or v <= 0:
            raise CalibrationError(
                path, key, f"the {axis} must be a positive whole number of pixels, got {v!r}"
            )
    return int(value[0]), int(value[1])


def _rigid(value, path, key: str) -> np.ndarray:
    """A 4x4 rigid transform (nested lists), checked (:func:`~fisheyedepth.geometry.rigid_problem`)."""
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = None
    if m is None or m.shape != (4, 4):
        raise CalibrationError(path, key, f"expected a 4x4 matrix, got {value!r}")
    out = np.eye(4)
    out[:3] = m[:3]
    return checked_rigid(out, path, key, last_row=m[3])


def checked_rigid(T: np.ndarray, path, key: str, last_row: np.ndarray | None = None) -> np.ndarray:
    """``T`` (4x4) if it is a rigid transform (:func:`~fisheyedepth.geometry.rigid_problem`), with the last
    row of the matrix it was read from (``last_row``, when one was given); otherwise
    :class:`CalibrationError` naming ``path`` and ``key``."""
    problem = rigid_problem(T if last_row is None else np.vstack([T[:3], last_row]))
    if problem is not None:
        raise CalibrationError(path, key, problem)
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def quaternion_xyzw_matrix(q) -> np.ndarray:
    """Rotation matrix of a unit quaternion given as (x, y, z, w)."""
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _camera(data: dict[str, Any], source_keys: dict[str, str], path, name: str) -> CameraModel:
    """``camera_from_mapping`` with errors naming the camera's key in the file."""
    try:
        return camera_from_mapping({**data, "_source_keys": source_keys}, path)
    except CalibrationError as err:
        raise CalibrationError(path, err.key or name, err.reason) from None


def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except OSError as exc:
        raise CalibrationError(path, None, f"cannot read calibration file ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise CalibrationError(path, None, f"not a text file (byte {exc.start} is not UTF-8)") from None


def _parse(path: Path) -> Any:
    """The file's tree: JSON when it starts with '{', else YAML (both safe, errors naming ``path``)."""
    text = _read_text(path)
    if text.lstrip().startswith("{"):
        return load_json(text, path)
    return load_yaml(text, path)


# ------------------------------------------------------------------------------------------- Kalibr
_CAM_KEY = re.compile(r"cam(\d+)")


def _kalibr_keys(tree) -> list[str]:
    if not isinstance(tree, dict):
        return []
    keys = [k for k in tree if isinstance(k, str) and _CAM_KEY.fullmatch(k)]
    return sorted(keys, key=lambda k: int(k[3:]))


def read_kalibr(path: str | os.PathLike) -> list[CalibratedCamera]:
    """The cameras of a Kalibr ``camchain.yaml`` or ``camchain-imucam.yaml`` (module docstring)."""
    path = Path(path)
    return _kalibr(_parse(path), path)


def _kalibr(tree, path: Path) -> list[CalibratedCamera]:
    keys = _kalibr_keys(tree)
    if not keys:
        raise CalibrationError(path, None, "not a Kalibr camchain: expected keys cam0, cam1, ...")
    gaps = [f"cam{i}" for i, key in enumerate(keys) if key != f"cam{i}"]
    if gaps:  # cam0, cam1, ... in order: T_cn_cnm1 chains each camera to the one before it
        raise CalibrationError(path, gaps[0], f"missing (the file has {', '.join(keys)})")
    entries = {}
    for name in keys:
        entry = tree[name]
        if not isinstance(entry, dict):
            raise CalibrationError(path, name, f"expected a mapping of camera fields, got {entry!r}")
        entries[name] = entry
    imu_body = "T_cam_imu" in entries["cam0"]
    cameras: list[CalibratedCamera] = []
    previous: np.ndarray | None = None  # the previous camera's cam_to_body
    for index, name in enumerate(keys):
        entry = entries[name]
        camera, combination = _kalibr_camera(entry, path, name)
        # ---- extrinsics
        chained = None
        if index > 0 and "T_cn_cnm1" in entry:  # T_body_cn = T_body_cnm1 @ inv(T_cn_cnm1)
            chained = previous @ inverse(_rigid(entry["T_cn_cnm1"], path, f"{name}.T_cn_cnm1"))
        if imu_body:
            if "T_cam_imu" in entry:
                cam_to_body = inverse(_rigid(entry["T_cam_imu"], path, f"{name}.T_cam_imu"))
                if chained is not None:
                    _check_chain(cam_to_body, chained, path, name)
            elif chained is not None:
                cam_to_body = chained
            else:
                raise CalibrationError(
                    path, f"{name}.T_cam_imu", "missing (and no T_cn_cnm1 to chain it to the previous camera)"
                )
        elif index == 0:
            cam_to_body = np.eye(4)
        else:
            if "T_cam_imu" in entry:
                raise CalibrationError(
                    path,
                    f"{name}.T_cam_imu",
                    "cam0 has no T_cam_imu: give every camera's T_cam_imu, or none (the body is then cam0)",
                )
            if chained is None:
                raise CalibrationError(
                    path, f"{name}.T_cn_cnm1", "missing (needed to place this camera relative to cam0)"
                )
            cam_to_body = chained
        previous = cam_to_body
        topic = entry.get("rostopic")
        cameras.append(
            CalibratedCamera(
                name=name,
                camera=camera,
                cam_to_body=cam_to_body,
                body="imu" if imu_body else "cam0",
                topic=None if topic is None else str(topic),
                source=f"{path}: {name} ({combination})",
            )
        )
    return cameras


def _kalibr_camera(entry: dict, path: Path, name: str) -> tuple[CameraModel, str]:
    for key in ("camera_model", "distortion_model"):
        if key not in entry:
            raise CalibrationError(path, f"{name}.{key}", "missing")
    camera_model, distortion = str(entry["camera_model"]).lower(), str(entry["distortion_model"]).lower()
    combination = f"{camera_model}-{distortion}"
    if (camera_model, distortion) not in KALIBR_MODELS:
        supported = ", ".join(f"{c}-{d}" for c, d in KALIBR_MODELS)
        raise CalibrationError(
            path,
            name,
            f"camera_model {camera_model!r} with distortion_model {distortion!r} ({combination}) is not "
            f"supported; supported: {supported}",
        )
    model, intrinsic_fields, coefficient_fields = KALIBR_MODELS[(camera_model, distortion)]
    if "intrinsics" not in entry:
        raise CalibrationError(path, f"{name}.intrinsics", "missing")
    names = "[" + " ".join(_KALIBR_NAMES.get(f, f) for f in intrinsic_fields) + "]"
    intrinsics = _numbers(
        entry["intrinsics"], len(intrinsic_fields), path, f"{name}.intrinsics", f"{names} for {combination}"
    )
    coefficients = entry.get("distortion_coeffs")
    if coefficients is None and not coefficient_fields:
        coefficients = []
    if coefficients is None:
        raise CalibrationError(path, f"{name}.distortion_coeffs", "missing")
    names = "[" + " ".join(_KALIBR_NAMES.get(f, f) for f in coefficient_fields) + "]"
    coefficients = _numbers(
        coefficients, len(coefficient_fields), path, f"{name}.distortion_coeffs", f"{names} for {combination}"
    )
    width, height = _resolution(entry.get("resolution"), path, f"{name}.resolution")
    data: dict[str, Any] = {"model": model, "width": width, "height": height}
    data.update(zip(intrinsic_fields, intrinsics, strict=True))
    data.update(zip(coefficient_fields, coefficients, strict=True))
    keys = {f: f"{name}.intrinsics[{i}] ({_KALIBR_NAMES.get(f, f)})" for i, f in enumerate(intrinsic_fields)}
    keys.update(
        {
            f: f"{name}.distortion_coeffs[{i}] ({_KALIBR_NAMES.get(f, f)})"
            for i, f in enumerate(coefficient_fields)
        }
    )
    keys.update(width=f"{name}.resolution", height=f"{name}.resolution")
    return _camera(data, keys, path, name), combination


def _check_chain(direct: np.ndarray, chained: np.ndarray, path: Path, name: str) -> None:
    """Warn when ``T_cam_imu`` and the ``T_cn_cnm1`` chain place a camera differently."""
    delta = inverse(direct) @ chained
    shift = float(np.linalg.norm(delta[:3, 3]))
    angle = math.acos(max(-1.0, min(1.0, (float(np.trace(delta[:3, :3])) - 1) / 2)))
    if shift > _CHAIN_TOLERANCE_M or angle > _CHAIN_TOLERANCE_RAD:
        log.warning(
            "%s: %s: T_cam_imu and the T_cn_cnm1 chain disagree by %.4f m and %.3f degrees; using T_cam_imu",
            path, name, shift, math.degrees(angle),
        )  # fmt: skip


# ------------------------------------------------------------------------------------------- Basalt
def read_basalt(path: str | os.PathLike) -> list[CalibratedCamera]:
    """The cameras of a Basalt calibration JSON (module docstring)."""
    path = Path(path)
    return _basalt(_parse(path), path)


def _basalt(tree, path: Path) -> list[CalibratedCamera]:
    prefix = "value0."
    if isinstance(tree, dict) and "value0" in tree:
        tree = tree["value0"]
    else:
        prefix = ""
    if not isinstance(tree, dict) or "intrinsics" not in tree:
        raise CalibrationError(path, f"{prefix}intrinsics", "missing: not a Basalt calibration")
    intrinsics, transforms = tree["intrinsics"], tree.get("T_imu_cam")
    resolutions = tree.get("resolution")
    if not isinstance(intrinsics, list) or not intrinsics:
        raise CalibrationError(path, f"{prefix}intrinsics", "expected a non-empty list of cameras")
    for key, value in (("T_imu_cam", transforms), ("resolution", resolutions)):
        if value is None:
            raise CalibrationError(path, prefix + key, f"missing (one per camera, {len(intrinsics)} cameras)")
        if not isinstance(value, list) or len(value) != len(intrinsics):
            count = len(value) if isinstance(value, list) else repr(value)
            raise CalibrationError(
                path, prefix + key, f"expected one entry per camera ({len(intrinsics)}), got {count}"
            )
    cameras = []
    for i, (entry, pose, size) in enumerate(zip(intrinsics, transforms, resolutions, strict=True)):
        name, where = f"cam{i}", f"{prefix}intrinsics[{i}]"
        if not isinstance(entry, dict) or "camera_type" not in entry:
            raise CalibrationError(path, f"{where}.camera_type", f"missing (camera {name})")
        camera_type = str(entry["camera_type"])
        if camera_type not in BASALT_MODELS:
            raise CalibrationError(
                path,
                f"{where}.camera_type",
                f"camera {name}: camera_type {camera_type!r} is not supported; supported: "
                f"{', '.join(BASALT_MODELS)}",
            )
        model, extra = BASALT_MODELS[camera_type]
        params = entry.get("intrinsics")
        if not isinstance(params, dict):
            raise CalibrationError(
                path, f"{where}.intrinsics", f"camera {name}: expected a mapping, got {params!r}"
            )
        fields = (*_FOCAL, *extra)
        for f in fields:
            if f not in params:
                raise CalibrationError(
                    path,
                    f"{where}.intrinsics.{f}",
                    f"missing (camera {name}, {camera_type}: {' '.join(fields)})",
                )
            if not _is_number(params[f]):
                raise CalibrationError(
                    path,
                    f"{where}.intrinsics.{f}",
                    f"camera {name}: expected a finite number, got {params[f]!r}",
                )
        unknown = sorted(set(params) - set(fields) - _BASALT_IGNORED.get(camera_type, set()))
        if unknown:
            raise CalibrationError(
                path,
                f"{where}.intrinsics.{unknown[0]}",
                f"camera {name}: not a parameter of camera_type {camera_type} ({' '.join(fields)})",
            )
        width, height = _resolution(size, path, f"{prefix}resolution[{i}]")
        data = {"model": model, "width": width, "height": height, **{f: float(params[f]) for f in fields}}
        keys = {f: f"{where}.intrinsics.{f}" for f in fields}
        keys.update(width=f"{prefix}resolution[{i}]", height=f"{prefix}resolution[{i}]")
        camera = _camera(data, keys, path, where)
        cameras.append(
            CalibratedCamera(
                name=name,
                camera=camera,
                cam_to_body=_basalt_pose(pose, path, f"{prefix}T_imu_cam[{i}]"),
                body="imu",
                source=f"{path}: {name} ({camera_type})",
            )
        )
    return cameras


def _basalt_pose(pose, path: Path, key: str) -> np.ndarray:
    """``T_imu_cam`` from ``{px, py, pz, qx, qy, qz, qw}``."""
    if not isinstance(pose, dict):
        raise CalibrationError(path, key, f"expected {{px, py, pz, qx, qy, qz, qw}}, got {pose!r}")
    values = []
    for f in ("px", "py", "pz", "qx", "qy", "qz", "qw"):
        if f not in pose:
            raise CalibrationError(path, f"{key}.{f}", "missing")
        if not _is_number(pose[f]):
            raise CalibrationError(path, f"{key}.{f}", f"expected a finite number, got {pose[f]!r}")
        values.append(float(pose[f]))
    q = np.array(values[3:])
    norm = float(np.linalg.norm(q))
    if abs(norm - 1) > 1e-3:
        raise CalibrationError(
            path,
            key,
            f"(qx, qy, qz, qw) = {tuple(values[3:])} is not a unit quaternion (norm {norm:.6g})",
        )
    T = np.eye(4)
    T[:3, :3] = quaternion_xyzw_matrix(q / norm)
    T[:3, 3] = values[:3]
    return T


# ------------------------------------------------------------------------------------------- either
def read_calibration(path: str | os.PathLike) -> list[CalibratedCamera]:
    """The cameras of a Kalibr camchain or a Basalt calibration JSON, told apart by their content."""
    path = Path(path)
    tree = _parse(path)
    if isinstance(tree, dict) and ("value0" in tree or "T_imu_cam" in tree):
        return _basalt(tree, path)
    if _kalibr_keys(tree):
        return _kalibr(tree, path)
    raise CalibrationError(
        path,
        None,
        "neither a Kalibr camchain (keys cam0, cam1, ... with camera_model) nor a Basalt calibration JSON "
        "(value0 with T_imu_cam, intrinsics, resolution); a single camera's calibration goes in a camera's "
        "own 'calibration: FILE'",
    )


def find_camera(cameras: list[CalibratedCamera], key: str, path) -> CalibratedCamera:
    """The camera named ``key`` (``cam1``), or whose Kalibr ``rostopic`` is ``key`` (a leading '/' or
    not); a :class:`CalibrationError` naming ``path`` and the cameras it has otherwise."""
    key = str(key)
    for camera in cameras:
        if camera.name == key:
            return camera
    for camera in cameras:
        if camera.topic is not None and camera.topic.lstrip("/") == key.lstrip("/"):
            return camera
    have = [c.name + (f" ({c.topic})" if c.topic else "") for c in cameras]
    raise CalibrationError(path, None, f"no camera named {key!r}; the file has {', '.join(have)}")
