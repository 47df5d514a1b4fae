"""``FisheyeDataset``: samples from any layout (KITTI-360 or robot rig), built one way for both.

Neighbouring frames are neighbouring pose rows (KITTI-360's frame indices are sparse) or neighbouring
images (rig). A target is dropped when a neighbour is missing, or when the translation to a neighbour is
below ``min_translation`` (standing still: no parallax) or above ``max_translation`` (a jump); the
counts are logged. Images are resized to the training size through a disk cache, and the camera model
is resized with them.

Surprises are reported once, not once per frame: a grayscale camera folder (its images are replicated
to three channels), a training size whose aspect ratio differs from a camera's (its images are
stretched).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from ..files import atomic_write_bytes, file_key, path_name
from ..geometry import relative_pose
from ..images import ImageError, read_image
from .augment import Augment, PoseNoise
from .files import binary_mask, read_checked, report_grayscale, warn_once
from .kitti360 import OCCLUSION, Kitti360Layout, LidarGroundTruth
from .layouts import Frame

log = logging.getLogger(__name__)

# A training size whose aspect ratio differs from a camera's by more than this stretches its images.
ASPECT_TOLERANCE = 0.01


def report_aspect(root, name: str, native: tuple[int, int], size: tuple[int, int]) -> None:
    """Warn (once per camera and size) when resizing to ``size`` stretches the camera's images."""
    native_ratio, ratio = native[0] / native[1], size[0] / size[1]
    if abs(ratio / native_ratio - 1) <= ASPECT_TOLERANCE:
        return
    warn_once(
        ("aspect", str(root), name, native, size),
        "%s: camera %s is %dx%d (aspect %.3f) but the training size is %dx%d (aspect %.3f): its images "
        "and camera model are stretched %s",
        root,
        name,
        *native,
        native_ratio,
        *size,
        ratio,
        "horizontally" if ratio > native_ratio else "vertically",
    )


def default_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "fisheyedepth"


class ImageCache:
    """Resized copies of images, keyed by source path, size and modification time; written atomically,
    so concurrent DataLoader workers never read half a file."""

    _announced: set[str] = set()

    def __init__(self, cache_dir: str | os.PathLike | None = None):
        self.dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()

    def read(self, path: Path, size: tuple[int, int], expect: tuple[int, int]) -> np.ndarray:
        """``path`` (which must be ``expect`` = (width, height)) resized to ``size``, cached."""
        if not path.is_file():
            raise FileNotFoundError(f"{path}: image not found")
        key = file_key(path, f"{expect[0]}x{expect[1]}")
        cached = self.dir / "resized" / f"{size[0]}x{size[1]}" / f"{key}.png"
        if cached.is_file():
            try:
                return read_image(cached).bgr
            except ImageError as exc:
                log.warning("%s; resizing %s again", exc, path)
        resized = cv2.resize(read_checked(path, expect), size, interpolation=cv2.INTER_AREA)
        cached.parent.mkdir(parents=True, exist_ok=True)
        if str(self.dir) not in ImageCache._announced:
            ImageCache._announced.add(str(self.dir))
            log.info("resized images are cached in %s", self.dir / "resized")
        ok, encoded = cv2.imencode(".png", resized)
        if not ok:
            raise OSError(f"{cached}: could not encode the resized image")
        atomic_write_bytes(cached, encoded.tobytes())  # concurrent workers never see half a file
        return resized


def baseline_rows(positions: np.ndarray, row: int, offsets, baseline: float) -> list[int] | None:
    """For each offset, the row on its side of ``row`` whose position (``[N, 3]``, metres) is nearest to
    ``baseline * |offset| / max|offsets|`` from the target's, among the frames up to the first one that
    is at least that far (the one nearer the target on a tie); None when the sequence ends before a
    frame on that side is that far. A stop with jittering poses, or a turn back, never ends the search
    early: only reaching the distance does."""
    top = max(abs(o) for o in offsets)
    rows = []
    for offset in offsets:
        want, step = baseline * abs(offset) / top, 1 if offset > 0 else -1
        best, k = None, row + step
        while 0 <= k < len(positions):
            distance = float(np.linalg.norm(positions[k] - positions[row]))
            if best is None or abs(distance - want) < best[0]:
                best = (abs(distance - want), k)
            if distance >= want:
                break
            k += step
        else:
            return None  # the sequence ended short of the wanted distance
        rows.append(best[1])
    return rows


