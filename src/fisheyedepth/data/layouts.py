"""Where frames, poses, cameras and masks live on disk: what every layout answers, and the robot-rig layout.

A layout answers a few questions for the dataset, which builds every sample the same way for both:
which cameras exist (model, camera-to-body extrinsic, optional body mask), which frames a sequence has
in time order (with body-to-world poses), and where each frame's image (and ground truth) lies.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import re
from pathlib import Path

import numpy as np
import torch
import yaml

from ..cameras import CalibrationError, CameraModel, camera_from_mapping, load_camera, load_yaml
from ..cameras.calibration_files import CalibratedCamera, checked_rigid, find_camera, read_calibration
from ..files import path_name
from ..geometry import make_pose, pose_from_3x4, quaternion_to_matrix
from ..geometry.se3 import rig_extent_problem
from .files import binary_mask, read_checked, read_distance

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class CameraSpec:
    name: str
    camera: CameraModel  # at the native image size
    cam_to_body: np.ndarray  # 4x4
    mask: Path | None = None  # body mask image (255 / nonzero = usable), native size


@dataclasses.dataclass(frozen=True)
class Frame:
    key: int  # frame index (KITTI-360) or timestamp in ns (rig)
    pose: np.ndarray  # 4x4 body to world


class RecordingFiles:
    """What every layout reads of its recording, each file checked once and refused by name
    (:mod:`.files`): a layout has ``cameras`` (name -> :class:`CameraSpec`) and says where each file lies
    (``image``, ``distance``); the dataset, the stereo command, refinement and the tools all read through
    these."""

    cameras: dict[str, CameraSpec]

    def read_image(self, sequence: str, camera: str, frame: Frame) -> np.ndarray:
        """The image of ``camera`` at ``frame`` as 8-bit BGR ``H x W x 3``, refused by name unless it is
        at the camera's calibrated size (:func:`~.files.read_checked`)."""
        native = self.cameras[camera].camera
        return read_checked(self.image(sequence, camera, frame), (native.width, native.height))

    def read_distance(self, sequence: str, camera: str, frame: Frame) -> np.ndarray | None:
        """The frame's ground-truth distance ``H x W`` float32 metres (0: none), checked
        (:func:`~.files.read_distance`); None where the recording has none."""
        path = self.distance(sequence, camera, frame)
        return None if path is None else read_distance(path, self.cameras[camera].camera)

    def read_mask(self, camera: str) -> np.ndarray | None:
        """``camera``'s body mask as ``H x W`` bool (True: the scene), refused by name unless it is at the
        camera's calibrated size; None where the rig names none. Decoded once."""
        spec = self.cameras[camera]
        if spec.mask is None:
            return None
        decoded = self.__dict__.setdefault("_decoded_masks", {})  # by camera, for the layout's life
        if camera not in decoded:
            size = (spec.camera.width, spec.camera.height)
            decoded[camera] = binary_mask(spec.mask, size, size, "body mask")[0].numpy() > 0.5
        return decoded[camera]


