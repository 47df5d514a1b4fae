"""Reading and writing camera calibration files.

Two formats are read by :func:`load_camera`:

1. OpenCV YAML as written by KITTI-360 and CamOdoCal (first line ``%YAML:1.0``), with
   ``model_type`` one of ``MEI`` (KITTI-360's ``image_02.yaml`` / ``image_03.yaml``),
   ``KANNALA_BRANDT`` (CamOdoCal: ``projection_parameters`` k2..k5, mu, mv, u0, v0) or ``PINHOLE``
   (``projection_parameters`` fx, fy, cx, cy; only without distortion).
   For ``MEI`` the tangential coefficients p1/p2 are **ignored by default**, exactly like KITTI-360's
   official projection and LiDAR tools; ``keep_tangential=True`` keeps them (OpenCV's omnidir model,
   up to ~1.2 px different at 1400 px).
2. The project's own YAML: the flat mapping of :meth:`CameraModel.to_dict`, e.g.
   ``{model: mei, width: 1400, height: 1400, xi: 2.21, k1: ..., gamma1: ..., u0: ...}``.

Every problem raises :class:`CalibrationError` naming the file and the key.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

import yaml

from ..files import atomic_write_text
from .base import CameraModel, CameraParameterError


class CalibrationError(ValueError):
    """A calibration file is missing, malformed, or holds an impossible value."""

    def __init__(self, path: str | os.PathLike, key: str | None, reason: str):
        where = f"{path}" if key is None else f"{path}: key '{key}'"
        super().__init__(f"{where}: {reason}")
        self.path = str(path)
        self.key = key
        self.reason = reason


class _SafeOpenCVLoader(yaml.SafeLoader):
    """Safe loader that also accepts OpenCV's ``!!opencv-matrix`` tag (read as a plain mapping)."""


_SafeOpenCVLoader.add_constructor(
    "tag:yaml.org,2002:opencv-matrix", lambda loader, node: loader.construct_mapping(node, deep=True)
)
# YAML 1.1 reads ``1e-3`` (no dot) as a string; OpenCV, YAML 1.2 and every calibration tool read a
# number. Resolve such scalars as floats too.
_SafeOpenCVLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)

# Both parsers recurse once per level of nesting (PyYAML through several Python calls), so a file nested
# deeper than the interpreter's recursion limit allows raises RecursionError. No calibration nests more
# than 5 levels.
_TOO_DEEP = "nested too deeply to be a calibration (lists or mappings hundreds of levels deep)"


def load_yaml(text: str, path) -> Any:
    """Parse a user's YAML safely (no Python tags), with OpenCV's conventions; every reader of a calibration
    or rig file parses through it. Errors name ``path``: not YAML, or nested too deeply to parse."""
    try:
        return yaml.load(text, Loader=_SafeOpenCVLoader)
    except yaml.YAMLError as exc:
        raise CalibrationError(path, None, f"not valid YAML: {exc}") from None
    except RecursionError:
        raise CalibrationError(path, None, _TOO_DEEP) from None


def load_json(text: str | bytes, path) -> Any:
    """Parse a user's JSON (``bytes`` are decoded as JSON's UTF-8, -16 or -32); every reader of a user's JSON
    parses through it. Errors name ``path``: not JSON (or not text), or nested too deeply to parse."""
    try:
        return json.loads(text)
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError
        raise CalibrationError(path, None, f"not valid JSON: {exc}") from None
    except RecursionError:
        raise CalibrationError(path, None, _TOO_DEEP) from None


def field(tree: dict, dotted: str, path) -> Any:
    """``tree[a][b]...`` for ``dotted`` "a.b..."; a :class:`CalibrationError` naming ``path`` and the key when
    a level is missing."""
    node: Any = tree
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            raise CalibrationError(path, dotted, "missing")
        node = node[part]
    return node


# The OpenCV YAML layouts, for reading and writing alike: model_type -> (our model name, our parameter
# -> the file's dotted key, in the file's order). MEI's p1/p2 are read only with keep_tangential.
OPENCV_LAYOUTS: dict[str, tuple[str, dict[str, str]]] = {
    "MEI": (
        "mei",
        {
            "xi": "mirror_parameters.xi",
            "k1": "distortion_parameters.k1",
            "k2": "distortion_parameters.k2",
            "p1": "distortion_parameters.p1",
            "p2": "distortion_parameters.p2",
            "gamma1": "projection_parameters.gamma1",
            "gamma2": "projection_parameters.gamma2",
            "u0": "projection_parameters.u0",
            "v0": "projection_parameters.v0",
        },
    ),
    "KANNALA_BRANDT": (
        "kannala_brandt",
        {
            "k1": "projection_parameters.k2",
            "k2": "projection_parameters.k3",
            "k3": "projection_parameters.k4",
            "k4": "projection_parameters.k5",
            "fx": "projection_parameters.mu",
            "fy": "projection_parameters.mv",
            "cx": "projection_parameters.u0",
            "cy": "projection_parameters.v0",
        },
    ),
    "PINHOLE": ("pinhole", {name: f"projection_parameters.{name}" for name in ("fx", "fy", "cx", "cy")}),
}
TANGENTIAL = ("p1", "p2")


