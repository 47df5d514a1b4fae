"""Where a checkpoint's near-range error is: per camera, pixels with ground truth in (0.3, 8) m (the
kitti360 protocol's range) inside the body mask, split into depth edges (the ground truth varies by
more than 1.5x within a 5x5 window) and interiors; for each, the share of the camera's pixels, abs_rel,
its part of the camera's abs_rel, and the share and part of the pixels predicted more than 1.5x too far.

    python near_range_outliers.py CHECKPOINT DATASET [SPLIT]   (the checkpoint's input size; SPLIT
    defaults to splits/test.txt; session 18 added it to count world 0's training frames)
"""

import sys
import tempfile

import torch
import torch.nn.functional as F

from fisheyedepth.data import FisheyeDataset, Kitti360Layout, collate
from fisheyedepth.module import FisheyeDepthModule

module = FisheyeDepthModule.from_checkpoint(sys.argv[1]).eval()
dataset = FisheyeDataset(
    Kitti360Layout(sys.argv[2]),
    sys.argv[3] if len(sys.argv) > 3 else "splits/test.txt",
    size=tuple(module.hparams.input_size),
    offsets=(-2, 2),
    ground_truth="distance",
    cache_dir=tempfile.mkdtemp(),
)
acc = {}
with torch.no_grad():
    for start in range(0, len(dataset), 4):
        batch = collate([dataset[i] for i in range(start, min(start + 4, len(dataset)))])
        gt = batch.distance[:, 0]
        pred = module.depth_net.distance(batch.image, batch.camera)[:, 0].float()
        g = torch.where(gt > 0, gt, torch.full_like(gt, 1e3))[:, None]
        edge = (F.max_pool2d(g, 5, 1, 2) / -F.max_pool2d(-g, 5, 1, 2) > 1.5)[:, 0]
        scored = (gt > 0.3) & (gt < 8) & (batch.mask[:, 0] > 0.5)
        for i, name in enumerate(batch.camera_name):
            rel = (pred[i] - gt[i]).abs() / gt[i]
            for kind, sel in (("edge", scored[i] & edge[i]), ("interior", scored[i] & ~edge[i])):
                a = acc.setdefault((name, kind), [0, 0.0, 0, 0.0])
                far = sel & (pred[i] > 1.5 * gt[i])
                a[0] += int(sel.sum())
                a[1] += float(rel[sel].sum())
                a[2] += int(far.sum())
                a[3] += float(rel[far].sum())
total = {}
for (name, _), a in acc.items():
    total[name] = total.get(name, 0) + a[0]
for (name, kind), (n, r, nf, rf) in sorted(acc.items()):
    t = total[name]
    print(
        f"{name} {kind:8s} share {n / t:.3f} abs_rel {r / max(n, 1):.3f} part {r / t:.3f} | "
        f">1.5x too far: share {nf / t:.3f} part {rf / t:.3f}"
    )