class RigLayout(RecordingFiles):
    """A robot's own recording (docs/data-format.md, "Robot rig layout").

    ``root/rig.yaml`` lists the cameras; ``root/<sequence>/images/<camera>/<timestamp_ns>.png`` hold the
    images and ``root/<sequence>/poses.txt`` the body poses as ``timestamp_ns tx ty tz qx qy qz qw``.
    Poses are interpolated to each image's timestamp (linear translation, slerp rotation); images outside
    the pose time range are reported and left out, never extrapolated, and so are images in a gap of the
    poses longer than ``max_pose_gap`` seconds (default: ``rig.yaml``'s ``max_pose_gap``, else
    ``GAP_FACTOR`` times the sequence's median pose interval), never interpolated across it.

    A top-level ``calibration: FILE`` (a Kalibr camchain or a Basalt calibration JSON,
    :mod:`fisheyedepth.cameras.calibration_files`) gives the model and ``cam_to_body`` of every camera
    entry that names neither: the file's camera ``calibration_camera`` (its name, ``cam1``, or its Kalibr
    rostopic; default: the entry's name), composed with ``calibration_to_body`` (default identity).
    Without ``cameras``, every camera of the file is used under its name there.
    """

    name = "rig"

    def __init__(
        self,
        root: str | os.PathLike,
        cameras: list[str] | None = None,
        masks: dict[str, str | os.PathLike] | None = None,
        expect_masks: bool = True,
        max_pose_gap: float | None = None,
    ):
        """``expect_masks``: a mask that ``rig.yaml`` (or ``masks``) names must exist; off for the
        command that is about to write it. ``mask_paths``: each camera's named mask, existing or not
        (None: the camera has none). ``max_pose_gap``: seconds (class docstring); the images it leaves out
        are listed in ``in_gaps``, as those outside the poses are in ``outside``."""
        self.root = Path(root)
        self.topics: dict[str, str] = {}  # camera -> the ROS image topic it was imported from
        self.frame_ids: dict[str, str] = {}  # camera -> its ROS frame id
        rig_file = existing(self.root / "rig.yaml", "rig description")
        try:
            text = rig_file.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            raise CalibrationError(rig_file, None, "not a text file (not UTF-8)") from None
        rig = load_yaml(text, rig_file)  # safe, and reads 1e-3 as a number like OpenCV does
        entries = rig.get("cameras") if isinstance(rig, dict) else None
        if max_pose_gap is None and isinstance(rig, dict):
            max_pose_gap = rig.get("max_pose_gap")
        if max_pose_gap is not None and not _positive_seconds(max_pose_gap):
            raise CalibrationError(rig_file, "max_pose_gap", f"expected seconds > 0, got {max_pose_gap!r}")
        self.max_pose_gap = max_pose_gap
        calibrated, calibration_to_body = self._calibration_file(rig, rig_file)
        if entries is None and calibrated:  # every camera of the calibration file, by its name there
            entries = [
                {"name": path_name(c.name, "camera", self.root / rig["calibration"])} for c in calibrated
            ]
        if not isinstance(entries, list) or not entries:
            raise CalibrationError(rig_file, "cameras", "expected a non-empty list of cameras")
        self.cameras = {}
        self.mask_paths: dict[str, Path | None] = {}
        named: dict[str, int] = {}
        for i, entry in enumerate(entries):
            where = f"cameras[{i}]"
            if not isinstance(entry, dict) or "name" not in entry:
                raise CalibrationError(rig_file, f"{where}.name", "missing")
            name = path_name(str(entry["name"]), f"{where}.name", rig_file)  # images/<name>/ under root
            if name in named:  # one folder of images, two calibrations: neither may win silently
                raise CalibrationError(rig_file, f"{where}.name", f"{name!r} is also cameras[{named[name]}]")
            named[name] = i
            if cameras is not None and name not in cameras:
                continue
            calibrated_as = None  # the camera of the top-level calibration file this entry takes
            if "calibration_camera" in entry and ("calibration" in entry or "model" in entry):
                raise CalibrationError(
                    rig_file,
                    f"{where}.calibration_camera",
                    "give either it or the camera's model/calibration",
                )
            if "calibration" in entry:
                camera = load_camera(self.root / entry["calibration"])
            elif "model" in entry:
                camera = camera_from_mapping(dict(entry["model"]), f"{rig_file} ({where}.model)")
            elif calibrated is not None:
                try:
                    calibrated_as = find_camera(
                        calibrated, entry.get("calibration_camera", name), self.root / rig["calibration"]
                    )
                except CalibrationError as err:  # named by rig.yaml's entry and by the calibration file
                    raise CalibrationError(rig_file, f"{where}.calibration_camera", str(err)) from None
                camera = calibrated_as.camera
            elif "calibration_camera" in entry:
                raise CalibrationError(
                    rig_file,
                    f"{where}.calibration_camera",
                    "given, but rig.yaml has no top-level 'calibration'",
                )
            else:
                raise CalibrationError(
                    rig_file,
                    f"{where}.model",
                    "missing (or give 'calibration: FILE', or a top-level 'calibration: CAMCHAIN')",
                )
            if "cam_to_body" in entry:
                extrinsic = read_transform(entry["cam_to_body"], rig_file, f"{where}.cam_to_body")
            elif calibrated_as is not None:
                extrinsic = calibration_to_body @ calibrated_as.cam_to_body
            else:
                raise CalibrationError(rig_file, f"{where}.cam_to_body", "missing")
            mask = masks.get(name) if masks else entry.get("mask")
            self.mask_paths[name] = mask = None if mask is None else self.root / mask
            if mask is not None and (expect_masks or mask.is_file()):
                existing(mask, "body mask")
            else:
                mask = None
            self.cameras[name] = CameraSpec(name, camera, extrinsic, mask)
            self._ros_names(entry.get("ros"), name, rig_file, f"{where}.ros")
        if cameras is not None and set(cameras) - set(self.cameras):
            raise CalibrationError(
                rig_file, "cameras", f"no camera named {sorted(set(cameras) - set(self.cameras))}"
            )
        spread = rig_extent_problem({n: c.cam_to_body for n, c in self.cameras.items()})
        if spread is not None:
            raise CalibrationError(rig_file, "cameras[].cam_to_body", spread)
        self._frames: dict[tuple[str, str], list[Frame]] = {}
        self.outside: dict[tuple[str, str], list[int]] = {}
        self.in_gaps: dict[tuple[str, str], list[int]] = {}
        self.not_understood: dict[tuple[str, str], list[str]] = {}  # file names that are no timestamp
        self._order_checked: set[Path] = set()

    def _ros_names(self, ros, camera: str, rig_file: Path, where: str) -> None:
        """A camera entry's ``ros: {image_topic: /front/image_raw, frame_id: front}`` (what
        ``fisheyedepth-import-rosbag`` writes): the names a ROS bag of its outputs follows."""
        if ros is None:
            return
        if not isinstance(ros, dict) or set(ros) - {"image_topic", "frame_id"}:
            raise CalibrationError(
                rig_file, where, f"expected {{image_topic: TOPIC, frame_id: FRAME}}, got {ros!r}"
            )
        for key, names in (("image_topic", self.topics), ("frame_id", self.frame_ids)):
            if key in ros:
                if (
                    not isinstance(ros[key], str)
                    or not ros[key].strip("/")
                    or any(c.isspace() for c in ros[key])
                ):
                    raise CalibrationError(
                        rig_file, f"{where}.{key}", f"expected a ROS name, got {ros[key]!r}"
                    )
                names[camera] = ros[key]

    def _calibration_file(self, rig, rig_file: Path) -> tuple[list[CalibratedCamera] | None, np.ndarray]:
        """The cameras of ``rig.yaml``'s top-level ``calibration`` (a Kalibr camchain or a Basalt
        calibration JSON, relative to the root), and ``calibration_to_body``: the file's body frame (its
        IMU, or Kalibr's cam0 without one) -> the rig's body frame (identity unless given)."""
        if not isinstance(rig, dict) or "calibration" not in rig:
            if isinstance(rig, dict) and "calibration_to_body" in rig:
                raise CalibrationError(
                    rig_file, "calibration_to_body", "given without a top-level 'calibration'"
                )
            return None, np.eye(4)
        if not isinstance(rig["calibration"], str):
            raise CalibrationError(
                rig_file, "calibration", f"expected a file path, got {rig['calibration']!r}"
            )
        cameras = read_calibration(existing(self.root / rig["calibration"], "calibration file"))
        to_body = np.eye(4)
        if "calibration_to_body" in rig:
            to_body = read_transform(rig["calibration_to_body"], rig_file, "calibration_to_body")
        return cameras, to_body

    def sequences(self) -> list[str]:
        return sorted(p.name for p in self.root.iterdir() if (p / "poses.txt").is_file())

    def _poses(self, sequence: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        path = existing(self.root / sequence / "poses.txt", "pose file")
        stamps, rows = [], []
        lines: dict[int, int] = {}
        for lineno, line in enumerate(path.read_text().splitlines(), start=1):
            fields = line.split()
            if not fields or fields[0].startswith("#"):
                continue
            try:
                stamp, values = _timestamp(fields[0]), [float(x) for x in fields[1:]]
            except ValueError:
                raise ValueError(f"{path}:{lineno}: expected 'timestamp_ns tx ty tz qx qy qz qw'") from None
            if len(values) != 7:
                raise ValueError(f"{path}:{lineno}: expected 8 finite numbers, got {len(values) + 1}")
            pose_row(f"{path}:{lineno}", values, stamp, str(stamp), lines, lineno)
            stamps.append(stamp)
            rows.append(values)
        if len(rows) < 2:
            raise ValueError(f"{path}: needs at least two poses to interpolate")
        order = np.argsort(np.array(stamps, dtype=np.int64), kind="stable")
        times, a = np.array(stamps, dtype=np.int64)[order], np.array(rows)[order]
        q = a[:, 3:7] / np.linalg.norm(a[:, 3:7], axis=1, keepdims=True)
        if path not in self._order_checked:  # once per file, not once per camera
            self._order_checked.add(path)
            hint = quaternion_order_hint(a[:, :3], q)
            if hint:
                log.warning("%s: %s: quaternions in w,x,y,z order? The file's order is x,y,z,w", path, hint)
        return times, a[:, :3], q

    def frames(self, sequence: str, camera: str) -> list[Frame]:
        key = (sequence, camera)
        if key not in self._frames:
            path_name(sequence, "sequence", self.root)  # from a split or an option: a folder under root
            path_name(camera, "camera", self.root)
            times, trans, quats = self._poses(sequence)
            folder = self.root / sequence / "images" / camera
            stamps, self.not_understood[key] = image_stamps(folder)
            if self.not_understood[key]:
                log.warning(
                    "%s: %d files are not named <timestamp_ns>.png and are left out: %s",
                    folder,
                    len(self.not_understood[key]),
                    ", ".join(self.not_understood[key][:5]),
                )
            if not stamps:
                raise FileNotFoundError(f"{folder}: no images named <timestamp_ns>.png")
            inside = [t for t in stamps if times[0] <= t <= times[-1]]
            self.outside[key] = [t for t in stamps if not times[0] <= t <= times[-1]]
            if self.outside[key]:
                log.warning(
                    "%s: %d images of %s lie outside the pose time range and are left out",
                    self.root / sequence,
                    len(self.outside[key]),
                    camera,
                )
            bound = max_gap_ns(times, self.max_pose_gap)
            gapped = in_pose_gap(times, inside, bound)
            self.in_gaps[key] = [t for t, g in zip(inside, gapped, strict=True) if g]
            if self.in_gaps[key]:
                log.warning(
                    "%s: %d images of %s lie in gaps of the poses longer than %.3f s (max_pose_gap) and are "
                    "left out; the longest gap is %.3f s",
                    self.root / sequence,
                    len(self.in_gaps[key]),
                    camera,
                    bound * 1e-9,
                    np.diff(times).max() * 1e-9,
                )
                inside = [t for t, g in zip(inside, gapped, strict=True) if not g]
            self._frames[key] = [Frame(t, interpolate_pose(times, trans, quats, t)) for t in inside]
        return self._frames[key]

    def image(self, sequence: str, camera: str, frame: Frame) -> Path:
        return self.root / sequence / "images" / camera / f"{frame.key}.png"

    def distance(self, sequence: str, camera: str, frame: Frame) -> Path | None:
        path = self.root / sequence / "distance" / camera / f"{frame.key}.npy"
        return path if path.is_file() else None

    def moving(self, sequence: str, camera: str, frame: Frame) -> Path | None:
        """The frame's mask of pixels that see a moving object (a PNG, nonzero = moving), if any."""
        path = self.root / sequence / "moving" / camera / f"{frame.key}.png"
        return path if path.is_file() else None


STAMP = re.compile(r"(0|[1-9]\d*)\.png")  # a timestamp in ns, written as an integer is written


IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm"}


def written_rig(staging: Path, rig: dict, sequence: str, names, src: Path, out: Path) -> dict[str, int]:
    """An importer's ``rig`` written as ``staging/rig.yaml`` and read back as training reads it: the frames
    each camera of ``names`` keeps in ``sequence``. What the loader refuses is a ValueError naming the
    source ``src``, with the paths as they will be at ``out``: it is never moved into place."""
    (staging / "rig.yaml").write_text(yaml.safe_dump(rig, sort_keys=False, width=120))
    try:
        layout = RigLayout(staging)
        return {name: len(layout.frames(sequence, name)) for name in names}
    except (FileNotFoundError, ValueError) as err:
        raise ValueError(
            f"{src}: the converted rig does not load: {str(err).replace(str(staging), str(out))}"
        ) from None


def image_stamps(folder: Path) -> tuple[list[int], list[str]]:
    """The timestamps of ``folder``'s images (``<timestamp_ns>.png``, sorted) and the names of the other
    image files (``frame_x.png``, ``1.PNG``, ``0012.png``: a leading zero would name another file than the
    one the timestamp writes; ``1.jpg``), which are reported, never read. Folders, hidden files and files
    that are no image (``notes.txt``) are not the layout's."""
    if not folder.is_dir():
        return [], []
    stamps, other = [], []
    for path in sorted(folder.iterdir()):
        if path.is_dir() or path.name.startswith("."):
            continue
        if STAMP.fullmatch(path.name):
            stamps.append(int(path.stem))
        elif path.suffix.lower() in IMAGE_SUFFIXES:  # an image the layout cannot place in time
            other.append(path.name)
    return sorted(stamps), other


QUATERNION_NORM_TOLERANCE = 1e-3


def unit_quaternion(values, where: str) -> np.ndarray:
    """``values`` as a unit quaternion, refused (naming ``where``) unless its norm lies within
    ``QUATERNION_NORM_TOLERANCE`` of 1: a norm of 2 or 1e-6 is a unit or a column gone wrong, not a
    rotation to normalise silently."""
    q = np.asarray(values, dtype=float)
    norm = float(np.linalg.norm(q))
    if not abs(norm - 1) <= QUATERNION_NORM_TOLERANCE:
        raise ValueError(
            f"{where}: quaternion of norm {norm:.6g}; a rotation is a unit quaternion "
            f"(norm within {QUATERNION_NORM_TOLERANCE:g} of 1)"
        )
    return q / norm


def pose_row(where: str, values, stamp: int, said: str, lines: dict[int, int], line: int) -> None:
    """One row of a pose file checked (``where``: its file and line): finite numbers, a unit quaternion
    (``values[3:]``, :func:`unit_quaternion`) and a stamp no earlier row has (``lines``: stamp -> its line,
    updated; ``said``: the stamp as the file writes it)."""
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{where}: a non-finite value")
    unit_quaternion(values[3:], where)
    if stamp in lines:
        raise ValueError(f"{where}: timestamp {said} already has a pose on line {lines[stamp]}")
    lines[stamp] = line


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (shortest arc)."""
    dot = float(np.dot(q0, q1))
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(dot)
    return (math.sin((1 - u) * theta) * q0 + math.sin(u * theta) * q1) / math.sin(theta)


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) to a rotation matrix: ``geometry.quaternion_to_matrix`` for numpy."""
    return quaternion_to_matrix(torch.from_numpy(np.asarray(q, dtype=np.float64))).numpy()


GAP_FACTOR = 5  # default bound on a gap of the poses: this many median pose intervals


def max_gap_ns(times: np.ndarray, max_gap: float | None = None) -> int:
    """The longest gap of the poses (ns) that images are interpolated across: ``max_gap`` seconds, or by
    default ``GAP_FACTOR`` times the median interval of ``times`` (sorted pose stamps, ns)."""
    if max_gap is not None:
        return round(max_gap * 1e9)
    return int(GAP_FACTOR * np.median(np.diff(times)))


def in_pose_gap(times: np.ndarray, stamps, max_gap: int) -> np.ndarray:
    """Which ``stamps`` (inside ``times``' range) fall between two poses more than ``max_gap`` ns apart;
    a stamp on a pose is never in a gap."""
    stamps = np.asarray(stamps, dtype=np.int64).reshape(-1)
    i = np.clip(np.searchsorted(times, stamps, side="right") - 1, 0, len(times) - 2)
    on_pose = (stamps == times[i]) | (stamps == times[i + 1])
    return (times[i + 1] - times[i] > max_gap) & ~on_pose


def quaternion_order_hint(trans: np.ndarray, quats: np.ndarray) -> str | None:
    """Why the unit quaternions ``quats`` (read as x, y, z, w) look like w, x, y, z ones, or None.

    Two tells: every quaternion is (+-1, 0, 0, 0), which read as x, y, z, w is a 180-degree roll about x
    and written as w, x, y, z is the identity; or the direction of motion in the body frame is
    scattered as the file reads, and nearly constant (a vehicle moving along one of its axes) when read
    as w, x, y, z. The relative angle between two rotations is the same in either order, so only the
    rotations against the translations can tell them apart."""
    if np.abs(quats[:, 1:]).max() < 1e-6:
        return "every rotation is a 180-degree roll about x (quaternion 1 0 0 0), an identity in w,x,y,z"
    stride = max(1, len(trans) // 100)  # high-rate odometry: steps long enough to show a direction
    steps = trans[stride:] - trans[:-stride]
    length = np.linalg.norm(steps, axis=1)
    moving = length > 0.5 * np.median(length)
    if moving.sum() < 5:
        return None

    def axis_consistency(q: np.ndarray) -> float:  # 1: the body moves along one of its own axes
        d = np.einsum(
            "nji,nj->ni", quaternion_matrix(q[:-stride][moving]), steps[moving] / length[moving, None]
        )
        return float(np.linalg.eigvalsh(d.T @ d / len(d))[-1])

    as_read, as_wxyz = axis_consistency(quats), axis_consistency(quats[:, [1, 2, 3, 0]])
    if as_wxyz > 0.9 and as_wxyz - as_read > 0.2:
        return (
            f"the body's direction of motion is scattered over its axes (consistency {as_read:.2f}), "
            f"but nearly constant when the quaternions are read as w,x,y,z ({as_wxyz:.2f})"
        )
    return None


def interpolate_pose(times: np.ndarray, trans: np.ndarray, quats: np.ndarray, t: int) -> np.ndarray:
    """Body-to-world pose at ``t`` (inside ``times``): linear in translation, slerp in rotation."""
    i = int(np.searchsorted(times, t, side="right")) - 1
    i = min(max(i, 0), len(times) - 2)
    u = (t - times[i]) / (times[i + 1] - times[i])
    R = quaternion_matrix(slerp(quats[i], quats[i + 1], float(u)))
    return make_pose(R, (1 - u) * trans[i] + u * trans[i + 1]).numpy()


def read_transform(value, path: Path, key: str) -> np.ndarray:
    """A 4x4 / 3x4 matrix (nested lists) or ``{translation: [3], quaternion_xyzw: [4]}``."""
    if isinstance(value, dict) and "quaternion_xyzw" in value:
        try:
            norm = float(np.linalg.norm(np.asarray(value["quaternion_xyzw"], float)))
        except (ValueError, TypeError):
            norm = 1.0  # not numbers: the message below
        if not abs(norm - 1) <= QUATERNION_NORM_TOLERANCE:
            raise CalibrationError(
                path, f"{key}.quaternion_xyzw", f"norm {norm:.6g}; a rotation is a unit quaternion "
                f"(norm within {QUATERNION_NORM_TOLERANCE:g} of 1)"
            )  # fmt: skip
    try:
        if isinstance(value, dict):
            q = np.asarray(value["quaternion_xyzw"], float)
            T = make_pose(
                quaternion_matrix(q / np.linalg.norm(q)), np.asarray(value["translation"], float)
            ).numpy()
        else:
            m = np.asarray(value, dtype=float)
            if m.shape not in ((3, 4), (4, 4)):
                raise ValueError
            T = pose_from_3x4(m[:3]).numpy()
    except (KeyError, ValueError, TypeError):
        raise CalibrationError(
            path, key, "expected a 3x4/4x4 matrix or {translation, quaternion_xyzw}"
        ) from None
    last_row = m[3] if not isinstance(value, dict) and m.shape == (4, 4) else None
    return checked_rigid(T, path, key, last_row)


def _positive_seconds(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and value > 0


def _timestamp(field: str) -> int:
    """A nanosecond timestamp, parsed exactly: as a float, today's ~1.7e18 ns would lose 8 bits."""
    try:
        return int(field)
    except ValueError:
        value = float(field)  # "1.5e9" and the like; a ValueError here is the caller's to report
        if not math.isfinite(value) or value != int(value):
            raise ValueError(field) from None
        return int(value)


def existing(path: Path, what: str) -> Path:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {what} not found")
    return path
