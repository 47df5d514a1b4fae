"""Per world: full-range abs_rel, a1 / kitti360-protocol abs_rel (unscaled), then each camera's
full-range and kitti360-protocol abs_rel (image_02 left / image_03 right, the kerb side), for runs
whose held-out scores are in RUN/heldout_kitti360_seed<S>/results.json (train.py runs scored by
scripts/heldout.py, or this record's probes).

    python compare.py RUN [RUN ...]
"""

import json
import sys
from pathlib import Path

SEEDS = (1001, 1002, 1003, 2001, 2002, 2003)  # development, then held out

for run in sys.argv[1:]:
    print(f"== {run}")
    for seed in SEEDS:
        results = json.loads((Path(run) / f"heldout_kitti360_seed{seed}" / "results.json").read_text())
        full, k360 = results["results"]["full"], results["results"]["kitti360"]
        by_camera = full["none_by_camera"], k360["none_by_camera"]
        cams = " ".join(
            f"{name} {by_camera[0][name]['abs_rel']:.3f} / {by_camera[1][name]['abs_rel']:.3f}"
            for name in ("image_02", "image_03")
        )
        print(
            f"{seed}: {full['none']['abs_rel']:.3f}, {full['none']['a1']:.3f} / {k360['none']['abs_rel']:.3f}"
            f" | {cams}"
        )
