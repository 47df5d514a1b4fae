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

    python scripts/research/diagnose_warp.py data/synthetic_kitti360_256_seed0_f200 [more roots] [--size 96]
        [--split train]

Each dataset is read as ``data=synthetic`` reads it, un-augmented, with its rendered distance; each warp
model is ``model=fisheyedepth`` with the overrides below (MODEL, WARPS).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import torch

from fisheyedepth.cameras.pinhole import PINHOLE_FOCALS
from fisheyedepth.data import collate

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # scripts/, for _compose
from _compose import build_datamodule, build_module, compose_config  # noqa: E402

SKY = 1e4  # metres given to pixels without ground truth (the sky): nearly parallax-free
POSES = ("true", "reversed translation", "no motion")
DATA = ["data=synthetic", "data.datamodule.augment=null", "data.datamodule.ground_truth=distance"]
# The objective at scale 0 without auto-masking, with Monodepth2's neighbours one frame away (the data
# module loads what the model warps); the rows differ in their warp model only.
MODEL = [
    "model=fisheyedepth",
    "model.net.scales=[0]",
    "model.objective.automask=false",
    "model.objective.source_offsets=[-1,1]",
    "model.log_images_every=0",
]
FISHEYE, PINHOLE_FOCAL = "model.objective.fisheye_projection", "model.objective.pinhole_focal"
WARPS = {"fisheye": [f"{FISHEYE}=true"]} | {
    f"pinhole ({f})": [f"{FISHEYE}=false", f"{PINHOLE_FOCAL}={f}"] for f in PINHOLE_FOCALS
}


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
    table, modules = {}, {}
    with tempfile.TemporaryDirectory() as cache:
        values = {"data.datamodule.root": root, "data.datamodule.size": [size, size]}
        values["data.datamodule.cache_dir"] = cache
        datamodule = build_datamodule(compose_config(DATA + MODEL, values))
        dataset = datamodule.dataset(split)
        samples = [dataset[i] for i in range(0, len(dataset), every)]
        for name, warp in WARPS.items():
            modules[name] = build_module(compose_config(DATA + MODEL + warp, values), datamodule).eval()
    for name, module in modules.items():
        sums, n = dict.fromkeys(POSES, 0.0), 0
        for start in range(0, len(samples), batch):
            b = collate(samples[start : start + batch])
            gt = torch.where(b.distance > 0, b.distance, torch.full_like(b.distance, SKY))
            outputs = {"distance": {0: gt}, "disp": {0: torch.full_like(gt, 0.5)}}
            for pose in POSES:
                moved = dataclasses.replace(b, poses=poses_for(pose, b.poses))
                sums[pose] += module.objective(moved, outputs)[1]["photometric/0"].item() * len(b)
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
    parser.add_argument("--split", default="train", help="a split of the data config: train, val or test")
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
