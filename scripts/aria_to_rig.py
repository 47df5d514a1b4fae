#!/usr/bin/env python
"""Convert a Project Aria export (Fisheye624 calibration JSON, VIO poses CSV, one image folder per
camera) into the robot-rig layout that ``train.py data=rig`` reads.

    python scripts/aria_to_rig.py --src ../shared/realdata/aria_gen2_rig --out data/aria_gen2_rig
        [--overwrite]
    RIG_ROOT=data/aria_gen2_rig python train.py data=rig ...

An export the rig layout would refuse once converted (a camera whose model gives no pixel a ray, a size
that is not whole pixels, two images with one capture time, ...) is refused with one line naming the file,
and nothing is written.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from fisheyedepth.data.aria import aria_to_rig


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--src", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--sequence", default="seq0")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    try:
        summary = aria_to_rig(args.src, args.out, args.sequence, args.overwrite)
    except (OSError, ValueError) as err:  # CalibrationError and ImageError are ValueErrors
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
