"""Each camera's full-range abs_rel (unscaled) averaged over worlds scored in both lanes (the right
lane of training and scoring, and ``scripts/heldout.py --lane left``): the content each side camera
faces, balanced. Runs are folders with ``heldout_<rig>_seed<S>[_laneleft]/results.json``.

    python lane_balanced.py RUN [RUN ...] [--right DIR ...] [--rig kitti360] [--seeds S ...]

``--right``: where each run's right-lane scores are, if not in the run's folder (one per run, in order).
"""

import argparse
import json
from pathlib import Path

parser = argparse.ArgumentParser()
parser.add_argument("runs", nargs="+")
parser.add_argument("--rig", default="kitti360")
parser.add_argument("--seeds", nargs="+", type=int, default=[1001, 1002, 1003, 2001, 2002, 2003])
parser.add_argument("--right", nargs="+")
args = parser.parse_args()
if args.right and len(args.right) != len(args.runs):
    parser.error("--right needs one folder per run")

for i, run in enumerate(args.runs):
    right = args.right[i] if args.right else run
    scores: dict[str, list[float]] = {}
    for seed in args.seeds:
        for folder, lane in ((right, ""), (run, "_laneleft")):
            path = Path(folder) / f"heldout_{args.rig}_seed{seed}{lane}" / "results.json"
            by_camera = json.loads(path.read_text())["results"]["full"]["none_by_camera"]
            for camera, metrics in by_camera.items():
                scores.setdefault(camera, []).append(metrics["abs_rel"])
    means = {camera: sum(v) / len(v) for camera, v in sorted(scores.items())}
    cells = " ".join(f"{camera} {mean:.3f}" for camera, mean in means.items())
    print(f"{run}: {cells} | spread {max(means.values()) / min(means.values()):.2f}x")
