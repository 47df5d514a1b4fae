"""``fisheyedepth-import-rosbag BAG --out OUT --camera NAME=TOPIC ... --odometry TOPIC``: a ROS 1 or ROS 2
bag into the rig layout, all or nothing (:mod:`fisheyedepth.data.rosbag`)."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from pathlib import Path

import yaml

from ..cameras import load_yaml
from ..data.layouts import read_transform
from ..data.rosbag import RosbagError, import_rosbag, imported, is_bag
from ..files import check_apart
from ..signals import run_import
from . import CommandParser, named_values


def add_bag_options(parser, poses_required: bool = True) -> None:
    """The import's options (what a bag holds and where), shared by ``fisheyedepth-multiview BAG``."""
    parser.add_argument("--camera", action="append", metavar="NAME=IMAGE_TOPIC", required=poses_required)
    parser.add_argument(
        "--camera-info", action="append", metavar="NAME=TOPIC", help="default: <ns>/camera_info"
    )
    parser.add_argument("--calibration", action="append", metavar="NAME=FILE", help="instead of CameraInfo")
    parser.add_argument(
        "--extrinsics", type=Path, help="YAML {NAME: 4x4 camera->body}, instead of /tf_static"
    )
    poses = parser.add_mutually_exclusive_group(required=poses_required)
    poses.add_argument("--odometry", metavar="TOPIC", help="nav_msgs/Odometry poses of the body")
    poses.add_argument("--tf-poses", nargs=2, metavar=("WORLD", "BODY"), help="body poses from /tf")
    parser.add_argument("--body-frame", help="default: the odometry's child_frame_id (or BODY)")
    parser.add_argument("--sequence", default="seq0")
    parser.add_argument(
        "--max-pose-gap", type=float, metavar="SECONDS",
        help="drop images in a longer gap of the poses (default: 5 median pose intervals)",
    )  # fmt: skip
    parser.add_argument(
        "--bit-depth", type=int, metavar="BITS",
        help="bits of data in 16-bit images, scaled to the full range (default: detected per topic)",
    )  # fmt: skip
    parser.add_argument("--strict", action="store_true", help="refuse a corrupt image instead of skipping it")


def bag_import(args) -> dict:
    """:func:`~fisheyedepth.data.rosbag.import_rosbag`'s keyword arguments from :func:`add_bag_options`'
    options, each checked and named."""
    extrinsics = {}
    if args.extrinsics:
        data = load_yaml(args.extrinsics.read_text(), args.extrinsics)  # safe, and names the file
        if not isinstance(data, dict):
            raise ValueError(f"{args.extrinsics}: expected a mapping NAME: 4x4 camera -> body")
        extrinsics = {k: read_transform(v, args.extrinsics, k) for k, v in data.items()}
    return {
        "cameras": named_values(args.camera, "--camera"),
        "info_topics": named_values(args.camera_info, "--camera-info"),
        "calibrations": named_values(args.calibration, "--calibration"),
        "extrinsics": extrinsics,
        "odometry": args.odometry,
        "tf_poses": tuple(args.tf_poses) if args.tf_poses else None,
        "body_frame": args.body_frame,
        "sequence": args.sequence,
        "max_pose_gap": args.max_pose_gap,
        "bit_depth": args.bit_depth,
        "strict": args.strict,
    }


IMPORT_OPTIONS = ("camera", "camera_info", "calibration", "extrinsics", "odometry", "tf_poses", "body_frame",
                  "max_pose_gap", "bit_depth")  # fmt: skip


@contextlib.contextmanager
def recording_of(args, out: Path) -> Iterator[Path]:
    """The rig folder a command reads: ``args.root`` itself, or, where it is a ROS bag (:func:`is_bag`),
    the bag imported with :func:`add_bag_options`' options into a hidden folder beside ``out``, removed
    when the block ends. An import option given with a rig folder is refused, not ignored."""
    root = Path(args.root)
    if not is_bag(root):
        given = [f"--{o.replace('_', '-')}" for o in IMPORT_OPTIONS if getattr(args, o)]
        if given:
            raise ValueError(f"{', '.join(given)}: options of a ROS bag given as {root}, which is no bag")
        yield root
        return
    if not args.camera or not (args.odometry or args.tf_poses):
        raise ValueError(f"{root}: a ROS bag; name its cameras and poses as for fisheyedepth-import-rosbag "
                         "(--camera NAME=TOPIC ..., --odometry TOPIC or --tf-poses WORLD BODY)")  # fmt: skip
    check_apart(out, "--out", {"the bag": root})
    with imported(root, out, **bag_import(args)) as rig:
        yield rig


def main(argv=None) -> int:
    """Console script ``fisheyedepth-import-rosbag``."""
    parser = CommandParser(
        description="Import a ROS 1 or ROS 2 bag into the rig layout (docs/data-format.md).",
        epilog="example: fisheyedepth-import-rosbag run.bag --out data/my_rig "
        "--camera front=/front/image_raw --camera left=/left/image_raw/compressed --odometry /odom",
    )
    parser.add_argument("bag", type=Path, help="a ROS 1 .bag, a ROS 2 bag folder (.db3 or .mcap), an .mcap")
    parser.add_argument("--out", type=Path, required=True)
    add_bag_options(parser)
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s: %(message)s")

    def convert():
        check_apart(args.out, "--out", {"the bag": args.bag})
        return import_rosbag(args.bag, args.out, overwrite=args.overwrite, **bag_import(args))

    errors = (RosbagError, FileExistsError, FileNotFoundError, ValueError, yaml.YAMLError)
    return run_import(convert, args.out, errors)
