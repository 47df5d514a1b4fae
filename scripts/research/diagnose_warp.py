#!/usr/bin/env python
"""Does a warp model's photometric objective have its minimum at the truth? A check on a dataset with
ground-truth distance (the synthetic worlds) and its real-scale poses.

For every warp model (the fisheye camera itself, and the pinhole stand-ins of the Monodepth2 baseline),
the photometric error (SSIM + L1, scale 0, no auto-masking) of the target frames reconstructed from
their sources with the ground-truth distance and:
- the true relative poses;
- the true poses with the translation reversed;
- no motion at all (the identity pose).

A model whose error at the truth is above its error with no motion cannot learn the truth by
minimising it: the Table 2 baseline's PoseNet is pulled away from the true motion, not towards it.

    python scripts/diagnose_warp.py data/synthetic_kitti360_256_seed0_f200 [more roots] [--size 96]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import torch

from fisheyedepth.cameras.pinhole import PINHOLE_FOCALS
from fisheyedepth.data import FisheyeDataset, Kitti360Layout, collate
from fisheyedepth.module import FisheyeDepthModule

SKY = 1e4  # metres given to pixels without ground truth (the sky): nearly parallax-free
POSES = ("true", "reversed translation", "no motion")


def poses_for(name: str, true: torch.Tensor) -> torch.Tensor:
    if name == "true":
        return true
    if name == "reversed translation":
        out = true.clone()
        out[..., :3, 3] *= -1
        return out
    return torch.eye(4, dtype=true.dtype).expand_as(true).clone()


@torch.no_grad()
def errors(root: Path, split: str, size: int, every: int, batch: int) -> dict[str, dict[str, float]]:
    with tempfile.TemporaryDirectory() as cache:
        dataset = FisheyeDataset(
            Kitti360Layout(root), split, size=(size, size), ground_truth="distance", cache_dir=cache
        )
        samples = [dataset[i] for i in range(0, len(dataset), every)]
    models = {"fisheye": {"fisheye_projection": True}}
    models |= {f"pinhole ({f})": {"fisheye_projection": False, "pinhole_focal": f} for f in PINHOLE_FOCALS}
    table = {}
    for name, switches in models.items():
        module = FisheyeDepthModule(scales=(0,), automask=False, log_images_every=0, **switches).eval()
        sums, n = dict.fromkeys(POSES, 0.0), 0
        for start in range(0, len(samples), batch):
            b = collate(samples[start : start + batch])
            gt = torch.where(b.distance > 0, b.distance, torch.full_like(b.distance, SKY))
            outputs = {"distance": {0: gt}, "disp": {0: torch.full_like(gt, 0.5)}}
            for pose in POSES:
                moved = dataclasses.replace(b, poses=poses_for(pose, b.poses))
                sums[pose] += module.losses(moved, outputs)[1]["photometric/0"].item() * len(b)
            n += len(b)
        table[name] = {pose: s / n for pose, s in sums.items()}
    return table


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "roots", nargs="+", type=Path, help="datasets in the KITTI-360 layout with distance maps"
    )
    parser.add_argument("--split", default="splits/train.txt")
    parser.add_argument("--size", type=int, default=96)
    parser.add_argument("--every", type=int, default=8, help="use every n-th sample")
    parser.add_argument("--batch", type=int, default=8)
    args = parser.parse_args(argv)
    print(f"| dataset | warp model | {' | '.join(POSES)} | truth below no motion |")
    print("|---|---|" + "---|" * len(POSES) + "---|")
    for root in args.roots:
        for model, row in errors(root, args.split, args.size, args.every, args.batch).items():
            cells = " | ".join(f"{row[p]:.4f}" for p in POSES)
            ok = "yes" if row["true"] < row["no motion"] else "**no**"
            print(f"| {root.name} | {model} | {cells} | {ok} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
