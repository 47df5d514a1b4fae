"""Writing a synthetic dataset in the KITTI-360 layout (see docs/data-format.md).

The dataset is written into a hidden temporary folder beside ``out`` and renamed into place only when
complete, so an interrupted run never looks like a dataset; ``synthetic.json`` is written last. The first
file written is the marker ``.fisheyedepth-synthetic``: a folder that holds it was started by this generator
and may be rendered again, anything else is somebody's data and is never replaced by ``ensure_dataset``.

SIGTERM while rendering (as SIGINT) stops the worker processes, removes the temporary folder and raises
``Terminated`` (``SystemExit(143)``); workers also die with the rendering process on Linux even if it is
killed outright, and the next run removes the temporary folder such a run left behind.

A full disk (or quota) stops the run the same way and raises :class:`NoSpaceLeft`, naming the dataset
folder; every file is written through Python's file objects, whose failures carry ``ENOSPC``
(``ndarray.tofile`` and ``cv2.imwrite`` report only a short write, or nothing).
"""

from __future__ import annotations

import ctypes
import errno
import io
import json
import math
import os
import shutil
import signal
import socket
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import cv2
import numpy as np
import torch
import yaml
from tqdm import tqdm

from .. import __version__
from ..cameras import CameraModel, opencv_yaml
from ..geometry import axis_angle_to_matrix, make_pose
from ..option_checks import SWITCH, Choice, Group, Kind, ListOf, Number, check_options
from ..utils import pid_alive
from .indoor import make_indoor_trajectory, make_indoor_world
from .raycast import Movers, scene_tensors
from .render import CameraRenderer, LidarRenderer, quantise
from .rig import RIGS, Rig, make_rig
from .sensor import EFFECTS, Sensor, blur_times, check_effects
from .traffic import DENSITY, Traffic, make_traffic, no_traffic
from .world import SCENES, World, make_drive, make_world

SPLITS = ("train", "val", "test")
SEQUENCES = {split: f"2013_05_28_drive_{i:04d}_sync" for i, split in enumerate(SPLITS)}
GAP = 10  # trajectory frames left out between two splits, so no two splits share a segment
MARKER = ".fisheyedepth-synthetic"  # the first file of every dataset this generator starts
MARKER_TEXT = (
    "Rendered by fisheyedepth's synthetic generator (fisheyedepth.synthetic.generate).\n"
    "This folder may be deleted and rendered again; see docs/data-format.md.\n"
)
OWNER = ".partial-owner"  # "<host> <pid>" of the rendering run; removed before synthetic.json is written
# must match a finished dataset's synthetic.json (a key it lacks, from an older version, is not checked)
CHECKED = (
    "rig",
    "frames",
    "size",
    "seed",
    "supersample",
    "lane",
    "scene",
    "random_cameras",
    "traffic",
    "effects",
)
# parameters a street dataset with fixed cameras does not write into synthetic.json (its files stay those
# of the versions before them): a finished dataset without the key was rendered with this value
UNWRITTEN = {"scene": "street", "random_cameras": False, "traffic": 0, "effects": []}
# The kind and range of each switch and number of the generation (``data.generate.*`` of a training
# config, the flags of ``fisheyedepth-synthetic``; fisheyedepth.option_checks): checked before anything
# is rendered. ``worlds``: a mixed dataset's per-folder parameters, each of the same kinds.
_WORLD_OPTIONS: dict[str, Kind] = {
    "frames": Number(low=9, whole=True, note="3 per split"),
    "size": Number(low=16, whole=True),  # and a multiple of 8 (generate)
    "seed": Number(low=0, whole=True),
    "supersample": Number(low=1, whole=True),
    "workers": Number(low=0, whole=True),
    "lidar": SWITCH,
    "progress": SWITCH,
    "random_cameras": SWITCH,
    "traffic": DENSITY,
    "effects": ListOf(Choice(EFFECTS, note="each effect a switch, named alone"), single=True),
}
GENERATE_OPTIONS: dict[str, Kind] = _WORLD_OPTIONS | {"worlds": ListOf(Group(_WORLD_OPTIONS), optional=True)}
LANES = {"right": 1.75, "left": -1.75}  # the car's offset from the street's centreline, metres to its right
PR_SET_PDEATHSIG = 1  # linux/prctl.h


