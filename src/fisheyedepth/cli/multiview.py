"""``fisheyedepth-multiview ROOT --out OUT [--refine] [--sources rig,time] [--matcher sgbm|sweep]``: metric
distance from geometry over a recording in the rig layout (docs/data-format.md, "Robot rig layout"), or
over a ROS bag with the import's options (``--camera NAME=TOPIC ... --odometry TOPIC``, imported into a
folder beside ``OUT`` and removed after the run):
every image paired with the rig's other cameras at the same instant (``rig``) and with its own camera's
previous and next images that moved far enough (``time``, the odometry's motion), metric because the
calibration and the odometry are.

The matcher: ``sgbm`` (default) rectifies each pair on the sphere and matches it with OpenCV's
semi-global block matcher (:mod:`fisheyedepth.stereo.pipeline`): every pair once, both of its images
answered, every partner of an image fused; ``sweep`` sweeps distance hypotheses over all partners at once
(:mod:`fisheyedepth.stereo.sweep`, on CUDA where there is one: a hundred times slower on a CPU).

For each image it can pair it writes, under ``OUT/<sequence>/``:
- ``distance/<camera>/<timestamp_ns>.npy``: float32 H x W metres along the ray, 0 where no partner's
  checks keep the pixel;
- ``dense/<camera>/<timestamp_ns>.npy``: the filled map (every pixel a partner could match);
- ``confidence/<camera>/<timestamp_ns>.npy``: float32 in [0, 1] of the kept pixels;
- ``panels/<camera>/<timestamp_ns>.png``: image | checked | filled [| ground truth];
with ``--bag-out BAG``, the same as ROS 2 messages (distance, confidence, camera info, points, tf) in
``BAG``; with ``--refine``, ``OUT/rig.yaml``: the recording's rig.yaml with the refined ``cam_to_body`` (what
changed, and the epipolar error before and after, in the summary); and ``OUT/summary.json``: per image
its partners, its seconds and, where the folder has ground truth (``<sequence>/distance/<camera>/
<timestamp_ns>.npy``), abs_rel, a1, coverage and the constant map on the same scored pixels, and the
share of its pixels too flat to match (``flat``); the seconds of each stage; every image left out, by
name, with why (no partner, outside the poses, in a gap of the poses, a file name that is no timestamp);
the pairs left out (no overlap within the range, too short a baseline, one centre), by name; and the
images that kept no pixel. ``OUT`` is checked before any work (a folder of its own, writable, none of
these files there unless ``--overwrite``, no other run writing into it), and so is every input the run
reads (images, ground truth) and the memory its largest image needs; the files are written beside ``OUT``
and moved into place when the run completes. Exit status: 0, 2 for a refused input (one ``error:`` line),
1 when the run completed but no image kept a pixel.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
from pathlib import Path

import cv2
import torch

from ..files import WRITE_ERRORS
from ..signals import Terminated, sigterm_raises, stopped_by
from ..stereo.matchers import MATCHERS
from ..stereo.pipeline import SgbmSettings
from ..stereo.recording import RECORDING, run
from ..stereo.refine import REFINE
from ..stereo.sgbm import SgbmMatcher
from ..stereo.sweep import SweepMatcher, SweepSettings
from ..utils import check_threads
from . import CommandParser
from .import_rosbag import add_bag_options, recording_of


def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="fisheyedepth-multiview", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    parser.add_argument("root", type=Path, help="a recording in the rig layout, or a ROS bag (its import's "
                        "options: fisheyedepth-import-rosbag)")  # fmt: skip
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--sources", default="rig,time", help="rig, time, or both (default)")
    parser.add_argument("--matcher", choices=MATCHERS, default="sgbm")
    parser.add_argument("--min-distance", type=float, default=0.3, help="metres (default 0.3)")
    parser.add_argument("--max-distance", type=float, default=80.0, help="metres (default 80)")
    parser.add_argument("--resolution", type=float, default=None,
                        help="degrees per rectified pixel (default: each pair's coarser camera)")  # fmt: skip
    parser.add_argument("--min-confidence", type=float, default=None,
                        help="--matcher sgbm: the least confidence a kept pixel needs (default 0: every "
                        "pixel the checks keep; docs/inference.md says what each level keeps)")  # fmt: skip
    parser.add_argument("--threads", type=int, default=None, help="CPU threads (default: all)")
    parser.add_argument("--hypotheses", type=int, default=None, help="--matcher sweep: distances (128)")
    parser.add_argument("--cost", choices=("zncc", "census"), default=None, help="--matcher sweep (zncc)")
    parser.add_argument("--max-images", type=int, default=None)
    refine_help = "refine the rig's extrinsics from its images first (rotation, the default, or pose: also "
    refine_help += "the translation's direction); writes OUT/rig.yaml"
    parser.add_argument("--refine", nargs="?", const="rotation", choices=REFINE, help=refine_help)
    parser.add_argument("--rerun", action="store_true",
                        help=f"also write OUT/{RECORDING}, a 3-D recording for the Rerun viewer")  # fmt: skip
    parser.add_argument("--bag-out", type=Path, help="also a ROS 2 bag of the outputs: OUT.mcap (one MCAP "
                        "file) or a bag folder (docs/inference.md, ROS 2 bags)")  # fmt: skip
    parser.add_argument("--overwrite", action="store_true")
    parser.add_argument("--quiet", action="store_true")
    add_bag_options(parser, poses_required=False)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(message)s")
    try:
        if args.threads is not None:
            check_threads(args.threads, "--threads")
            torch.set_num_threads(args.threads)
            cv2.setNumThreads(args.threads)
        if args.max_images is not None and args.max_images < 1:
            raise ValueError(f"--max-images: {args.max_images}; at least 1 (or leave it out: every image)")
        only = {"sweep": ("hypotheses", "cost"), "sgbm": ("resolution", "min_confidence")}
        for matcher, options in only.items():
            given = [f"--{o.replace('_', '-')}" for o in options if getattr(args, o) is not None]
            if given and args.matcher != matcher:
                raise ValueError(f"{', '.join(given)}: an option of --matcher {matcher}, not {args.matcher}")
        if args.matcher == "sweep":
            hypotheses = 128 if args.hypotheses is None else args.hypotheses
            settings = SweepSettings(hypotheses, args.min_distance, args.max_distance, args.cost or "zncc")
            matcher = SweepMatcher(settings)
        else:
            resolution = None if args.resolution is None else math.radians(args.resolution)
            matcher = SgbmMatcher(SgbmSettings(args.min_distance, args.max_distance, resolution,
                                               min_confidence=args.min_confidence or 0.0))  # fmt: skip
        sources = tuple(args.sources.split(","))
        with sigterm_raises(), recording_of(args, args.out) as root:
            summary = run(root, args.out, matcher, sources, args.overwrite, not args.quiet, args.max_images,
                          args.refine, args.rerun, args.bag_out, args.root)  # fmt: skip
    except (FileNotFoundError, FileExistsError, NotADirectoryError, ValueError, ImportError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except (Terminated, KeyboardInterrupt) as stop:  # its staging folder and lock are gone with it
        why, status = stopped_by(stop)
        print(f"error: {why}; nothing was written to {args.out}", file=sys.stderr)
        return status
    except OSError as err:  # the disk filled, a folder turned read-only, or an input cannot be read
        if err.errno not in WRITE_ERRORS:
            raise
        where = os.path.abspath(err.filename or args.out)
        written = where.startswith(os.path.abspath(args.out)) or where.startswith(
            os.path.abspath(args.out.parent / f".{args.out.name}.")
        )  # --out, or its staging folder or lock beside it
        what = f"--out: {where}: cannot be written" if written else f"{where}: cannot be read"
        print(f"error: {what} ({err.strerror})", file=sys.stderr)
        return 2
    seconds = summary["seconds"]["per_image"]
    left = len(summary["images_left_out"])
    print(f"{len(summary['images'])} images matched ({seconds:.2f} s each), {left} left out "
          f"(summary.json says why); {args.out}")  # fmt: skip
    if len(summary["kept_nothing"]) == len(summary["images"]):  # nothing done: no exit 0 for it
        why = sorted(set(summary["pairs_left_out"].values()))
        flat = [r["image"] for r in summary["images"] if r["flat"] > 0.5]
        if flat:
            why.append(f"{len(flat)} of the images are flat (no contrast to match) over half their pixels")
        why = "; ".join(why) or "no pixel passed the checks"
        print(f"error: {args.out}: no image kept a pixel ({why})", file=sys.stderr)
        return 1
    return 0
