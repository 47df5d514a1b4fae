"""What the plane-sweep hints could teach a checkpoint: on a world's test split (ground truth read for
this report only), per camera, over the pixels with ground truth inside the body mask: the hints'
coverage and share within 1.25x of the truth; over the near pixels (truth under 8 m) the checkpoint
predicts more than 1.5x too far, the share with a right hint; and the share of near pixels where a
hint would act in training (valid, and warping the sources better than the checkpoint's distance)
and is right where the checkpoint is wrong (helps) or wrong where it is right (hurts), within 1.25x.

    python hint_quality.py CHECKPOINT DATASET   (48 candidates, sources at 1.67 m, make_hints' defaults)

It needs the plane sweep of commit cca14f3 (``fisheyedepth.losses.plane_sweep``, removed by the revert
after row 47 of BENCHMARKS.md "Time to accuracy"): run it from a checkout of that commit.
"""

import sys
import tempfile

import torch

from fisheyedepth.cameras import RayCache
from fisheyedepth.data import FisheyeDataset, Kitti360Layout, collate
from fisheyedepth.losses import candidate_distances, plane_sweep
from fisheyedepth.module import FisheyeDepthModule

module = FisheyeDepthModule.from_checkpoint(sys.argv[1]).eval()
dataset = FisheyeDataset(
    Kitti360Layout(sys.argv[2]),
    "splits/test.txt",
    size=tuple(module.hparams.input_size),
    offsets=(-2, 2),
    source_baseline=1.67,
    ground_truth="distance",
    cache_dir=tempfile.mkdtemp(),
)
candidates = candidate_distances(0.5, 80.0, 48).float()
rays = RayCache()
acc: dict[str, list[int]] = {}
with torch.no_grad():
    for i in range(len(dataset)):
        b = collate([dataset[i]])
        r, rv = rays.batch(b.camera, "cpu", torch.float32)
        usable = b.mask[:, 0] > 0.5
        hint, valid = plane_sweep(
            b.image, b.sources, b.poses, r, rv & usable, b.source_camera, b.source_mask, candidates
        )
        pred = module.depth_net.distance(b.image, b.camera)[:, 0].float()
        gt = b.distance[:, 0]
        err_p, _, _ = module.pixel_objective(b, pred, b.poses)
        err_h, _, _ = module.pixel_objective(b, torch.where(valid, hint, pred), b.poses)
        scored = usable & (gt > 0)
        near = scored & (gt < 8)
        right_h = valid & (torch.maximum(hint / gt, gt / hint) < 1.25)
        right_p = torch.maximum(pred / gt, gt / pred) < 1.25
        missed = near & (pred > 1.5 * gt)
        acts = near & valid & (err_h < err_p)
        a = acc.setdefault(b.camera_name[0], [0] * 8)
        for k, v in enumerate(
            (
                scored,
                scored & valid,
                scored & right_h,
                near,
                missed,
                missed & right_h,
                acts & right_h & ~right_p,
                acts & ~right_h & right_p,
            )
        ):
            a[k] += int(v.sum())
print(
    "| camera | coverage | hints within 1.25x | near pixels missed (> 1.5x too far) | of those, a right hint"
    " | helps | hurts |"
)
print("|---|---|---|---|---|---|---|")
for name, (n, v, good, nn, miss, miss_ok, helps, hurts) in sorted(acc.items()):
    print(
        f"| {name} | {v / n:.3f} | {good / max(v, 1):.3f} | {miss / nn:.3f} | {miss_ok / max(miss, 1):.3f} |"
        f" {helps / nn:.4f} | {hurts / nn:.4f} |"
    )
