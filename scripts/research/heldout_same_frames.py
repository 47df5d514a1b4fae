#!/usr/bin/env python
"""Monocular and multi-view checkpoints side by side on exactly the same held-out frames.

A multi-view network (``net.cost_volume``) is scored on the test frames that have its sources
(``objective.source_offsets``, and the rig's other cameras with ``--rig-offsets``); ``heldout.py`` scores a
monocular network on every test frame. This script scores each checkpoint on the frames that have the
``--offsets`` neighbours, the multi-view one with its sources, the monocular one on the image alone
(``--alone``: the multi-view one without its sources too, what its cost volume adds), full-range and
kitti360-protocol abs_rel, unscaled:

    python scripts/research/heldout_same_frames.py CKPT [CKPT ...] [--rig kitti360] [--seed 2001]
                                                   [--offsets -2 2] [--rig-offsets 0] [--alone]

The world is the 200-frame held-out one ``heldout.py`` renders (rendered on first use).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from hydra.utils import instantiate

from fisheyedepth.cli import prepare_data
from fisheyedepth.evaluation import evaluate
from fisheyedepth.module import FisheyeDepthModule
from fisheyedepth.plan import data_plan
from fisheyedepth.runtimes import TorchRuntime

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _compose import compose_config  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("checkpoints", nargs="+")
    parser.add_argument("--rig", default="kitti360")
    parser.add_argument("--seed", type=int, default=2001)
    parser.add_argument("--offsets", type=int, nargs="+", default=[-2, 2])
    parser.add_argument("--rig-offsets", type=int, nargs="*", default=[])
    parser.add_argument("--alone", action="store_true", help="also each multi-view one without sources")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    world = [f"data.generate.rig={args.rig}", f"data.generate.seed={args.seed}", "data.generate.frames=200"]
    cfg = compose_config(["data=synthetic", *world])
    prepare_data(data_plan(cfg))
    datamodule = instantiate(cfg.data.datamodule)
    print("| checkpoint | sources | images | full abs_rel | a1 | kitti360 abs_rel |")
    print("|---|---|---|---|---|---|")
    for ckpt in args.checkpoints:
        runtime = TorchRuntime(FisheyeDepthModule.from_checkpoint(ckpt))
        ways = [("with its sources" if runtime.sources else "none (monocular)", runtime.sources)]
        if runtime.sources and args.alone:
            ways.append(("withheld", None))
        for label, sources in ways:
            runtime.sources = sources
            loader = datamodule.scoring_loader("test", offsets=args.offsets, rig_offsets=args.rig_offsets)
            scores = evaluate(
                runtime, loader, runtime.input_size, ["full", "kitti360"], ["none"], n_pictures=0
            )
            full, near = scores["full"]["none"], scores["kitti360"]["none"]
            print(f"| {ckpt} | {label} | {full['images']} | {full['abs_rel']:.4f} | {full['a1']:.3f} "
                  f"| {near['abs_rel']:.4f} |", flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
