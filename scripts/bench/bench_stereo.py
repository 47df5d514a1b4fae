#!/usr/bin/env python
"""Sweep stereo beside OpenCV's StereoSGBM; results go into BENCHMARKS.md (between this script's markers).

1. Middlebury 2014 Motorcycle (real photographs, scikit-image; 741x500 rectified pinhole pair with exact
   disparity): the census sweep (``--hypotheses``, default 128) and StereoSGBM (128 disparities, 5x5
   blocks) on the same pair, one thread each, taking turns round by round: their seconds, the ratio, and
   both scored against the ground truth (abs_rel, a1 and coverage of what each keeps, and the sweep's
   dense map on every pixel).
2. A 640x480 fisheye pair (two KITTI-360-like Mei cameras 0.2 m apart, turned 30 degrees, the sweep's
   test room): the sweep's seconds with the same settings.

Usage: python scripts/bench/bench_stereo.py [--hypotheses 128] [--rounds 2] [--threads 1]
           [--no-write] [--quick]
"""

from __future__ import annotations

import datetime
import platform
import statistics
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

from fisheyedepth.cameras.rays import compute_rays
from fisheyedepth.data.kitti360 import kitti360_camera
from fisheyedepth.stereo import SweepStereo
from fisheyedepth.stereo.pairs import MOTORCYCLE, motorcycle

from _benchmarks import bench_parser, interleaved, markers, parse_args, publish

START, END = markers("bench_stereo")
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))  # the sweep tests' textured room

from stereo_world import pair as room_pair  # noqa: E402
from stereo_world import pose, scores  # noqa: E402


def sgbm_distance(pair) -> torch.Tensor:
    left, right = (
        (v.image[0].permute(1, 2, 0).numpy() * 255).astype(np.uint8) for v in (pair.reference, pair.source)
    )
    sgbm = cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=128, blockSize=5, P1=8 * 3 * 25, P2=32 * 3 * 25, uniquenessRatio=5,
        disp12MaxDiff=1,
    )  # fmt: skip
    disparity = sgbm.compute(left, right).astype(np.float32) / 16
    c = MOTORCYCLE
    z = np.where(disparity > 0, c["f"] * c["baseline"] / (disparity + c["doffs"]), 0.0)
    rays, _ = compute_rays(pair.reference.camera)
    return torch.from_numpy(z).float() / rays[..., 2]


def main(argv=None) -> None:
    parser = bench_parser(__doc__)
    parser.add_argument("--hypotheses", type=int, default=128)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1)
    args = parse_args(parser, argv, quick={"hypotheses": 16, "rounds": 1})
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    pair = motorcycle()
    sweep = SweepStereo(hypotheses=args.hypotheses, min_distance=1.5, max_distance=10.0, cost="census")
    results = {}
    times = interleaved(
        {
            "sweep": lambda: results.__setitem__("sweep", sweep(pair.reference, [pair.source])),
            "sgbm": lambda: results.__setitem__("sgbm", sgbm_distance(pair)),
        },
        args.rounds,
        warmup=0 if args.quick else 1,
    )
    sweep_s, sgbm_s = statistics.median(times["sweep"]), statistics.median(times["sgbm"])
    ours, dense, theirs = (
        scores(results["sweep"].distance, pair.distance[None]),
        scores(results["sweep"].dense, pair.distance[None]),
        scores(results["sgbm"][None], pair.distance[None]),
    )

    camera = kitti360_camera(2).resize(640, 480)
    reference, source, _ = room_pair(camera, camera, pose(), pose(30.0, (0.2, 0.0, 0.0)))
    fisheye_sweep = SweepStereo(hypotheses=args.hypotheses, min_distance=0.3, max_distance=20.0)
    fisheye_s = statistics.median(
        interleaved({"": lambda: fisheye_sweep(reference, [source])}, 1, warmup=0)[""]
    )

    def row(name, score, seconds):
        cells = f"{score['abs_rel']:.4f} | {score['a1']:.3f} | {100 * score['coverage']:.1f} %"
        return f"| {name} | {cells} | {seconds} |"

    today = datetime.date.today().isoformat()
    lines = [
        START,
        f"### Sweep stereo beside StereoSGBM ({today}, {platform.machine()}, {args.threads} thread(s))",
        "",
        f"`python scripts/bench/bench_stereo.py --hypotheses {args.hypotheses} --threads {args.threads}`: "
        "Middlebury 2014 Motorcycle, 741x500 (real photographs, scikit-image), scored against its exact "
        "disparity; each method's kept pixels, seconds the median of the rounds taken in turns.",
        "",
        "| method | abs_rel | a1 | coverage | seconds |",
        "|---|---|---|---|---|",
        row(f"sweep, census 7x7, {args.hypotheses} hypotheses, round-trip check", ours, f"{sweep_s:.2f}"),
        row("the same before the check (dense)", dense, "-"),
        row("OpenCV StereoSGBM, 128 disparities, 5x5", theirs, f"{sgbm_s:.3f}"),
        "",
        f"The sweep takes {sweep_s / sgbm_s:.0f}x StereoSGBM's time on this pair. A 640x480 fisheye pair "
        f"(Mei, 0.2 m apart, turned 30 degrees; ZNCC 11x11, {args.hypotheses} hypotheses, round trip): "
        f"{fisheye_s:.1f} s.",
        END,
    ]
    publish("\n".join(lines) + "\n", args.output, START, END, not args.no_write)


if __name__ == "__main__":
    main()
