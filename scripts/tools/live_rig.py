#!/usr/bin/env python
"""A rig recording replayed as if live: per instant, every camera's image goes through the multi-view live
API (:class:`fisheyedepth.stereo.RigStereo`: the rig's overlapping pairs, and each camera against its own
image of an earlier instant at least ``min_baseline`` away by odometry), the instants per second are
printed as they go, and each instant is written to a Rerun recording (:mod:`fisheyedepth.rerun3d`; the
``kept`` and ``filled`` maps: the fused distance the checks keep, and the dense one).

    python scripts/tools/live_rig.py RIG --out OUT/recording.rrd [--threads 2] [--max-instants N]
        [--min-distance 0.3] [--max-distance 80] [--points 100000] [--no-record] [--overwrite]
        [--foxglove [PORT]] [--bag-out BAG.mcap]
    rerun OUT/recording.rrd

``--foxglove [PORT]`` (default 8765) serves every instant as it is computed to Foxglove on
``ws://127.0.0.1:PORT`` (:class:`fisheyedepth.rosout.foxglove.FoxgloveLive`); ``--bag-out`` writes the same
as a ROS 2 bag or MCAP file (:class:`fisheyedepth.rosout.BagRecorder`), put in place when the replay ends.

RIG: a rig layout (docs/data-format.md), or a Project Aria export such as ``realdata/aria_gen2_rig``
(converted into the rig layout in a temporary folder first, by ``fisheyedepth-import-aria``'s function).
An instant is an image of the first camera; another camera takes part with its image nearest in time,
within half the first camera's median frame interval; a camera without one at some instant is left out
(named). The body's pose is the odometry at the first camera's image.

Ctrl-C (exit 130) or SIGTERM (143) stops the replay: the recording keeps the instants finished (it is
closed and valid), or nothing is written where none was; the Aria conversion's temporary folder is removed
either way.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import sys
import tempfile
import time
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

from fisheyedepth.cli import CommandParser
from fisheyedepth.data.layouts import RigLayout
from fisheyedepth.files import check_apart, pid_alive
from fisheyedepth.images import read_image
from fisheyedepth.signals import Terminated, sigterm_raises, stopped_by
from fisheyedepth.stereo import RigStereo, SgbmSettings
from fisheyedepth.utils import check_threads

HISTORY = 10  # earlier instants kept for the motion partner (the latest one far enough away is taken)


class Instant(NamedTuple):
    index: int
    time_ns: int
    body_to_world: np.ndarray  # 4x4
    images: dict[str, Path]  # camera -> image file


CONVERSION = "fisheyedepth-live-rig-"  # + <pid>-<random>: an Aria export converted, in the temp folder


def remove_stale_conversions() -> list[Path]:
    """The conversions that runs killed outright (SIGKILL) left in the temporary folder, removed: a live
    run's are kept (its pid is in the name)."""
    removed = []
    for folder in sorted(Path(tempfile.gettempdir()).glob(f"{CONVERSION}*")):
        pid = folder.name[len(CONVERSION) :].split("-")[0]
        if folder.is_dir() and pid.isdigit() and not pid_alive(int(pid)):
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(folder)
    return removed


@contextlib.contextmanager
def rig_layout(path: Path) -> Iterator[RigLayout]:
    """``path`` as a :class:`RigLayout`; a Project Aria export is converted into one first (removed after,
    and by the next run where a kill left it)."""
    remove_stale_conversions()
    if (path / "rig.yaml").is_file():
        yield RigLayout(path)
        return
    from fisheyedepth.data.aria import aria_to_rig

    with tempfile.TemporaryDirectory(prefix=f"{CONVERSION}{os.getpid()}-") as tmp:
        aria_to_rig(path, Path(tmp) / "rig")
        yield RigLayout(Path(tmp) / "rig")


