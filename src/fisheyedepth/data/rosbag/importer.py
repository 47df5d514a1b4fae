"""One bag imported, all or nothing: :func:`import_rosbag`; for a command that reads a bag directly, into a
folder removed after it (:func:`imported`)."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ...files import inside, move_into_place, staged_folder
from .index import index_bag, plan_cameras
from .messages import RosbagError
from .options import BagImport
from .write import write_import


def import_rosbag(
    bag: str | os.PathLike,
    out: str | os.PathLike,
    cameras: dict[str, str],
    info_topics: dict[str, str] | None = None,
    calibrations: dict[str, str | os.PathLike] | None = None,
    extrinsics: dict[str, Any] | None = None,
    odometry: str | None = None,
    tf_poses: tuple[str, str] | None = None,
    body_frame: str | None = None,
    sequence: str = "seq0",
    overwrite: bool = False,
    max_pose_gap: float | None = None,
    bit_depth: int | None = None,
    strict: bool = False,
) -> dict[str, Any]:
    """Import ``bag`` into the rig layout at ``out`` (the package docstring); returns a summary.

    ``cameras``: name -> image topic. ``info_topics``: name -> CameraInfo topic (default: the image
    topic's namespace + ``/camera_info``). ``calibrations``/``extrinsics``: given per camera instead of
    the bag's (``extrinsics`` values: 4x4 camera -> body). Poses from ``odometry`` (a topic) or
    ``tf_poses`` (world frame, body frame); ``body_frame`` defaults to the odometry's child frame.
    ``max_pose_gap``: seconds; images in a longer gap of the poses are dropped (default: ``GAP_FACTOR``
    median pose intervals; a given value is written to ``rig.yaml`` so that training drops the same).
    ``bit_depth``: the bits of data in 16-bit images (default: the highest set bit over each topic).
    ``strict``: a corrupt image message stops the import instead of being skipped and counted.

    Two passes over the bag: the first (:mod:`.index`) reads poses, calibrations, stamps, extrinsics and
    16-bit peaks and checks every camera, so most problems stop the import before an image is decoded;
    the second (:mod:`.write`) streams the images to disk one at a time. ``overwrite`` replaces
    ``rig.yaml``, the cameras' calibration files and the sequence's folder; other files of ``out`` stay."""
    job = BagImport(bag, cameras, info_topics, calibrations, extrinsics, odometry, tf_poses, body_frame,
                    sequence, max_pose_gap, bit_depth, strict)  # fmt: skip
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out} exists and is not a folder")
    parts = [Path(sequence), *(Path("calibration") / f"{name}.yaml" for name in cameras), Path("rig.yaml")]
    for part in reversed(parts):  # rig.yaml first: the clash that says "this is a rig already"
        if os.path.lexists(inside(out, out / part, "--out")) and not overwrite:
            raise FileExistsError(f"{out / part} exists; pass overwrite=True (--overwrite) to replace it")
    with staged_folder(out, "importing") as staging:
        try:
            found = index_bag(job)
            summary = write_import(found, plan_cameras(found), staging)
            move_into_place(staging, out, parts, overwrite)  # rig.yaml last: a rig is complete with it
        except RosbagError as err:  # named by the bag, and by the path the file would have had
            message = str(err).replace(str(staging), str(out))
            raise RosbagError(message if str(job.bag) in message else f"{job.bag}: {message}") from None
    summary["out"] = str(out)
    return summary


def is_bag(path: str | os.PathLike) -> bool:
    """``path`` is a ROS bag: a ROS 1 ``.bag``, an ``.mcap`` or ``.db3`` file, or a ROS 2 bag folder
    (``metadata.yaml`` in it)."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix in (".bag", ".mcap", ".db3") and path.is_file()


@contextlib.contextmanager
def imported(bag: str | os.PathLike, beside: str | os.PathLike, **options) -> Iterator[Path]:
    """``bag`` imported (:func:`import_rosbag` with ``options``) into a hidden rig folder beside
    ``beside`` (on its disk), removed when the block ends however it ends: a command reads the bag as it
    reads a rig folder, and the user has no folder to manage."""
    beside = Path(beside)
    beside.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=beside.parent, prefix=f".{beside.name}.bag-import-"))
    try:
        import_rosbag(bag, tmp / "rig", **options)
        yield tmp / "rig"
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
