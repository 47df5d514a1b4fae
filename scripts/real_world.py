#!/usr/bin/env python
"""Score checkpoints (.ckpt) or exported files (.onnx) on every real fisheye frame with metric ground
truth under the real data folder (``--root``, else ``FISHEYEDEPTH_REALDATA``; ``make realscore``
defaults to ``../shared/realdata``): the KITTI-360 frame against its LiDAR (80 m, inside the body
mask), the ScanNet++ frame and four Aria Digital Twin SLAM frames against their rendered depth (capped
at the frame's range). Real cameras, never trained on.

    python scripts/real_world.py MODEL [MODEL ...] [--root DIR] [--frames kitti360 scannetpp adt]
                                 [--pictures DIR] [--json OUT] [--force] [--post-process flip]
                                 [--no-multiview]
    python scripts/real_world.py --from-records docs/records/real_photographs   # kept scores
    python scripts/real_world.py --from-records --multiview RECORD               # the sweep's, kept

Prints one Markdown row per model and frame: abs_rel, a1 and rmse unscaled, then median-scaled (and
the ratio ground truth / prediction), beside a constant map at the ground truth's median distance,
the score any real-world result must beat; then the published zero-shot anchors on KITTI-360. The
network runs at its input size on the image and camera resized alike, its distance upsampled to the
frame's size. ``--pictures``: input | prediction | ground truth | error per model and frame;
``--json``: every number (the kitti360 protocol under 8 m for the KITTI-360 frame too). Exit status
1 when a frame's files are missing (each is named in the table), 2 on a malformed file or option, or
without a real data folder.
Then sweep stereo (fisheyedepth.stereo, untrained) on every real frame with a partner: the ADT SLAM
pairs, frames 0 and 1, each camera as the reference, the pair's rotation refined from its images first;
and Middlebury 2014 Motorcycle (scikit-image). Each is scored on the reference's overlap with its partner,
checked and dense, beside the constant map and each model on the same pixels (``--no-multiview``: not).
``--from-records``: the MODEL arguments are run records (files or folders, ``docs/records``) whose
``real_world`` scores are printed as kept, nothing re-scored.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from fisheyedepth.data.realframes import FRAME_SETS
from fisheyedepth.realworld import records_table, score_models
from fisheyedepth.runtimes import POST_PROCESSING
from fisheyedepth.stereo.realpairs import multiview_records_table, multiview_scores

ROOT_VARIABLE = "FISHEYEDEPTH_REALDATA"  # the real data folder, when --root is not given


def data_root(root: Path | None) -> Path:
    """``--root``, else ``$FISHEYEDEPTH_REALDATA``; a ValueError naming both when neither is given."""
    if root is not None:
        return Path(root)
    if os.environ.get(ROOT_VARIABLE):
        return Path(os.environ[ROOT_VARIABLE])
    raise ValueError(f"--root: no real data folder given; pass --root DIR or set {ROOT_VARIABLE}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("models", nargs="+", type=Path, help="checkpoints (.ckpt) or exported files (.onnx)")
    parser.add_argument("--root", type=Path, help=f"real data folder (default: ${ROOT_VARIABLE})")
    parser.add_argument("--frames", nargs="+", choices=FRAME_SETS, default=list(FRAME_SETS))
    parser.add_argument("--pictures", type=Path, help="write <model>_<frame>.png here")
    parser.add_argument("--json", type=Path, help="write every number to this JSON file")
    parser.add_argument("--force", action="store_true", help="replace existing pictures and JSON")
    parser.add_argument("--post-process", default="none", choices=POST_PROCESSING)
    parser.add_argument("--from-records", action="store_true", help="MODEL...: run records; score nothing")
    parser.add_argument("--no-multiview", action="store_true", help="score the models only, not sweep stereo")
    parser.add_argument("--multiview", action="store_true", help="with --from-records: the sweep's table")
    args = parser.parse_args(argv)
    if args.from_records:
        try:
            table = multiview_records_table if args.multiview else records_table
            print("\n".join(table(args.models) if args.multiview else table(args.models, args.frames)))
        except (OSError, ValueError) as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        return 0
    echo = lambda line: print(line, flush=True)  # noqa: E731

    try:
        root = data_root(args.root)

        def multiview(record, predictions):
            record["multiview"] = multiview_scores(root, predictions, args.pictures, echo)

        if args.pictures is not None and not args.force and not args.no_multiview:
            taken = sorted(Path(args.pictures).glob("multiview_*.png"))
            if taken:
                raise FileExistsError(f"{taken[0]} exists; pass --force to replace it")
        record = score_models(
            args.models, root, args.frames, args.pictures, args.json, args.force, args.post_process,
            echo=echo, more=None if args.no_multiview else multiview,
        )  # fmt: skip
    except (OSError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    missing = [name for name, frame in record["frames"].items() if "missing" in frame]
    if missing:
        print(f"missing: {', '.join(missing)} (their rows name the path)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