@dataclasses.dataclass(frozen=True)
class Item:
    sequence: str
    camera: str
    row: int  # index of the target in layout.frames(sequence, camera)
    sources: tuple[int, ...]  # rows of its source frames, one per offset (none for evaluation)


def parse_split(spec, layout) -> list[tuple[str, set[int] | None, int, list[str] | None]]:
    """A split is a file of ``<sequence> <frame_key> [camera]`` lines, or a list of entries
    ``{sequence, start?, stop?, stride?, cameras?}`` (rows of the sequence, Python slice semantics), or
    ``"all"``. Returns (sequence, frame keys or None, stride, cameras or None) per entry."""
    if spec == "all":
        return [(s, None, 1, None) for s in layout.sequences()]
    if isinstance(spec, str | os.PathLike):
        path = Path(spec) if Path(spec).is_absolute() or Path(spec).is_file() else layout.root / spec
        if not path.is_file():
            raise FileNotFoundError(f"{path}: split file not found")
        per_seq: dict[tuple[str, str | None], set[int]] = {}
        for lineno, line in enumerate(path.read_text().splitlines(), start=1):
            fields = line.split()
            if not fields:
                continue
            if len(fields) not in (2, 3) or not fields[1].isdigit():
                raise ValueError(f"{path}:{lineno}: expected '<sequence> <frame> [camera]'")
            path_name(fields[0], "sequence", f"{path}:{lineno}")  # folders under the layout's root
            if len(fields) == 3:
                path_name(fields[2], "camera", f"{path}:{lineno}")
            per_seq.setdefault((fields[0], fields[2] if len(fields) == 3 else None), set()).add(
                int(fields[1])
            )
        return [(s, keys, 1, None if c is None else [c]) for (s, c), keys in per_seq.items()]
    out = []
    for entry in spec:
        entry = dict(entry)
        rows = slice(entry.get("start"), entry.get("stop"))
        path_name(entry["sequence"], "sequence", "split")  # a folder under the layout's root
        out.append((entry["sequence"], rows, int(entry.get("stride", 1)), entry.get("cameras")))
    return out


