#!/usr/bin/env python
"""What a multi-view checkpoint's cost volume knows on its own: the winner-take-all distance of the volume
(the hypothesis of lowest cost at each pixel of the map it joins) against the ground truth, beside the
network's own distance, on a held-out world's test frames with their sources.

    python scripts/research/volume_winner.py CHECKPOINT [--seed 2001] [--rig kitti360] [--frames 16]

The truth at the volume's stride is each block's nearest surface (its minimum); pixels that every
hypothesis of some source sees are scored. A volume whose winner is far from the truth gives the decoder
little to read, whatever the network learns around it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
import torch.nn.functional as F
from hydra.utils import instantiate

from fisheyedepth.cli import prepare_data
from fisheyedepth.models.cost_volume import Sources
from fisheyedepth.module import FisheyeDepthModule
from fisheyedepth.plan import data_plan

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _compose import compose_config  # noqa: E402


def relative_errors(estimate: torch.Tensor, truth: torch.Tensor, where: torch.Tensor) -> torch.Tensor:
    return (estimate[where] - truth[where]).abs() / truth[where]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("checkpoint")
    parser.add_argument("--seed", type=int, default=2001)
    parser.add_argument("--rig", default="kitti360")
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    module = FisheyeDepthModule.from_checkpoint(args.checkpoint).eval()
    net = module.depth_net
    if net.cost_volume is None:
        raise SystemExit(f"error: {args.checkpoint}: net.cost_volume is 0, a monocular checkpoint")
    size = list(module.hparams["input_size"])
    world = [f"data.generate.rig={args.rig}", f"data.generate.seed={args.seed}", "data.generate.frames=200"]
    cfg = compose_config(["data=synthetic", *world, f"data.datamodule.size=[{size[0]},{size[1]}]"])
    prepare_data(data_plan(cfg))
    dataset = instantiate(cfg.data.datamodule).dataset("test")
    stride = 2 ** (net.volume_level + 1)
    volume_errors, network_errors = [], []
    for index in range(0, len(dataset), max(1, len(dataset) // args.frames))[: args.frames]:
        sample = dataset[index]
        image, cameras = sample["image"][None], [sample["camera"]]
        cams = sample.get("source_camera", [sample["camera"]] * sample["sources"].shape[0])
        sources = Sources(sample["sources"][None], sample["poses"][None], [cams])
        with torch.no_grad():
            volume = net.match(net.volume_map(image), cameras, sources)[0]
            distance = net.for_cameras(image, cameras, sources=sources)["distance"][0][0, 0]
        winner = 1 / net.cost_volume.inverse[volume[:-1].argmin(0)]
        truth = sample["distance"][0]
        far = torch.where(truth > 0, truth, torch.full_like(truth, float("inf")))
        nearest = -F.max_pool2d(-far[None, None], stride)[0, 0]
        scored = (volume[-1] > 0.99) & torch.isfinite(nearest) & (nearest < 80)
        volume_errors.append(relative_errors(winner, nearest, scored))
        usable = (truth > 0) & (truth < 80) & (sample["mask"][0] > 0.5)
        network_errors.append(relative_errors(distance, truth, usable))
    for label, errors in (("the volume's winner", volume_errors), ("the network", network_errors)):
        e = torch.cat(errors)
        a1 = float((e < 0.25).float().mean())
        print(f"{label}: median relative error {float(e.median()):.3f}, a1 {a1:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