class NotASyntheticDataset(FileExistsError):
    """A folder that fisheyedepth did not render (no ``synthetic.json``, no marker): it is never replaced."""


class DatasetMismatch(ValueError):
    """A finished synthetic dataset rendered with other generation parameters than the ones asked for."""


class NoSpaceLeft(OSError, ValueError):
    """The disk (or the quota) filled up while rendering; the partial dataset was removed. A ValueError
    too, so that the entry points report it in one line."""

    def __init__(self, out: Path, file: str | None):
        free = shutil.disk_usage(out.parent).free / 2**20 if out.parent.is_dir() else 0.0
        at = f" (writing {Path(file).name})" if file else ""
        super().__init__(
            f"{out}: no space left on device while rendering the synthetic dataset{at}; the partial "
            f"dataset was removed, {free:.0f} MB are free there: free some space or choose another folder"
        )
        self.errno = errno.ENOSPC


class Terminated(SystemExit):
    """SIGTERM arrived while rendering; exits with status 143 (128 + SIGTERM) like an untrapped SIGTERM."""

    def __init__(self) -> None:
        super().__init__(128 + int(signal.SIGTERM))


@dataclass(frozen=True)
class Job:
    sequence: str
    frame: int
    pose: np.ndarray
    index: int = 0  # the frame's place on the whole trajectory (traffic, exposure and noise follow it)


def _row(T: np.ndarray) -> str:
    return " ".join(f"{v:.10f}" for v in T[:3].reshape(-1))


def split_frames(frames: int) -> dict[str, tuple[int, int]]:
    """Trajectory index ranges [start, stop) per split: 80 / 10 / 10 %, GAP frames apart."""
    if frames < 9:
        raise ValueError(f"need at least 9 frames (3 per split), got {frames}")
    n_val = n_test = max(3, round(0.1 * frames))
    n_train = frames - n_val - n_test
    starts = (0, n_train + GAP, n_train + n_val + 2 * GAP)
    return {s: (a, a + n) for s, a, n in zip(SPLITS, starts, (n_train, n_val, n_test), strict=True)}


def _write(path: Path, data: bytes) -> None:
    """``path.write_bytes(data)``; a failure names the file (a full disk's ENOSPC arrives without it)."""
    try:
        path.write_bytes(data)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None


def _png(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"could not encode a {image.shape} {image.dtype} image as PNG")
    return data.tobytes()


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def make_scene_world(scene: str, seed: int) -> World:
    """The world of ``scene`` ("street" or "indoor") drawn from ``seed``."""
    if scene not in SCENES:
        raise ValueError(f"scene must be one of {SCENES}, got {scene!r}")
    return make_world(seed) if scene == "street" else make_indoor_world(seed)


def make_scene_trajectory(world: World, frames: int, seed: int, lane: str = "right") -> np.ndarray:
    """``[frames, 4, 4]`` body poses through ``world``: the car in ``lane``, or the walk around the room."""
    return make_scene_motion(world, frames, seed, lane)[0]


def make_scene_motion(
    world: World, frames: int, seed: int, lane: str = "right", traffic: float = 0.0
) -> tuple[np.ndarray, Traffic]:
    """The body poses of :func:`make_scene_trajectory` and the traffic at density ``traffic`` (streets
    only; 0 leaves the world as it was)."""
    if world.scene == "indoor":
        if traffic:
            raise ValueError(f"traffic: {traffic} asked for, but the indoor scene has no streets (use 0)")
        return make_indoor_trajectory(world, frames, seed), no_traffic(frames)
    drive = make_drive(world, frames, seed, LANES[lane])
    return drive.poses, make_traffic(world, drive, traffic, seed)


def pose_at(poses: np.ndarray, time: float) -> np.ndarray:
    """The ``[4, 4]`` pose at a fractional trajectory frame: positions interpolated linearly, rotations
    along the shortest arc between the two frames around it (extrapolated past either end)."""
    k = int(np.clip(np.floor(time), 0, len(poses) - 2))
    u = time - k
    a, b = poses[k], poses[k + 1]
    step = a[:3, :3].T @ b[:3, :3]
    angle = float(np.arccos(np.clip((np.trace(step) - 1) / 2, -1.0, 1.0)))
    axis = np.array([step[2, 1] - step[1, 2], step[0, 2] - step[2, 0], step[1, 0] - step[0, 1]])
    axis *= 0.0 if angle < 1e-12 else angle / (2 * math.sin(angle))  # the rotation's log: axis x angle
    R = a[:3, :3] @ axis_angle_to_matrix(torch.from_numpy(u * axis)).numpy()
    return make_pose(R, (1 - u) * a[:3, 3] + u * b[:3, 3]).numpy()


