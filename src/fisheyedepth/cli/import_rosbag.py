"""``fisheyedepth-import-rosbag BAG --out OUT --camera NAME=TOPIC ... --odometry TOPIC``: a ROS 1 or ROS 2
bag into the rig layout, all or nothing (:mod:`fisheyedepth.data.rosbag`)."""

from __future__ import annotations

import logging
from pathlib import Path

import yaml

from ..cameras import load_yaml
from ..data.layouts import read_transform
from ..data.rosbag import RosbagError, import_rosbag
from ..files import check_apart
from ..signals import run_import
from . import CommandParser, named_values


def main(argv=None) -> int:
    """Console script ``fisheyedepth-import-rosbag``."""
    parser = CommandParser(
        description="Import a ROS 1 or ROS 2 bag into the rig layout (docs/data-format.md).",
        epilog="example: fisheyedepth-import-rosbag run.bag --out data/my_rig "
        "--camera front=/front/image_raw --camera left=/left/image_raw/compressed --odometry /odom",
    )
    parser.add_argument("bag", type=Path, help="a ROS 1 .bag, or a ROS 2 bag folder (.db3 or .mcap)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--camera", action="append", required=True, metavar="NAME=IMAGE_TOPIC")
    parser.add_argument(
        "--camera-info", action="append", metavar="NAME=TOPIC", help="default: <ns>/camera_info"
    )
    parser.add_argument("--calibration", action="append", metavar="NAME=FILE", help="instead of CameraInfo")
    parser.add_argument(
        "--extrinsics", type=Path, help="YAML {NAME: 4x4 camera->body}, instead of /tf_static"
    )
    poses = parser.add_mutually_exclusive_group(required=True)
    poses.add_argument("--odometry", metavar="TOPIC", help="nav_msgs/Odometry poses of the body")
    poses.add_argument("--tf-poses", nargs=2, metavar=("WORLD", "BODY"), help="body poses from /tf")
    parser.add_argument("--body-frame", help="default: the odometry's child_frame_id (or BODY)")
    parser.add_argument("--sequence", default="seq0")
    parser.add_argument("--overwrite", action="store_true")
    parser.add_argument(
        "--max-pose-gap", type=float, metavar="SECONDS",
        help="drop images in a longer gap of the poses (default: 5 median pose intervals)",
    )  # fmt: skip
    parser.add_argument(
        "--bit-depth", type=int, metavar="BITS",
        help="bits of data in 16-bit images, scaled to the full range (default: detected per topic)",
    )  # fmt: skip
    parser.add_argument("--strict", action="store_true", help="refuse a corrupt image instead of skipping it")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s: %(message)s")

    def convert():
        check_apart(args.out, "--out", {"the bag": args.bag})
        extrinsics = {}
        if args.extrinsics:
            data = load_yaml(args.extrinsics.read_text(), args.extrinsics)  # safe, and names the file
            if not isinstance(data, dict):
                raise ValueError(f"{args.extrinsics}: expected a mapping NAME: 4x4 camera -> body")
            extrinsics = {k: read_transform(v, args.extrinsics, k) for k, v in data.items()}
        return import_rosbag(
            args.bag, args.out, named_values(args.camera, "--camera"),
            named_values(args.camera_info, "--camera-info"),
            named_values(args.calibration, "--calibration"),
            extrinsics, args.odometry, tuple(args.tf_poses) if args.tf_poses else None,
            args.body_frame, args.sequence, args.overwrite, args.max_pose_gap, args.bit_depth,
            args.strict,
        )  # fmt: skip

    errors = (RosbagError, FileExistsError, FileNotFoundError, ValueError, yaml.YAMLError)
    return run_import(convert, args.out, errors)
