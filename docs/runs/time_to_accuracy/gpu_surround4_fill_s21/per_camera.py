"""Per world and camera, full-range and kitti360-protocol abs_rel (unscaled) of runs scored by
scripts/heldout.py, and the spread (the worst camera's full-range abs_rel over the best's, issue #13's
item 3 asks for at most 1.25x).

    python per_camera.py RIG RUN [RUN ...] [--seeds S ...] [--lane left]

``--lane left``: the scores of ``scripts/heldout.py --lane left`` (the car in the left lane).
"""

import argparse
import json
from pathlib import Path

parser = argparse.ArgumentParser()
parser.add_argument("rig", choices=["kitti360", "surround4"])
parser.add_argument("runs", nargs="+")
parser.add_argument("--seeds", nargs="+", type=int, default=[1001, 1002, 2001, 2002])
parser.add_argument("--lane", choices=("right", "left"), default="right")
args = parser.parse_args()

for run in args.runs:
    print(f"== {run}")
    for seed in args.seeds:
        lane = "_laneleft" if args.lane == "left" else ""
        path = Path(run) / f"heldout_{args.rig}_seed{seed}{lane}" / "results.json"
        results = json.loads(path.read_text())["results"]
        full, k360 = results["full"], results["kitti360"]
        cameras = sorted(full["none_by_camera"])
        values = [full["none_by_camera"][c]["abs_rel"] for c in cameras]
        cells = " ".join(
            f"{c} {v:.3f} / {k360['none_by_camera'][c]['abs_rel']:.3f}"
            for c, v in zip(cameras, values, strict=True)
        )
        print(
            f"{seed}: {full['none']['abs_rel']:.3f}, {full['none']['a1']:.3f} | {cells}"
            f" | spread {max(values) / min(values):.2f}x"
        )