class _Worker:
    """Renders and writes whole frames; built once per process."""

    def __init__(
        self,
        root: Path,
        seed: int,
        rig_name: str,
        size: int,
        supersample: int,
        lidar: bool,
        scene: str = "street",
        random_cameras: bool = False,
        traffic: float = 0.0,
        effects: tuple[str, ...] = (),
        lane: str = "right",
        frames: int = 0,
    ):
        self.root, self.world = root, make_scene_world(scene, seed)
        self.rig = make_rig(rig_name, size, scene, random_cameras, seed)
        self.effects = check_effects(effects)
        self.poses, self.traffic = None, None
        if traffic or "motion_blur" in self.effects:  # the motion around each frame is needed
            self.poses, self.traffic = make_scene_motion(self.world, frames, seed, lane, traffic)
        # the street with its own cameras keeps the ground truth it has always had (SceneTensors)
        self.scene = scene_tensors(self.world, legacy_culling=scene == "street" and not random_cameras)
        self.cameras = {
            name: CameraRenderer(cam, self.rig.cam_to_pose[name], supersample, self.rig.ego)
            for name, cam in self.rig.cameras.items()
        }
        self.lidar = LidarRenderer(self.rig.velo_to_pose, ego=self.rig.ego) if lidar else None
        self.sensors = {}
        if self.effects:
            for i, (name, renderer) in enumerate(self.cameras.items()):
                valid = renderer.centre.untile(renderer.centre.valid[:, None])[..., 0].numpy()
                self.sensors[name] = Sensor(self.effects, seed, i, valid)

    def movers(self, time: float, pose: np.ndarray) -> Movers | None:
        """The traffic's boxes at a (fractional) trajectory frame; None without traffic."""
        if self.traffic is None or not self.traffic.n_agents:
            return None
        return Movers.from_boxes(self.traffic.boxes_at(time, pose[:2, 3]))

    def __call__(self, job: Job) -> None:
        stem = f"{job.frame:010d}"
        movers = self.movers(job.index, job.pose)
        moving = self.traffic.moving(job.index) if movers is not None else None
        shots = [(job.pose, movers)]
        if "motion_blur" in self.effects:  # the open shutter: the car and the traffic move
            shots = [(pose := pose_at(self.poses, t), self.movers(t, pose)) for t in blur_times(job.index)]
        for name, renderer in self.cameras.items():
            colour = sum(renderer.colour(self.scene, self.world, *shot) for shot in shots) / len(shots)
            sensor = self.sensors.get(name)
            if sensor is not None:
                colour = sensor(colour, job.index)
            distance, moving_mask = renderer.truth(self.scene, job.pose, movers, moving)
            image = self.root / "data_2d_raw" / job.sequence / name / "data_rgb" / f"{stem}.png"
            _write(image, _png(quantise(colour)[..., ::-1]))
            path = self.root / "data_2d_distance" / job.sequence / name / f"{stem}.npy"
            _write(path, _npy(distance))
            if moving_mask is not None:  # with traffic
                path = self.root / "data_2d_moving" / job.sequence / name / f"{stem}.png"
                _write(path, _png(moving_mask * np.uint8(255)))
        if self.lidar is not None:
            points = self.lidar.render(self.scene, self.world, job.pose, movers)
            scan = self.root / "data_3d_raw" / job.sequence / "velodyne_points" / "data" / f"{stem}.bin"
            _write(scan, np.ascontiguousarray(points).tobytes())


_WORKER: _Worker | None = None


