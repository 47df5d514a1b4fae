"""``fisheyedepth-import-aria --src EXPORT --out OUT``: a Project Aria export into the rig layout
(:mod:`fisheyedepth.data.aria`)."""

from __future__ import annotations

import argparse
import inspect
from pathlib import Path

from ..data.aria import aria_to_rig
from ..files import check_apart
from ..signals import run_import
from . import CommandParser


def main(argv=None) -> int:
    """Convert a Project Aria export (Fisheye624 calibration JSON, VIO poses CSV, one image folder per
    camera) into the robot-rig layout that ``train.py data=rig`` reads.

        fisheyedepth-import-aria --src ../shared/realdata/aria_gen2_rig --out data/aria_gen2_rig
            [--overwrite]
        RIG_ROOT=data/aria_gen2_rig python train.py data=rig ...

    An export the rig layout would refuse once converted (a camera whose model gives no pixel a ray, a size
    that is not whole pixels, two images with one capture time, ...) is refused with one line naming the
    file, and nothing is written.
    """
    parser = CommandParser(
        prog="fisheyedepth-import-aria",
        description=inspect.cleandoc(main.__doc__ or ""),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--src", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--sequence", default="seq0")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)

    def convert():
        check_apart(args.out, "--out", {"the Aria export": args.src})
        return aria_to_rig(args.src, args.out, args.sequence, args.overwrite)

    return run_import(convert, args.out)