def _opencv_to_dict(tree: dict, path, keep_tangential: bool) -> dict[str, Any]:
    model_type = str(field(tree, "model_type", path)).strip().upper()
    size = {"width": field(tree, "image_width", path), "height": field(tree, "image_height", path)}
    if model_type not in OPENCV_LAYOUTS:
        raise CalibrationError(
            path, "model_type", f"unknown model_type {model_type!r}; expected MEI, KANNALA_BRANDT or PINHOLE"
        )
    model, layout = OPENCV_LAYOUTS[model_type]
    keys = {ours: theirs for ours, theirs in layout.items() if keep_tangential or ours not in TANGENTIAL}
    if model_type == "PINHOLE":
        for name, value in (tree.get("distortion_parameters") or {}).items():
            if value not in (0, 0.0):
                raise CalibrationError(
                    path, f"distortion_parameters.{name}", "pinhole distortion is not supported"
                )
    out: dict[str, Any] = {"model": model, **size}
    out.update({ours: field(tree, theirs, path) for ours, theirs in keys.items()})
    out["_source_keys"] = {**keys, "width": "image_width", "height": "image_height"}
    return out


def opencv_yaml(camera: CameraModel, name: str) -> str:
    """``camera`` in KITTI-360's (CamOdoCal's) OpenCV YAML layout, the one :func:`load_camera` reads."""
    layouts = {model: (model_type, keys) for model_type, (model, keys) in OPENCV_LAYOUTS.items()}
    if camera.model_name not in layouts:
        raise TypeError(f"no OpenCV YAML layout for {type(camera).__name__}")
    model_type, keys = layouts[camera.model_name]
    lines = [
        "%YAML:1.0",
        "---",
        f"model_type: {model_type}",
        f"camera_name: {name}",
        f"image_width: {camera.width}",
        f"image_height: {camera.height}",
    ]
    section = None
    for ours, theirs in keys.items():
        group, key = theirs.split(".")
        if group != section:
            lines.append(f"{group}:")
            section = group
        lines.append(f"   {key}: {getattr(camera, ours)!r}")
    return "\n".join(lines) + "\n"


def camera_from_mapping(data: dict[str, Any], path="<mapping>") -> CameraModel:
    """Build a camera from the project's YAML mapping, with errors naming ``path`` and the key: a missing or
    impossible parameter, or a calibration that cannot be a real camera's
    (:func:`~fisheyedepth.cameras.base.check_plausible`, through :meth:`CameraModel.from_dict`)."""
    data = dict(data)
    source_keys = data.pop("_source_keys", {})
    try:
        camera = CameraModel.from_dict(data)
    except CameraParameterError as exc:
        raise CalibrationError(path, source_keys.get(exc.key, exc.key), exc.reason) from None
    except TypeError as exc:  # a value of the wrong kind reached a constructor
        raise CalibrationError(path, None, str(exc)) from None
    return camera


def load_camera(path: str | os.PathLike, keep_tangential: bool = False) -> CameraModel:
    """Read a camera from a KITTI-360/CamOdoCal OpenCV YAML file or the project's own YAML file.

    ``keep_tangential`` applies to OpenCV ``MEI`` files only (see the module docstring).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise CalibrationError(path, None, f"cannot read calibration file ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise CalibrationError(
            path, None, f"not a text file (byte {exc.start} is not UTF-8): not a calibration YAML"
        ) from None
    opencv = text.lstrip().startswith("%YAML")
    if opencv:  # PyYAML rejects OpenCV's '%YAML:1.0' directive; drop it
        text = text.split("\n", 1)[1] if "\n" in text else ""
    tree = load_yaml(text, path)
    if not isinstance(tree, dict):
        raise CalibrationError(path, None, "expected a mapping of calibration keys")
    data = _opencv_to_dict(tree, path, keep_tangential) if opencv else dict(tree)
    return camera_from_mapping(data, path)


def save_camera(camera: CameraModel, path: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write ``camera`` as the project's YAML, atomically; refuses to replace a file unless ``overwrite``."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    atomic_write_text(path, yaml.safe_dump(camera.to_dict(), sort_keys=False))
    return path