class FisheyeDataset(Dataset):
    def __init__(
        self,
        layout,
        split="all",
        cameras: list[str] | None = None,
        size: tuple[int, int] | None = None,
        offsets: tuple[int, ...] = (-1, 1),
        min_translation: float = 0.03,
        max_translation: float = 3.0,
        augment: Augment | None = None,
        ground_truth: str = "auto",
        skip_bad_frames: bool = False,
        cache_dir: str | os.PathLike | None = None,
        lidar_occlusion: float | None = OCCLUSION,
        pose_noise: PoseNoise | None = None,
        rig_offsets: tuple[int, ...] = (),
        source_baseline: float | None = None,
    ):
        """``ground_truth``: "distance" (rendered maps), "lidar" (projected scans, KITTI-360 layout),
        "auto" (whichever exists), or "none"; LiDAR is projected lazily, per frame, when a sample is
        read (``lidar_occlusion``: the occlusion filter's ratio, None for every point). ``offsets``:
        the source frames; empty for evaluation, which scores every frame of the split (no neighbour
        needed, no translation bound). ``pose_noise``: seeded odometry error on the relative poses (the
        paper's claim that the multi-channel head copes with noisy real poses). ``rig_offsets``: the
        rig's other cameras as sources too, at these time offsets (Full Surround Monodepth's spatial
        (0) and spatio-temporal (+-1) contexts): the known extrinsics and odometry warp one camera into
        another where their fields of view overlap; see :meth:`rig_frame` for how frames are paired.
        ``source_baseline``: metres; None (default) takes the sources ``offsets`` frames away. Set, each
        offset only gives a direction and a share of the baseline: its source is the frame on that side
        whose distance from the target is nearest to ``source_baseline * |offset| / max|offsets|``
        (see :func:`baseline_rows`), so a fast stretch of a drive gets nearer frames and a slow one
        farther ones, and every target sees about the same parallax."""
        if source_baseline is not None and not (source_baseline > 0 and math.isfinite(source_baseline)):
            raise ValueError(f"source_baseline: {source_baseline!r}, expected metres > 0 or None")
        if source_baseline is not None and 0 in offsets:
            raise ValueError(f"source_baseline needs offsets with a direction; got offsets {list(offsets)}")
        self.source_baseline = source_baseline
        self.pose_noise = pose_noise or PoseNoise()
        self.layout, self.size, self.offsets = layout, size, tuple(offsets)
        self.rig_offsets = tuple(rig_offsets)
        self.augment, self.skip_bad_frames = augment, skip_bad_frames
        self.cache = ImageCache(cache_dir)
        self.cameras = cameras or list(layout.cameras)
        unknown = set(self.cameras) - set(layout.cameras)
        if unknown:
            raise KeyError(
                f"{layout.root}: no camera {sorted(unknown)}; the layout has {sorted(layout.cameras)}"
            )
        if size is not None:
            for name in self.cameras:
                native = layout.cameras[name].camera
                report_aspect(layout.root, name, (native.width, native.height), tuple(size))
        self.ground_truth = ground_truth
        self.lidar = None
        if ground_truth in ("lidar", "auto") and isinstance(layout, Kitti360Layout):
            self.lidar = LidarGroundTruth(layout, self.cache.dir, lidar_occlusion)
        self.dropped = {
            "no neighbour": 0,
            "below min_translation": 0,
            "above max_translation": 0,
            "no pose": 0,
        }
        self.items: list[Item] = []
        self._keys: dict[tuple[str, str], tuple[np.ndarray, float]] = {}
        self._masks: dict[tuple[str, tuple[int, int]], torch.Tensor] = {}
        if self.rig_offsets:
            self._check_rig_sizes()
        for sequence, keys, stride, cams in parse_split(split, layout):
            for cam in cams or self.cameras:
                if cam not in self.cameras:
                    continue
                frames = layout.frames(sequence, cam)
                rows = self._rows(frames, keys, layout, sequence)
                positions = np.stack([f.pose[:3, 3] for f in frames]) if frames else np.zeros((0, 3))
                for row in rows[::stride]:
                    sources = self._source_rows(positions, row)
                    reason = self._check(positions, row, sources, min_translation, max_translation)
                    if reason is None and self.rig_offsets and not self._rig_frames(sequence, cam, row):
                        reason = "no neighbour"
                    if reason:
                        self.dropped[reason] += 1
                    else:
                        self.items.append(Item(sequence, cam, row, tuple(sources)))
        if any(self.dropped.values()):
            log.info(
                "%s: %d samples kept, dropped: %s",
                layout.root,
                len(self.items),
                ", ".join(f"{n} {k}" for k, n in self.dropped.items() if n),
            )
        self._posesets: dict[tuple[str, str], list[Frame]] = {}
        self._probe_grayscale()
        # a dataset whose first frame has a moving-object mask has one for every frame (synthetic traffic)
        self._has_moving = (
            bool(self.items) and ground_truth != "none" and bool(self._moving_path(self.items[0]))
        )

    def _probe_grayscale(self) -> None:
        """Read one image per (sequence, camera) now, so a grayscale camera is reported even when every
        later read comes from the resize cache. Unreadable images are left to the sample that reads them."""
        seen: set[tuple[str, str]] = set()
        for item in self.items:
            if (item.sequence, item.camera) in seen:
                continue
            seen.add((item.sequence, item.camera))
            frame = self.layout.frames(item.sequence, item.camera)[item.row]
            path = self.layout.image(item.sequence, item.camera, frame)
            try:
                image = read_image(path)
            except (FileNotFoundError, ValueError):
                continue
            if image.grayscale:
                report_grayscale(path)

    def _rows(self, frames: list[Frame], keys, layout, sequence) -> list[int]:
        if keys is None:
            return list(range(len(frames)))
        if isinstance(keys, slice):
            return list(range(len(frames)))[keys]
        index = {f.key: i for i, f in enumerate(frames)}
        missing = sorted(k for k in keys if k not in index)
        if missing:
            if not self.skip_bad_frames:
                raise KeyError(f"{layout.root}: sequence {sequence} has no pose for frame(s) {missing[:5]}")
            self.dropped["no pose"] += len(missing)
        return sorted(index[k] for k in keys if k in index)

    def _source_rows(self, positions: np.ndarray, row: int) -> list[int] | None:
        """The rows of the target's sources, one per offset, or None when one is outside the sequence."""
        if self.source_baseline is None or not self.offsets:
            rows = [row + offset for offset in self.offsets]
            return rows if all(0 <= r < len(positions) for r in rows) else None
        return baseline_rows(positions, row, self.offsets, self.source_baseline)

    def _check(
        self, positions: np.ndarray, row: int, sources: list[int] | None, lo: float, hi: float
    ) -> str | None:
        if sources is None:
            return "no neighbour"
        for source in sources:
            step = np.linalg.norm(positions[source] - positions[row])
            if step < lo:
                return "below min_translation"
            if step > hi:
                return "above max_translation"
        return None

    def __len__(self) -> int:
        return len(self.items)

    def _check_rig_sizes(self) -> None:
        sizes = {
            n: (self.layout.cameras[n].camera.width, self.layout.cameras[n].camera.height)
            for n in self.cameras
        }
        if self.size is None and len(set(sizes.values())) > 1:
            raise ValueError(
                f"{self.layout.root}: rig_offsets stack every camera's images as one target's sources, but "
                f"the cameras differ in size ({sizes}); set a training size"
            )

    def rig_frame(self, sequence: str, camera: str, key: int) -> int | None:
        """The row of ``camera``'s frame taken with the frame ``key`` of another camera: the nearest key
        within half of ``camera``'s median frame interval (KITTI-360's frame indices: the same index;
        a rig's timestamps: the same trigger), else None. The pose of that frame is its own, so a
        small time offset between the cameras moves no pixel of a static world."""
        if (sequence, camera) not in self._keys:
            keys = np.array([f.key for f in self.layout.frames(sequence, camera)], dtype=np.int64)
            spacing = float(np.median(np.diff(keys))) if len(keys) > 1 else 1.0
            self._keys[(sequence, camera)] = (keys, spacing / 2)
        keys, tolerance = self._keys[(sequence, camera)]
        i = int(np.searchsorted(keys, key))
        near = [j for j in (i - 1, i) if 0 <= j < len(keys)]  # the keys either side; the earlier on a tie
        row = min(near, key=lambda j: abs(int(keys[j]) - key), default=None)
        return row if row is not None and abs(int(keys[row]) - key) <= tolerance else None

    def _rig_frames(self, sequence: str, camera: str, row: int) -> list[tuple[str, int]] | None:
        """``(camera, row)`` of every rig source of the target, or None when one is missing."""
        frames = self.layout.frames(sequence, camera)
        out = []
        for offset in self.rig_offsets:
            if not 0 <= row + offset < len(frames):
                return None
            for other in self.cameras:
                if other == camera:
                    continue
                match = self.rig_frame(sequence, other, frames[row + offset].key)
                if match is None:
                    return None
                out.append((other, match))
        return out

    def _image(self, path: Path, camera, native) -> torch.Tensor:
        size, expect = (camera.width, camera.height), (native.width, native.height)
        bgr = read_checked(path, expect) if size == expect else self.cache.read(path, size, expect)
        return torch.from_numpy(np.ascontiguousarray(bgr[..., ::-1])).permute(2, 0, 1).float() / 255.0

    def build(self, item: Item) -> dict[str, Any]:
        spec = self.layout.cameras[item.camera]
        native = spec.camera
        camera = (
            native.resize(*self.size) if self.size and self.size != (native.width, native.height) else native
        )
        frames = self.layout.frames(item.sequence, item.camera)
        target = frames[item.row]
        E = torch.from_numpy(spec.cam_to_body)
        path = self.layout.image(item.sequence, item.camera, target)
        sample: dict[str, Any] = {"camera": camera, "image": self._image(path, camera, native)}
        sample["camera_name"], sample["frame"] = item.camera, f"{item.sequence}/{item.camera}/{target.key}"
        sources, poses = [], []
        for offset, source in zip(self.offsets, item.sources, strict=True):
            other = frames[source]
            sources.append(self._image(self.layout.image(item.sequence, item.camera, other), camera, native))
            T = relative_pose(torch.from_numpy(target.pose), torch.from_numpy(other.pose), E)
            poses.append(self.pose_noise(T, f"{item.sequence}|{item.camera}|{target.key}|{offset}"))
        sample["mask"] = self._mask(spec, camera)
        if self.rig_offsets:
            source_cameras, source_masks = [camera] * len(sources), [sample["mask"]] * len(sources)
            for name, row in self._rig_frames(item.sequence, item.camera, item.row) or []:
                other_spec = self.layout.cameras[name]
                other_cam = other_spec.camera.resize(camera.width, camera.height)
                other = self.layout.frames(item.sequence, name)[row]
                path_s = self.layout.image(item.sequence, name, other)
                sources.append(self._image(path_s, other_cam, other_spec.camera))
                E_s = torch.from_numpy(other_spec.cam_to_body)
                T = relative_pose(torch.from_numpy(target.pose), torch.from_numpy(other.pose), E, E_s)
                poses.append(
                    self.pose_noise(T, f"{item.sequence}|{item.camera}|{target.key}|{name}|{other.key}")
                )
                source_cameras.append(other_cam)
                source_masks.append(self._mask(other_spec, other_cam))
            sample["source_camera"], sample["source_mask"] = source_cameras, torch.stack(source_masks)
        if sources:
            sample["sources"], sample["poses"] = torch.stack(sources), torch.stack(poses).float()
        else:  # evaluation: the target alone
            sample["sources"] = sample["image"].new_zeros(0, *sample["image"].shape)
            sample["poses"] = torch.zeros(0, 4, 4)
        sample["cam_to_body"] = E.float()  # lets a PoseNet predict the body's motion, like odometry
        gt = self._ground_truth(item, camera, target)
        if gt is not None:
            sample["distance"], sample["distance_source"] = gt
            if self._has_moving:
                sample["moving"] = self._moving(item, camera, target)
        if not all(torch.isfinite(v).all() for v in sample.values() if isinstance(v, torch.Tensor)):
            raise ValueError(f"{path}: sample has non-finite values")
        return sample

    def _moving_path(self, item: Item, frame: Frame | None = None) -> Path | None:
        find = getattr(self.layout, "moving", None)
        if find is None:
            return None
        frame = frame or self.layout.frames(item.sequence, item.camera)[item.row]
        return find(item.sequence, item.camera, frame)

    def _moving(self, item: Item, camera, frame: Frame) -> torch.Tensor:
        """``[1, H, W]`` float: 1 where the ground truth sees a moving object (the mask at its native
        size, resized like the distance map). Missing for one frame of a dataset that has them: an error."""
        path = self._moving_path(item, frame)
        if path is None:
            raise FileNotFoundError(
                f"no moving-object mask for {item.sequence}/{item.camera}/{frame.key}, though the "
                "dataset's first frame has one"
            )
        native = self.layout.cameras[item.camera].camera
        size, native_size = (camera.width, camera.height), (native.width, native.height)
        return binary_mask(path, size, native_size, "moving-object mask")

    def _mask(self, spec, camera) -> torch.Tensor:
        """``[1, H, W]`` float: 1 where ``spec``'s body mask (if any) lets the pixel be used, read through
        the layout (checked at its camera's size) and resized like the images (nearest). Kept per camera
        and size for this dataset's life (a sample with rig sources needs every camera's mask)."""
        size = (camera.width, camera.height)
        if spec.mask is None:
            return torch.ones(1, camera.height, camera.width)
        key = (spec.name, size)
        if key not in self._masks:
            mask = self.layout.read_mask(spec.name).astype(np.uint8)
            if mask.shape[::-1] != size:
                mask = cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST)
            self._masks[key] = torch.from_numpy(mask.astype(np.float32))[None]
        return self._masks[key].clone()

    def _ground_truth(self, item: Item, camera, frame: Frame) -> tuple[torch.Tensor, str] | None:
        """``(distance [1, H, W], source)``: a ``distance_source`` of :mod:`.batch`."""
        if self.ground_truth in ("distance", "auto"):
            d = self.layout.read_distance(item.sequence, item.camera, frame)
            if d is not None:
                if d.shape[1::-1] != (camera.width, camera.height):  # the training size
                    d = cv2.resize(d, (camera.width, camera.height), interpolation=cv2.INTER_NEAREST)
                return torch.from_numpy(d)[None], "rendered"
            if self.ground_truth == "distance":
                raise FileNotFoundError(
                    f"no ground-truth distance map for {item.sequence}/{item.camera}/{frame.key}"
                )
        if self.lidar is not None and self.ground_truth in ("lidar", "auto"):
            out = self.lidar(item.sequence, item.camera, camera, frame)
            if out is not None:
                return torch.from_numpy(out[0])[None], self.lidar.source
            if self.ground_truth == "lidar":
                raise FileNotFoundError(
                    f"{self.layout.lidar(item.sequence, frame)}: no Velodyne scan for "
                    f"{item.sequence}/{item.camera}/{frame.key} (ground_truth: lidar)"
                )
            # auto: this frame has neither, its neighbours may; an empty map scores no pixel of it
            return torch.zeros(1, camera.height, camera.width), "none"
        return None

    def __getitem__(self, index: int) -> dict[str, Any]:
        item = self.items[index]
        try:
            sample = self.build(item)
        except (FileNotFoundError, ValueError, KeyError) as exc:
            if not self.skip_bad_frames:
                raise
            return {"skipped": f"{item.sequence}/{item.camera}/row {item.row}: {exc}"}
        if self.augment is not None:
            sample = self.augment(sample)
        return sample
