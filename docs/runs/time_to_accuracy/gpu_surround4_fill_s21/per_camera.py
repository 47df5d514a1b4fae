"""Per world and camera, full-range and kitti360-protocol abs_rel (unscaled) of runs scored by
scripts/heldout.py, and the spread (the worst camera's full-range abs_rel over the best's, issue #13's
item 3 asks for at most 1.25x).

    python per_camera.py RIG RUN [RUN ...] [--seeds S ...] [--lane left|both] [--right DIR ...]

``--lane left``: the scores of ``scripts/heldout.py --lane left`` (the car in the left lane).
``--lane both``: each camera's full-range abs_rel averaged over the seeds in both lanes, one line per
run: the content each side camera faces, balanced. ``--right``: where each run's right-lane scores are,
if not in the run's folder (one folder per run, in order).
"""

import argparse
import json
from pathlib import Path

parser = argparse.ArgumentParser()
parser.add_argument("rig", choices=["kitti360", "surround4"])
parser.add_argument("runs", nargs="+")
parser.add_argument("--seeds", nargs="+", type=int, default=[1001, 1002, 2001, 2002])
parser.add_argument("--lane", choices=("right", "left", "both"), default="right")
parser.add_argument("--right", nargs="+")
args = parser.parse_args()
if args.right and len(args.right) != len(args.runs):
    parser.error("--right needs one folder per run")


def results(folder: str, seed: int, lane: str) -> dict:
    suffix = "_laneleft" if lane == "left" else ""
    return json.loads((Path(folder) / f"heldout_{args.rig}_seed{seed}{suffix}" / "results.json").read_text())[
        "results"
    ]


for i, run in enumerate(args.runs):
    right = args.right[i] if args.right else run
    if args.lane == "both":
        scores: dict[str, list[float]] = {}
        for seed in args.seeds:
            for folder, lane in ((right, "right"), (run, "left")):
                for camera, metrics in results(folder, seed, lane)["full"]["none_by_camera"].items():
                    scores.setdefault(camera, []).append(metrics["abs_rel"])
        means = {camera: sum(v) / len(v) for camera, v in sorted(scores.items())}
        cells = " ".join(f"{camera} {mean:.3f}" for camera, mean in means.items())
        print(f"{run}: {cells} | spread {max(means.values()) / min(means.values()):.2f}x")
        continue
    print(f"== {run}")
    for seed in args.seeds:
        scored = results(right if args.lane == "right" else run, seed, args.lane)
        full, k360 = scored["full"], scored["kitti360"]
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