def _die_with_parent(parent: int) -> None:
    """Linux: the kernel sends this worker SIGTERM when the rendering process dies, even of SIGKILL."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
        except (OSError, AttributeError):  # best effort: no libc, no prctl
            pass
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(1)


def _init_worker(parent: int, *args) -> None:
    global _WORKER
    _die_with_parent(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group: the parent stops us
    torch.set_num_threads(1)
    _WORKER = _Worker(*args)


def _run_job(job: Job) -> None:
    assert _WORKER is not None
    _WORKER(job)


def calibration_text(camera: CameraModel, name: str) -> str:
    """A camera's ``calibration/<name>.yaml``: KITTI-360's OpenCV YAML for the models it has a layout for
    (Mei, Kannala-Brandt), the project's own YAML for the others (double sphere, Fisheye624); both are
    what ``load_camera`` reads back to the same camera."""
    try:
        return opencv_yaml(camera, name)
    except TypeError:
        return yaml.safe_dump(camera.to_dict(), sort_keys=False)


def _write_layout(
    root: Path,
    rig: Rig,
    body_masks: dict[str, np.ndarray],
    jobs: list[Job],
    lidar: bool,
    moving: bool = False,
) -> None:
    calib = root / "calibration"
    calib.mkdir(parents=True)
    for name, cam in rig.written.items():
        (calib / f"{name}.yaml").write_text(calibration_text(cam, name))
        _write(calib / f"body_mask_{name}.png", _png(np.where(body_masks[name], 255, 0).astype(np.uint8)))
    (calib / "calib_cam_to_pose.txt").write_text(
        "".join(f"{k}: {_row(T)}\n" for k, T in rig.cam_to_pose.items())
    )
    (calib / "calib_cam_to_velo.txt").write_text(_row(rig.cam0_to_velo) + "\n")
    for seq in sorted({j.sequence for j in jobs}):
        for name in rig.cameras:
            (root / "data_2d_raw" / seq / name / "data_rgb").mkdir(parents=True)
            (root / "data_2d_distance" / seq / name).mkdir(parents=True)
            if moving:
                (root / "data_2d_moving" / seq / name).mkdir(parents=True)
        if lidar:
            (root / "data_3d_raw" / seq / "velodyne_points" / "data").mkdir(parents=True)
        (root / "data_poses" / seq).mkdir(parents=True)
        rows = [f"{j.frame} {_row(j.pose)}\n" for j in jobs if j.sequence == seq]
        (root / "data_poses" / seq / "poses.txt").write_text("".join(rows))
    (root / "splits").mkdir()
    for split, seq in SEQUENCES.items():
        lines = [f"{seq} {j.frame}\n" for j in jobs if j.sequence == seq]
        (root / "splits" / f"{split}.txt").write_text("".join(lines))


@contextmanager
def _sigterm_raises() -> Iterator[None]:
    """While the block runs, SIGTERM raises ``Terminated`` in the main thread so that the cleanup runs as on
    Ctrl-C; a second SIGTERM during that cleanup is ignored. The previous handler comes back afterwards.
    A no-op off the main thread, and where SIGTERM is ignored or handled outside Python."""
    previous = signal.getsignal(signal.SIGTERM)
    if threading.current_thread() is not threading.main_thread() or previous in (signal.SIG_IGN, None):
        yield
        return
    fired = False

    def handler(signum, frame) -> None:
        nonlocal fired
        if not fired:
            fired = True
            raise Terminated

    signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _stop_pool(pool: ProcessPoolExecutor, timeout: float = 5.0) -> None:
    """Stop the workers now: queued jobs are cancelled, running ones are not waited for."""
    processes = list((pool._processes or {}).values())  # private, but the only handle on the workers
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        if process.is_alive():
            process.terminate()
    deadline = time.monotonic() + timeout
    for process in processes:
        process.join(max(0.0, deadline - time.monotonic()))
        if process.is_alive():
            process.kill()
            process.join(1.0)


def _render(jobs: list[Job], worker: _Worker, workers: int, initargs: tuple, bar: tqdm) -> None:
    if workers <= 1:
        for job in jobs:
            worker(job)
            bar.update()
        return
    pool = ProcessPoolExecutor(
        workers,
        mp_context=get_context("spawn"),
        initializer=_init_worker,
        initargs=(os.getpid(), *initargs),
    )
    try:
        for future in as_completed([pool.submit(_run_job, job) for job in jobs]):
            future.result()
            bar.update()
    except BaseException:
        _stop_pool(pool)
        raise
    pool.shutdown()


def _left_by_dead_run(folder: Path, pid: int) -> bool:
    """A temporary folder whose rendering run (on this machine) is gone; another machine's is kept."""
    try:
        host = (folder / OWNER).read_text().split()[0]
    except (OSError, IndexError):
        host = None  # killed before the owner file was written, or just before the rename
    return (host is None or host == socket.gethostname()) and not pid_alive(pid)


