"""How the three-world training set of this record was built (session 10): the 200-frame worlds of seeds
0, 1 and 2 (`fisheyedepth-synthetic --frames 200 --seed S`) joined by symlinks into one KITTI-360-layout
root, world k's train/val/test drives renamed 3k, 3k+1, 3k+2 and the splits concatenated. Its
synthetic.json is world 0's with frames 600, so `train.py data.generate.frames=600
data.datamodule.root=OUT` accepts it: 480 training frames, as many as the 600-frame world 0 of row 24.

    python make_union.py OUT WORLD0 WORLD1 WORLD2
"""

import json
import sys
from pathlib import Path

TOPS = ("data_2d_raw", "data_2d_distance", "data_poses", "data_3d_raw")
SPLITS = ("train", "val", "test")

out, worlds = Path(sys.argv[1]), [Path(p).resolve() for p in sys.argv[2:]]
out.mkdir(parents=True)
(out / "calibration").symlink_to(worlds[0] / "calibration")  # one rig: the same calibration
for top in (*TOPS, "splits"):
    (out / top).mkdir()
for k, world in enumerate(worlds):
    meta = json.loads((world / "synthetic.json").read_text())
    for i, split in enumerate(SPLITS):
        old, new = meta["sequences"][split]["name"], f"2013_05_28_drive_{3 * k + i:04d}_sync"
        for top in TOPS:
            if (world / top / old).exists():
                (out / top / new).symlink_to(world / top / old)
        frames = [line.split()[1] for line in (world / "splits" / f"{split}.txt").read_text().splitlines()]
        with open(out / "splits" / f"{split}.txt", "a") as f:
            f.writelines(f"{new} {frame}\n" for frame in frames)
meta = json.loads((worlds[0] / "synthetic.json").read_text())
meta.update(frames=600, note=f"worlds {[w.name for w in worlds]}, 200 frames each (symlinks)")
(out / "synthetic.json").write_text(json.dumps(meta, indent=2) + "\n")
