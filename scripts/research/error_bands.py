#!/usr/bin/env python
"""Where is a checkpoint's error, and does its training objective know better? Per camera and by
ground-truth distance band, on a dataset with rendered distance maps (the synthetic worlds):

- ``share``: the band's share of the camera's scored pixels; ``abs_rel``, ``ratio`` (median of
  prediction / truth) and ``part`` (the band's part of the camera's abs_rel: the parts add up to it);
- ``loss truth`` and ``loss pred``: the training objective per pixel
  (``SelfSupervisedObjective.pixel_objective``: scale 0, minimum reprojection over the sources with
  auto-masking, without training's tie-breaking noise) with the ground-truth distance and with the
  checkpoint's prediction, over the true relative poses;
- ``used``: the share of the band's pixels whose loss depends on the prediction (a warp reaches them
  and wins against every unwarped source); the others give the network no gradient.

A band whose ``loss truth`` is well below its ``loss pred`` is one the objective would fix: the network
has not got there (too few steps, a local minimum), not a loss that prefers the wrong answer.

    python scripts/research/error_bands.py CHECKPOINT DATASET [--split test] [--offsets -2 2]
                                           [--bands 0 1.5 3 6 10 20 40 80] [--every 1]

Everything is computed at the checkpoint's input size (the dataset is resized to it). Scored pixels:
ground truth in (0, last band edge), inside the body mask and the camera's field of view. DATASET is read
as ``data=synthetic`` reads it (DATA below), un-augmented, with its rendered distance.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import tempfile
from pathlib import Path

import torch

from fisheyedepth.data import FisheyeDataset, collate
from fisheyedepth.module import FisheyeDepthModule

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # scripts/, for _compose
from _compose import build_datamodule, compose_config  # noqa: E402

DATA = ["data=synthetic", "data.datamodule.augment=null", "data.datamodule.ground_truth=distance"]
SKY = 1e4  # metres given to pixels without ground truth (the sky) when warping with the truth
BANDS = (0.0, 1.5, 3.0, 6.0, 10.0, 20.0, 40.0, 80.0)


@torch.no_grad()
def error_bands(
    module: FisheyeDepthModule, dataset: FisheyeDataset, edges=BANDS, every: int = 1, batch_size: int = 4
) -> dict[str, dict[str, dict[str, float]]]:
    """``{camera: {band: {share, abs_rel, ratio, part, loss_truth, loss_pred, used, pixels}}}``; the
    band "all" is the camera's whole scored range."""
    module = module.eval()
    bands = [(f"{lo:g}-{hi:g} m", lo, hi) for lo, hi in itertools.pairwise(edges)]
    bands.append(("all", edges[0], edges[-1]))
    acc: dict[str, dict[str, dict[str, list]]] = {}
    indices = list(range(0, len(dataset), every))
    for start in range(0, len(indices), batch_size):
        batch = collate([dataset[i] for i in indices[start : start + batch_size]])
        gt = batch.distance[:, 0]
        pred = module.depth_net.distance(batch.image, batch.camera)[:, 0].float()  # scale 0 only
        truth = torch.where(gt > 0, gt, torch.full_like(gt, SKY))
        loss_truth, _, usable = module.objective.pixel_objective(batch, truth, batch.poses)
        loss_pred, used, _ = module.objective.pixel_objective(batch, pred, batch.poses)
        names = batch.camera_name or [f"camera {i}" for i in range(len(batch))]
        for i, name in enumerate(names):
            scored = usable[i] & (gt[i] > edges[0]) & (gt[i] < edges[-1])
            for band, lo, hi in bands:
                sel = scored & (gt[i] >= lo) & (gt[i] < hi)
                a = acc.setdefault(name, {}).setdefault(band, {k: [] for k in ("g", "p", "lt", "lp", "u")})
                a["g"].append(gt[i][sel])
                a["p"].append(pred[i][sel])
                a["lt"].append(loss_truth[i][sel])
                a["lp"].append(loss_pred[i][sel])
                a["u"].append(used[i][sel])
    table: dict[str, dict[str, dict[str, float]]] = {}
    for name, by_band in acc.items():
        total = sum(int(g.numel()) for g in by_band["all"]["g"])  # the bands partition "all"
        for band, a in by_band.items():
            g, p = torch.cat(a["g"]), torch.cat(a["p"])
            if g.numel() == 0:
                continue
            rel = (p - g).abs() / g
            table.setdefault(name, {})[band] = {
                "pixels": int(g.numel()),
                "share": g.numel() / total,
                "abs_rel": float(rel.mean()),
                "ratio": float((p / g).median()),
                "part": float(rel.sum()) / total,
                "loss_truth": float(torch.cat(a["lt"]).mean()),
                "loss_pred": float(torch.cat(a["lp"]).mean()),
                "used": float(torch.cat(a["u"]).float().mean()),
            }
    return table


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("dataset", type=Path, help="a dataset in the KITTI-360 layout with distance maps")
    parser.add_argument("--split", default="test", help="a split of the data config: train, val or test")
    parser.add_argument("--offsets", type=int, nargs="+", help="source frames (default: the checkpoint's)")
    parser.add_argument(
        "--source-baseline",
        type=float,
        help="metres: sources chosen by distance, as data.datamodule.source_baseline (cpu_30min: 1.67); "
        "default: the offsets' frames",
    )
    parser.add_argument("--bands", type=float, nargs="+", default=list(BANDS), help="band edges, metres")
    parser.add_argument("--every", type=int, default=1, help="use every n-th sample")
    args = parser.parse_args(argv)
    module = FisheyeDepthModule.from_checkpoint(args.checkpoint)
    size = module.hparams.get("input_size")
    offsets = args.offsets or list(module.objective.source_offsets)
    with tempfile.TemporaryDirectory() as cache:
        values = {
            "data.datamodule.root": args.dataset,
            "data.datamodule.size": None if size is None else list(size),
            "data.datamodule.cache_dir": cache,
            "data.datamodule.source_baseline": args.source_baseline,
        }
        datamodule = build_datamodule(compose_config(DATA, values), offsets=tuple(offsets))
        dataset = datamodule.dataset(args.split)
        table = error_bands(module, dataset, tuple(args.bands), args.every)
    chosen = f"sources {offsets}" + (f", {args.source_baseline} m away" if args.source_baseline else "")
    print(f"{args.checkpoint} on {args.dataset} ({args.split}, {chosen})\n")
    print("| camera | band | share | abs_rel | ratio | part | loss truth | loss pred | used |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in sorted(table):
        for band, r in table[name].items():
            bold = "**" if band == "all" else ""
            print(
                f"| {name} | {bold}{band}{bold} | {r['share']:.3f} | {r['abs_rel']:.3f} | {r['ratio']:.3f} | "
                f"{r['part']:.3f} | {r['loss_truth']:.4f} | {r['loss_pred']:.4f} | {r['used']:.3f} |"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