def _remove_stale(out: Path) -> None:
    """Remove the hidden ``.<name>.partial-<pid>`` / ``.<name>.old-<pid>`` folders of ``out`` left behind by
    an earlier run that was killed (SIGKILL, power loss): only those whose process is no longer alive."""
    if not out.parent.is_dir():
        return
    for entry in out.parent.iterdir():
        for kind in ("partial", "old"):
            prefix = f".{out.name}.{kind}-"
            pid = entry.name[len(prefix) :]
            if entry.name.startswith(prefix) and pid.isdigit() and int(pid) != os.getpid():
                if entry.is_dir() and _left_by_dead_run(entry, int(pid)):
                    shutil.rmtree(entry, ignore_errors=True)


def _move_into_place(tmp: Path, out: Path) -> None:
    if not out.exists():
        tmp.rename(out)
        return
    old = out.parent / f".{out.name}.old-{os.getpid()}"
    out.rename(old)
    tmp.rename(out)
    if old.is_dir():
        shutil.rmtree(old, ignore_errors=True)
    else:  # the CLI's --overwrite of a file
        old.unlink(missing_ok=True)


def _metadata(
    rig: Rig, world, ranges: dict[str, tuple[int, int]], params: dict, lidar: bool, agents: Traffic
) -> dict:
    """``synthetic.json``: ``params`` are the generation parameters (seed, rig, size, supersample, frames;
    scene and random_cameras where they differ from the street with fixed cameras)."""
    params = {k: v for k, v in params.items() if k not in UNWRITTEN or v != UNWRITTEN[k]}
    counts = {"boxes": len(world.boxes), "cylinders": len(world.cylinders), "spheres": len(world.spheres)}
    if world.scene == "indoor":
        described = {
            "room": world.room.tolist(),
            "walkway": world.walkway.tolist(),
            "light": world.sun.tolist(),
            "style": {k: np.asarray(v).tolist() for k, v in world.style.items()},
            **counts,
        }
    else:
        described = {"pitch": world.pitch, "sun": world.sun.tolist(), **counts}
        if agents.n_agents:
            described["agents"] = {k: agents.kind.count(k) for k in sorted(set(agents.kind))}
    return {
        "generator": f"fisheyedepth {__version__}",
        **params,
        "cameras": {name: cam.to_dict() for name, cam in rig.cameras.items()},
        "sequences": {
            split: {"name": SEQUENCES[split], "trajectory_frames": list(ranges[split])} for split in SPLITS
        },
        "world": described,
        "lidar": lidar,
    }


