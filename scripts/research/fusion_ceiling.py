#!/usr/bin/env python
"""How far matching can take a monocular network on a held-out world: the ceiling of any fusion.

On the test frames of a held-out world that have the ``--offsets`` neighbours, per pixel against the exact
distance (full range, below 80 m):

- the monocular checkpoint on the image alone (its input size);
- sweep stereo (ZNCC, 4 SGM paths, ``--hypotheses`` over 1.5-80 m) from those neighbours with their exact
  real-scale poses, at ``--size``: every pixel it sees, before its round-trip check;
- the monocular distance replaced by the sweep's where the round trip keeps it;
- the per-pixel better of the two, chosen *with the ground truth*: what a perfect selector between the
  monocular estimate and the match would score. A learned fusion recovers a part of the way from the
  first row to this one (ManyDepth: 0.115 -> 0.098 on KITTI), so a target near or under it is out of
  reach of matching at this resolution.

    python scripts/research/fusion_ceiling.py CKPT [--size 160] [--seed 2001] [--frames 16]
                                              [--offsets -2 2] [--hypotheses 128]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from hydra.utils import instantiate

from fisheyedepth.cli import prepare_data
from fisheyedepth.module import FisheyeDepthModule
from fisheyedepth.plan import data_plan
from fisheyedepth.stereo.sweep import SweepMatcher, SweepSettings, View

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _compose import compose_config  # noqa: E402


def summary(errors: list[torch.Tensor]) -> str:
    e = torch.cat(errors)
    a1 = float((e < 0.25).float().mean())
    return f"abs_rel {float(e.mean()):.4f}, median {float(e.median()):.4f}, a1 {a1:.3f}"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("checkpoint")
    parser.add_argument("--size", type=int, default=160, help="the sweep's image size (square)")
    parser.add_argument("--seed", type=int, default=2001)
    parser.add_argument("--rig", default="kitti360")
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--offsets", type=int, nargs="+", default=[-2, 2])
    parser.add_argument("--hypotheses", type=int, default=128)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    module = FisheyeDepthModule.from_checkpoint(args.checkpoint).eval()
    input_size = tuple(module.hparams["input_size"])
    world = [f"data.generate.rig={args.rig}", f"data.generate.seed={args.seed}", "data.generate.frames=200"]
    cfg = compose_config(["data=synthetic", *world, f"data.datamodule.size=[{args.size},{args.size}]"])
    prepare_data(data_plan(cfg))
    dataset = instantiate(cfg.data.datamodule, offsets=args.offsets).dataset("test")
    sweep = SweepMatcher(
        SweepSettings(args.hypotheses, 1.5, 80.0, cost="zncc", window=5 if args.size < 200 else 7, paths=4)
    )
    rows = {"monocular": [], "sweep, every pixel it sees": [], "monocular, sweep where checked": [],
            "better of the two per pixel (truth picks)": []}  # fmt: skip
    checked = []
    for index in range(0, len(dataset), max(1, len(dataset) // args.frames))[: args.frames]:
        sample = dataset[index]
        camera = sample["camera"]
        cameras = sample.get("source_camera", [camera] * sample["sources"].shape[0])
        views = [
            View(sample["sources"][None, j], cam, sample["poses"][None, j]) for j, cam in enumerate(cameras)
        ]
        result = sweep(View(sample["image"][None], camera, torch.eye(4)), views)
        with torch.no_grad():
            mono = module.depth_net.distance(sample["image"][None], [camera], input_size=input_size)[0, 0]
        truth = sample["distance"][0]
        scored = (truth > 0) & (truth < 80) & (sample["mask"][0] > 0.5)
        mono_error = (mono - truth).abs() / truth
        sweep_error = torch.where(result.seen[0], (result.dense[0] - truth).abs() / truth, mono_error)
        rows["monocular"].append(mono_error[scored])
        rows["sweep, every pixel it sees"].append(sweep_error[scored & result.seen[0]])
        rows["monocular, sweep where checked"].append(
            torch.where(result.valid[0], sweep_error, mono_error)[scored]
        )
        rows["better of the two per pixel (truth picks)"].append(
            torch.minimum(mono_error, sweep_error)[scored]
        )
        checked.append(result.valid[0][scored].float())
    print(
        f"world {args.seed} ({args.rig}), {len(checked)} test frames, sweep at {args.size} px, "
        f"sources {args.offsets}"
    )
    for name, errors in rows.items():
        print(f"  {name}: {summary(errors)}")
    print(f"  pixels the round trip keeps: {float(torch.cat(checked).mean()):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