def instants(layout: RigLayout, sequence: str) -> tuple[list[Instant], list[str]]:
    """The instants of ``sequence`` (module docstring) and the cameras left out."""
    names = list(layout.cameras)
    frames = {n: layout.frames(sequence, n) for n in names}
    first = frames[names[0]]
    stamps = np.array([f.key for f in first], dtype=np.int64)
    tolerance = int(np.median(np.diff(stamps)) // 2) if len(stamps) > 1 else 0
    chosen: dict[str, list] = {}
    for name in names:
        keys = np.array([f.key for f in frames[name]], dtype=np.int64)
        nearest = [int(np.abs(keys - t).argmin()) for t in stamps]
        if all(abs(int(keys[j]) - int(t)) <= tolerance for j, t in zip(nearest, stamps, strict=True)):
            chosen[name] = [frames[name][j] for j in nearest]
    left_out = [n for n in names if n not in chosen]
    found = [
        Instant(i, int(f.key), f.pose, {n: layout.image(sequence, n, chosen[n][i]) for n in chosen})
        for i, f in enumerate(first)
    ]
    return found, left_out


def body_masks(layout: RigLayout, cameras: list[str]) -> dict[str, np.ndarray]:
    """The named cameras' body masks (True: the scene), read and checked as ``fisheyedepth-multiview``
    reads them; a camera without one is not named."""
    masks = {name: layout.read_mask(name) for name in cameras}
    return {name: mask for name, mask in masks.items() if mask is not None}


def earlier_partner(history: deque, pose: np.ndarray, min_baseline: float):
    """The latest ``(images, pose)`` of ``history`` at least ``min_baseline`` metres from ``pose``."""
    for images, then in reversed(history):
        if np.linalg.norm(then[:3, 3] - pose[:3, 3]) >= min_baseline:
            return images, then
    return None, None


def rgb(bgr: np.ndarray) -> np.ndarray:
    return bgr if bgr.ndim == 2 else np.ascontiguousarray(bgr[..., ::-1])


def maps(result) -> dict[str, np.ndarray]:
    """The maps recorded of a camera's result: what the checks keep, and the dense fill."""
    return {"kept": result.fused.distance, "filled": result.fused.dense}


def replay(layout: RigLayout, stereo: RigStereo, found: list[Instant], recorder=None, quiet: bool = False,
           sinks=()):  # fmt: skip
    """Every instant of ``found`` through ``stereo`` (and into ``recorder``, a
    :class:`~fisheyedepth.rerun3d.RigRecorder`, when given, and each of ``sinks``, a bag or a Foxglove
    server: ``add(camera, stamp, image, distance, confidence, body_to_world)``), yielding
    ``(instant, results, seconds)``:
    the cameras' :class:`~fisheyedepth.stereo.pipeline.CameraResult` and the seconds the instant took
    (reading, stereo and recording)."""
    from fisheyedepth.rerun3d import CameraView

    history: deque = deque(maxlen=HISTORY)
    start = time.perf_counter()
    for done, instant in enumerate(found, start=1):
        began = time.perf_counter()
        images = {n: read_image(p).bgr for n, p in instant.images.items()}
        previous, then = earlier_partner(history, instant.body_to_world, stereo.settings.min_baseline)
        motion = None if then is None else np.linalg.inv(then) @ instant.body_to_world
        results = stereo(images, previous, motion)
        history.append((images, instant.body_to_world))
        if recorder is not None:
            views = {n: CameraView(stereo.cameras[n], rgb(images[n]), maps(r)) for n, r in results.items()}
            recorder.instant(instant.time_ns, instant.index, views, instant.body_to_world)
        for sink in sinks:
            for name, r in results.items():
                sink.add(name, instant.time_ns, images[name], r.fused.distance, r.fused.confidence,
                         instant.body_to_world)  # fmt: skip
        seconds = time.perf_counter() - began
        yield instant, results, seconds  # counted as finished before it is announced
        if not quiet:
            partners = sum(len(r.partners) for r in results.values())
            print(
                f"instant {done}/{len(found)}: {seconds:.2f} s, {partners} partner maps, "
                f"{done / (time.perf_counter() - start):.2f} instants/s so far",
                flush=True,
            )


def main(argv=None) -> int:
    parser = CommandParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("rig", type=Path)
    parser.add_argument("--out", type=Path, default=Path("recording.rrd"), help="default: %(default)s")
    parser.add_argument("--sequence", default=None, help="default: the first")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--max-instants", type=int, default=None)
    parser.add_argument("--min-distance", type=float, default=0.3)
    parser.add_argument("--max-distance", type=float, default=80.0)
    parser.add_argument("--points", type=int, default=100_000, help="points per image and map at most")
    parser.add_argument("--no-record", action="store_true", help="stereo only, no recording")
    parser.add_argument("--foxglove", type=int, nargs="?", const=8765, metavar="PORT",
                        help="serve the instants on ws://127.0.0.1:PORT (default 8765)")  # fmt: skip
    parser.add_argument("--bag-out", type=Path, help="also a ROS 2 bag (a folder) or an .mcap file")
    parser.add_argument("--overwrite", action="store_true")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    try:
        for option in ("points", "max_instants"):
            value = getattr(args, option)
            if value is not None and value < 1:
                raise ValueError(f"--{option.replace('_', '-')}: {value}; at least 1")
        check_threads(args.threads, "--threads")
        if not args.no_record:
            check_apart(args.out, "--out", {"the rig recording": args.rig})
        if args.foxglove is not None and not 0 <= args.foxglove <= 65535:
            raise ValueError(f"--foxglove: port {args.foxglove}; 0 (any free one) to 65535")
        if args.bag_out is not None:
            from fisheyedepth.rosout import check_bag_out

            check_apart(args.bag_out, "--bag-out", {"the rig recording": args.rig})
            check_bag_out(args.bag_out, args.overwrite)
        with sigterm_raises():
            summary = run(args)
    except (OSError, ValueError, ImportError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except (Terminated, KeyboardInterrupt) as stop:  # before the first instant: nothing recorded
        why, status = stopped_by(stop)
        print(f"error: {why} before any instant was finished; nothing recorded", file=sys.stderr)
        return status
    if summary["stopped"] is not None:
        stop = summary["stopped"]
        why, status = stopped_by(stop)
        kept = f"; {args.out} keeps them" if not args.no_record else ""
        print(f"error: {why} after {summary['instants']} instants{kept}", file=sys.stderr)
        return status
    print(
        f"{summary['instants']} instants in {summary['seconds']:.1f} s: {summary['fps']:.2f} instants/s"
        + (f"; recording {args.out}" if not args.no_record else "")
    )
    return 0


def run(args) -> dict:
    """What :func:`main` does with its parsed ``args``; the instants, seconds and instants per second."""
    settings = SgbmSettings(min_distance=args.min_distance, max_distance=args.max_distance)
    with rig_layout(args.rig) as layout:
        sequence = args.sequence or layout.sequences()[0]
        found, left_out = instants(layout, sequence)
        if left_out:
            print(f"left out (no image at every instant): {', '.join(left_out)}", file=sys.stderr)
        found = found[: args.max_instants]
        names = list(found[0].images) if found else []
        if len(names) < 2:
            raise ValueError(f"{args.rig}: {len(names)} camera(s) with an image at every instant; 2 needed")
        cameras = {n: layout.cameras[n].camera for n in names}
        extrinsics = {n: layout.cameras[n].cam_to_body for n in names}
        stereo = RigStereo(cameras, extrinsics, settings, args.threads, body_masks(layout, names))
        with contextlib.ExitStack() as stack:
            recorder = None
            if not args.no_record:
                from fisheyedepth.rerun3d import RigRecorder

                recorder = stack.enter_context(
                    RigRecorder(args.out, "fisheyedepth-live-rig", args.points, args.overwrite)
                )
                recorder.rig(extrinsics)
            sinks = ros_sinks(args, stack, layout, cameras, extrinsics)
            seconds, stopped = [], None
            try:
                for _, _, s in replay(layout, stereo, found, recorder, args.quiet, sinks):
                    seconds.append(s)
            except (Terminated, KeyboardInterrupt) as stop:  # the instants finished are kept
                if not seconds:
                    raise
                stopped = stop
    total = sum(seconds)
    return {"instants": len(seconds), "seconds": total, "fps": len(seconds) / total if total else 0.0,
            "stopped": stopped}  # fmt: skip


def ros_sinks(args, stack: contextlib.ExitStack, layout: RigLayout, cameras: dict, extrinsics: dict) -> list:
    """The ROS tools' ends of the replay: a bag (``--bag-out``) and a Foxglove server (``--foxglove``), each
    closed by ``stack`` (the bag put in place, also after a stop: it keeps the instants finished)."""
    sinks = []
    names = {"image_topics": layout.topics, "frame_ids": layout.frame_ids}
    if args.bag_out is not None:
        from fisheyedepth.rosout import BagRecorder, BagWriter

        writer = stack.enter_context(BagWriter(args.bag_out, args.overwrite))
        sinks.append(BagRecorder(writer, cameras, extrinsics, **names))
    if args.foxglove is not None:
        from fisheyedepth.rosout.foxglove import FoxgloveLive

        live = stack.enter_context(FoxgloveLive(cameras, extrinsics, port=args.foxglove, **names))
        print(f"serving to Foxglove on ws://127.0.0.1:{live.port}", file=sys.stderr, flush=True)
        sinks.append(live)
    return sinks


if __name__ == "__main__":
    raise SystemExit(main())