def generate(
    out: str | os.PathLike,
    rig: str = "kitti360",
    frames: int = 200,
    size: int = 256,
    seed: int = 0,
    supersample: int = 2,
    workers: int = 0,
    lidar: bool = True,
    overwrite: bool = False,
    progress: bool = True,
    lane: str = "right",
    scene: str = "street",
    random_cameras: bool = False,
    traffic: float = 0.0,
    effects=(),
) -> Path:
    """Render ``frames`` frames of every camera of ``rig`` (plus LiDAR) into ``out``. Returns ``out``.

    ``lane``: the car keeps to the "right" lane (KITTI-360: the right cameras see the near kerb,
    poles and facades) or the "left" one (the mirror situation, for per-camera comparisons).
    ``scene``: "street" (the city and the car) or "indoor" (a furnished room, a hand-held rig walking
    through it; ``lane`` does not apply). ``random_cameras``: every camera's model family, intrinsics,
    mounting height and tilt drawn from ``seed`` instead of the rig's own (``rig.random_camera``).
    ``traffic``: the density of moving cars and pedestrians (:mod:`.traffic`; 0: none, the world as
    before, bit for bit); with traffic, ``data_2d_moving`` holds each frame's mask of pixels that see a
    moving agent. ``effects``: names of :data:`.sensor.EFFECTS` (auto-exposure, white balance,
    vignetting, noise, motion blur), each a switch; none by default.

    ``overwrite`` replaces whatever ``out`` holds once the new dataset is complete (the CLI's explicit
    ``--overwrite``); ``ensure_dataset`` is the careful variant that replaces only what this generator made.
    SIGTERM or Ctrl-C stops the workers, removes the temporary folder and re-raises (``Terminated``).
    """
    check_options(locals(), GENERATE_OPTIONS)
    out = Path(out)
    if rig not in RIGS:
        raise ValueError(f"unknown rig {rig!r}; one of {RIGS}")
    if size < 16 or size % 8:
        raise ValueError(f"size must be a multiple of 8 and at least 16, got {size}")
    if lane not in LANES:
        raise ValueError(f"lane must be one of {LANES}, got {lane!r}")
    if scene not in SCENES:
        raise ValueError(f"scene must be one of {SCENES}, got {scene!r}")
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not overwrite:
        raise FileExistsError(f"{out} exists and is not empty; pass --overwrite to replace it")
    effects = check_effects(effects)
    ranges = split_frames(frames)
    n_trajectory = ranges["test"][1]
    world = make_scene_world(scene, seed)
    poses, agents = make_scene_motion(world, n_trajectory, seed, lane, traffic)
    jobs = [Job(SEQUENCES[s], i - a, poses[i], i) for s, (a, b) in ranges.items() for i in range(a, b)]

    out.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale(out)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    with _sigterm_raises():
        try:
            tmp.mkdir()
            (tmp / MARKER).write_text(MARKER_TEXT)
            (tmp / OWNER).write_text(f"{socket.gethostname()} {os.getpid()}\n")
            initargs = (
                *(tmp, seed, rig, size, supersample, lidar, scene, random_cameras),
                *(traffic, effects, lane, n_trajectory),
            )
            worker = _Worker(*initargs)
            masks = {name: r.body_mask for name, r in worker.cameras.items()}
            _write_layout(tmp, worker.rig, masks, jobs, lidar, agents.n_agents > 0)
            desc = f"rendering {rig} {size}px" if scene == "street" else f"rendering {scene} {rig} {size}px"
            with tqdm(total=len(jobs), desc=desc, unit="frame", disable=not progress) as bar:
                _render(jobs, worker, workers, initargs, bar)
            params = {
                "seed": seed,
                "rig": rig,
                "size": size,
                "supersample": supersample,
                "frames": frames,
                "lane": lane,
                "scene": scene,
                "random_cameras": random_cameras,
                "traffic": traffic,
                "effects": list(effects),
            }
            meta = _metadata(worker.rig, world, ranges, params, lidar, agents)
            (tmp / OWNER).unlink()
            (tmp / "synthetic.json").write_text(json.dumps(meta, indent=2) + "\n")
            _move_into_place(tmp, out)
        except BaseException as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise NoSpaceLeft(out, exc.filename) from exc
            raise
    return out


def is_complete(root: str | os.PathLike) -> bool:
    """A finished dataset has its ``synthetic.json`` (written last, before the atomic rename)."""
    return (Path(root) / "synthetic.json").is_file()


def made_by_generator(root: str | os.PathLike) -> bool:
    """``root`` was started by this generator: it holds the marker, or (older datasets) a fisheyedepth
    ``synthetic.json``. Such a folder may be rendered again; nothing else is ever replaced unasked."""
    root = Path(root)
    return (root / MARKER).is_file() or _generator_of(root).startswith("fisheyedepth")


def _generator_of(root: Path) -> str:
    try:
        meta = json.loads((root / "synthetic.json").read_text())
    except (OSError, ValueError):
        return ""
    return str(meta.get("generator", "")) if isinstance(meta, dict) else ""


def _is_empty_dir(root: Path) -> bool:
    return root.is_dir() and not any(root.iterdir())


def _refusal(root: Path) -> NotASyntheticDataset:
    what = "a file" if not root.is_dir() else f"a folder without synthetic.json or {MARKER}"
    return NotASyntheticDataset(
        f"{root} is not a synthetic dataset made by fisheyedepth ({what}), so it was left untouched. "
        "To train on your own data, choose its layout: data=kitti360 (KITTI-360 layout) or data=rig "
        f"(robot recording), e.g. `python train.py data=rig data.datamodule.root={root}`. To render the "
        "synthetic dataset, point data.datamodule.root at an absent or empty folder."
    )


