#!/usr/bin/env python
"""Stereo (fisheyedepth.stereo, untrained: the rectified SGBM pipeline or the sweep) on a held-out synthetic
world with exact ground truth: each test frame of the world rendered with ``--seed`` (the 200-frame world
``heldout.py`` scores the networks on) is the reference; its sources are the frames the model warps
(``model.source_offsets``: the odometry's motion between instants) and, with ``--rig-sources``, the rig's
other cameras at the same instant.

    python scripts/research/sweep_heldout.py [--matcher sgbm|sweep] [--seed 2001] [--rig kitti360]
                                             [--rig-sources] [--frames 16] [--hypotheses 128] [--cost zncc]
                                             [--min-distance 0.5] [--max-distance 80] [--world-frames 200]

Prints, over the frames, on the pixels ``eval.py`` scores (the ``full`` protocol): the checked output's
abs_rel and a1 on the pixels it keeps and its coverage; the same on the *resolvable* pixels only (where a
10 % change of the distance moves the point by at least one pixel in some source that sees it: a camera
moving forward leaves the focus of expansion without parallax); and the dense output, beside the
constant map at the median distance of the pixels scored. Then the checked output's ceiling: the median
relative error of the pixels it keeps, and their mean once every pixel off by more than 25 % is left out
(what a perfect outlier filter would leave). Never tuned on the held-out worlds (``--seed 0 --world-frames
600``: the training world ``make train`` renders).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import NamedTuple

import torch

from fisheyedepth.cameras.rays import RayCache
from fisheyedepth.cli import prepare_data
from fisheyedepth.evaluation import PROTOCOLS, Evaluator
from fisheyedepth.geometry.se3 import transform_points
from fisheyedepth.plan import data_plan
from fisheyedepth.stereo import (
    SgbmSettings,
    SweepMatcher,
    SweepSettings,
    View,
    fuse,
    match_pair,
    rectify_pair,
)
from fisheyedepth.stereo.scores import score

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # scripts/, for _compose
from _compose import build_datamodule, compose_config  # noqa: E402

FRAMES = 200  # the held-out worlds' length, as heldout.py renders them (--world-frames)
RAYS = RayCache()


def resolvable(camera, distance: torch.Tensor, sources: list[View], change: float = 0.1) -> torch.Tensor:
    """``[H, W]`` bool: pixels with truth whose point, moved ``change`` along its ray, moves at least one
    pixel in some source that sees it."""
    rays, has_ray = RAYS.get(camera)
    out = torch.zeros_like(has_ray)
    for source in sources:
        near = transform_points(source.T_ref_to_view, rays * distance[..., None])
        far = transform_points(source.T_ref_to_view, rays * (distance * (1 + change))[..., None])
        (uv_near, seen_near), (uv_far, seen_far) = source.camera.project(near), source.camera.project(far)
        w, h = source.camera.width, source.camera.height
        inside = (uv_near[..., 0] >= 0) & (uv_near[..., 0] <= w - 1) & (uv_near[..., 1] >= 0)
        inside &= uv_near[..., 1] <= h - 1
        out |= seen_near & seen_far & inside & ((uv_far - uv_near).norm(dim=-1) >= 1.0)
    return out & has_ray & (distance > 0)


class Result(NamedTuple):
    distance: torch.Tensor  # [1, H, W]
    dense: torch.Tensor
    confidence: torch.Tensor | None = None


def rectified(reference: View, sources: list[View], settings: SgbmSettings) -> Result:
    """The rectified pipeline on the reference against each source, fused."""
    maps = []
    for source in sources:
        T = source.T_ref_to_view.double().numpy()
        rect = rectify_pair(reference.camera, source.camera, T, settings, (True, False))
        maps.append(match_pair(reference.image, source.image, rect, settings, (True, False))[0])
    fused = fuse(maps)
    return Result(*(torch.from_numpy(x)[None] for x in (fused.distance, fused.dense, fused.confidence)))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seed", type=int, default=2001)
    parser.add_argument("--rig", default="kitti360")
    parser.add_argument(
        "--rig-sources", action="store_true", help="also the rig's other cameras, same instant"
    )
    parser.add_argument("--frames", type=int, default=16, help="test frames scored (spread over the split)")
    parser.add_argument("--matcher", choices=("sgbm", "sweep"), default="sgbm")
    parser.add_argument("--hypotheses", type=int, default=128)
    parser.add_argument("--cost", choices=("zncc", "census"), default="zncc")
    parser.add_argument("--min-distance", type=float, default=0.5)
    parser.add_argument("--max-distance", type=float, default=80.0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--world-frames", type=int, default=FRAMES, help="the world's length (its folder)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    world = [f"data.generate.rig={args.rig}", f"data.generate.seed={args.seed}"]
    world.append(f"data.generate.frames={args.world_frames}")
    cfg = compose_config(["data=synthetic", *world, "data.datamodule.size=null"])  # the rendered size
    prepare_data(data_plan(cfg))  # rendered on first use, as eval.py renders it
    dm = build_datamodule(cfg, rig_offsets=[0] if args.rig_sources else [])
    dataset = dm.dataset("test")  # with the frames the model warps
    step = max(1, len(dataset) // args.frames)
    sweep = SweepMatcher(SweepSettings(args.hypotheses, args.min_distance, args.max_distance, args.cost))
    settings = SgbmSettings(args.min_distance, args.max_distance)
    evaluator = Evaluator(PROTOCOLS["full"], ("none",), rays=RAYS)
    totals: dict[str, list] = {"checked": [], "resolvable": [], "dense": []}
    errors = []  # the checked output's relative error on every pixel it keeps
    confidences = []  # and its confidence there
    for index in range(0, len(dataset), step)[: args.frames]:
        sample = dataset[index]
        if "skipped" in sample or "distance" not in sample:
            raise ValueError(f"test frame {index}: {sample.get('skipped', 'no ground truth')}")
        camera, truth = sample["camera"], sample["distance"][0]
        reference = View(sample["image"][None], camera, torch.eye(4))
        cameras = sample.get("source_camera", [camera] * len(sample["sources"]))  # rig sources: theirs
        triples = zip(sample["sources"], cameras, sample["poses"], strict=True)
        sources = [View(image[None], cam, T) for image, cam, T in triples]
        if args.matcher == "sweep":
            result = sweep(reference, sources)
        else:
            result = rectified(reference, sources, settings)
        # the pixels eval.py scores (the "full" protocol: up to 80 m, not the ego vehicle's body, which
        # moves with the camera and so matches at the farthest hypothesis)
        scored = evaluator.scored(truth, sample["mask"][0] > 0.5, camera, sample.get("distance_source"))
        can = resolvable(camera, truth, sources) & scored
        checked = score(result.distance[0], truth, scored)
        kept = scored & (result.distance[0] > 0) & (truth > 0)
        errors.append(((result.distance[0][kept] - truth[kept]).abs() / truth[kept]).double())
        if result.confidence is not None:
            confidences.append(result.confidence[0][kept].double())
        kept_resolvable = score(result.distance[0], truth, can)
        dense = score(result.dense[0], truth, scored)
        for key, value in (("checked", checked), ("resolvable", kept_resolvable), ("dense", dense)):
            totals[key].append(value | {"resolvable": float(can.sum() / scored.sum())})
        print(f"{sample['frame']}: checked {checked['abs_rel']} on {checked['coverage']:.1%}; resolvable "
              f"{can.float().sum() / scored.sum():.1%}, checked there {kept_resolvable['abs_rel']} on "
              f"{kept_resolvable['coverage']:.1%}; dense {dense['abs_rel']}", flush=True)  # fmt: skip

    def mean(key: str, field: str) -> float:
        values = [r[field] for r in totals[key] if r[field] is not None]
        return sum(values) / len(values) if values else float("nan")

    sources = "time and rig" if args.rig_sources else "time"
    how = f"{args.hypotheses} hypotheses {args.cost}" if args.matcher == "sweep" else "rectified, SGBM"
    print(f"\nworld {args.rig} seed {args.seed}, {len(totals['checked'])} test frames, sources {sources}, "
          f"{how}:")  # fmt: skip
    print("| output | pixels | abs_rel | a1 | coverage | constant map there |")
    print("|---|---|---|---|---|---|")
    labels = {"checked": "checked, all pixels with truth", "resolvable": "checked, resolvable pixels",
              "dense": "dense, all pixels with truth"}  # fmt: skip
    for key, label in labels.items():
        print(f"| {label} | {mean(key, 'resolvable'):.1%} resolvable | {mean(key, 'abs_rel'):.4f} "
              f"| {mean(key, 'a1'):.3f} | {mean(key, 'coverage'):.1%} "
              f"| {mean(key, 'constant_abs_rel'):.4f} |")  # fmt: skip
    error = torch.cat(errors)
    inliers = error[error < 0.25]
    print(f"\nchecked output's ceiling: median relative error {float(error.median()):.3f}; without the "
          f"{1 - inliers.numel() / max(error.numel(), 1):.1%} of pixels off by more than 25 %, mean "
          f"{float(inliers.mean()):.3f}")  # fmt: skip
    if confidences:  # the kept pixels by confidence decile, lowest first
        confidence = torch.cat(confidences)
        order = torch.argsort(confidence)
        print("\nby confidence decile (lowest first): confidence from, abs_rel, share off by over 25 %")
        for part in torch.tensor_split(order, 10):
            print(
                f"  {float(confidence[part].min()):.3f}  {float(error[part].mean()):.3f}  "
                f"{float((error[part] > 0.25).double().mean()):.1%}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
