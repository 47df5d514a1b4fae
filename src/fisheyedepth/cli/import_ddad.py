"""``fisheyedepth-import-ddad --src SCENE --out OUT``: a DDAD scene into the rig layout, its LiDAR projected
into each camera as ground truth (:mod:`fisheyedepth.data.ddad`)."""

from __future__ import annotations

import argparse
import inspect
from pathlib import Path

from ..data.ddad import ddad_to_rig
from ..files import check_apart
from ..signals import run_import
from . import CommandParser, named_values


def main(argv=None) -> int:
    """Convert a DDAD scene (TRI's dgp scene format: scene_*.json, calibration/*.json, the images and the
    LiDAR sweeps) into the robot-rig layout that ``train.py data=rig`` reads, each sweep projected into
    each camera as ground-truth distance.

        fisheyedepth-import-ddad --src ../shared/realdata/ddad_scene01 --out data/ddad_scene01
            [--cameras CAMERA_01 CAMERA_05] [--lidar LIDAR] [--mask CAMERA_05=mask05.png] [--overwrite]
        RIG_ROOT=data/ddad_scene01 python train.py data=rig ...

    A scene the rig layout would refuse once converted (a quaternion that is not a unit one, names and
    intrinsics of different counts, an image of another size than its datum says, ...) is refused with one
    line naming the file and the field, and nothing is written.
    """
    parser = CommandParser(
        prog="fisheyedepth-import-ddad",
        description=inspect.cleandoc(main.__doc__ or ""),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--src", type=Path, required=True, help="a DDAD scene folder or its scene_*.json")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--sequence", default="seq0")
    parser.add_argument("--cameras", nargs="+", help="default: every camera of the scene")
    parser.add_argument("--lidar", help="the point cloud of the ground truth (default: the scene's only one)")
    parser.add_argument("--mask", action="append", metavar="CAMERA=FILE", help="a body mask, 255 = usable")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)

    def convert():
        masks = {k: Path(v) for k, v in named_values(args.mask, "--mask", "CAMERA=FILE").items()}
        check_apart(args.out, "--out", {"the DDAD scene": args.src})
        return ddad_to_rig(args.src, args.out, args.sequence, args.cameras, args.lidar, masks, args.overwrite)

    return run_import(convert, args.out)