def _check_parameters(root: Path, asked: dict) -> None:
    """A finished dataset is used only if it was rendered with the parameters asked for."""
    path = root / "synthetic.json"
    try:
        meta = json.loads(path.read_text())
    except ValueError as exc:
        raise DatasetMismatch(f"{path} is not valid JSON ({exc}); delete {root} to render it again") from exc
    if not isinstance(meta, dict) or not str(meta.get("generator", "")).startswith("fisheyedepth"):
        raise _refusal(root)
    meta = {**UNWRITTEN, **meta}
    differ = [f"{k} {meta[k]!r} (asked {asked[k]!r})" for k in CHECKED if k in meta and meta[k] != asked[k]]
    if differ:
        raise DatasetMismatch(
            f"{root} holds a synthetic dataset rendered with other parameters than asked: "
            f"{', '.join(differ)}. Ask for the same ones (data.generate.*), point data.datamodule.root at "
            f"another folder, or delete {root} to render it again."
        )


def ensure_dataset(
    root: str | os.PathLike,
    rig: str = "kitti360",
    frames: int = 200,
    size: int = 256,
    seed: int = 0,
    supersample: int = 2,
    workers: int = 0,
    lidar: bool = True,
    progress: bool = True,
    lane: str = "right",
    scene: str = "street",
    random_cameras: bool = False,
    traffic: float = 0.0,
    effects=(),
) -> Path:
    """The synthetic dataset at ``root``, rendered on first use (what ``train.py`` calls). Returns ``root``.

    A finished dataset is used as it is, if it was rendered with the same rig, frames, size, seed,
    supersample, lane, scene, camera randomisation, traffic and effects (``DatasetMismatch``
    otherwise). An absent or empty ``root`` is rendered; a folder that this generator started but that
    has no ``synthetic.json`` is rendered again. Anything else raises ``NotASyntheticDataset`` (a
    ``FileExistsError``) and is left untouched.
    """
    check_options(locals(), GENERATE_OPTIONS)
    root = Path(root)
    asked = {
        "rig": rig,
        "frames": frames,
        "size": size,
        "seed": seed,
        "supersample": supersample,
        "lane": lane,
        "scene": scene,
        "random_cameras": random_cameras,
        "traffic": traffic,
        "effects": list(check_effects(effects)),
    }
    if is_complete(root):
        _check_parameters(root, asked)
        return root
    if root.exists() and not _is_empty_dir(root) and not made_by_generator(root):
        raise _refusal(root)
    return generate(
        root,
        rig,
        frames,
        size,
        seed,
        supersample,
        workers,
        lidar,
        overwrite=root.exists(),
        progress=progress,
        lane=lane,
        scene=scene,
        random_cameras=random_cameras,
        traffic=traffic,
        effects=effects,
    )


def ensure_datasets(root, generate: dict, log=None) -> list[Path]:
    """:func:`ensure_dataset` for a data config: ``root`` one folder, or a list of folders (a mixed
    dataset); ``generate`` the config's ``data.generate`` mapping. With a list, ``generate["worlds"]``
    holds one mapping per folder, in the same order, whose keys replace the shared ones (``scene``,
    ``seed``, ...). Each folder is rendered on first use like a single one (its own progress bar, its own
    temporary folder renamed into place when complete). ``log``: a logger that names each folder it
    renders. Returns the folders. A parameter of the wrong kind or range is named as configured
    (``data.generate.traffic``), before anything is rendered."""
    check_options(generate, GENERATE_OPTIONS, "data.generate.")
    shared = {k: v for k, v in dict(generate).items() if k != "worlds"}
    worlds = generate.get("worlds")
    if isinstance(root, str | os.PathLike):
        if worlds:
            raise ValueError(
                "data.generate.worlds: one mapping per folder needs data.datamodule.root as a list"
            )
        jobs = [(Path(root), shared)]
    else:
        roots = [Path(r) for r in root]
        if not worlds or len(worlds) != len(roots):
            raise ValueError(
                f"data.datamodule.root lists {len(roots)} folders, so data.generate.worlds needs one mapping "
                f"per folder, in the same order; it has {len(worlds or [])}"
            )
        if len(set(roots)) != len(roots):
            raise ValueError(f"data.datamodule.root names a folder twice: {[str(r) for r in roots]}")
        jobs = [(r, {**shared, **dict(w)}) for r, w in zip(roots, worlds, strict=True)]
    for folder, params in jobs:
        if log is not None and not is_complete(folder):
            log.info("rendering the synthetic dataset into %s (first use)", folder)
        ensure_dataset(folder, **params)
    return [folder for folder, _ in jobs]
