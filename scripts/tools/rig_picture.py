#!/usr/bin/env python
"""One picture of a rig: for every camera of a rig layout, one frame and the checkpoint's metric distance
for it (log colour scale, black = no ray in the camera model), side by side with a colour bar.

    python scripts/tools/rig_picture.py --ckpt RUN/checkpoints/last.ckpt --rig data/aria_gen2_rig \\
        --out docs/figures/aria_rig_predictions.png [--frame 4] [--vmin 0.3] [--vmax 10] [--scale 0.5]
        [--overwrite]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch

from fisheyedepth.cli import CommandParser
from fisheyedepth.data.layouts import RigLayout
from fisheyedepth.files import atomic_write_png
from fisheyedepth.images import read_image
from fisheyedepth.inference import DistancePredictor, colour_bar
from fisheyedepth.module import FisheyeDepthModule
from fisheyedepth.signals import ends_on_signals
from fisheyedepth.viz import colourise


@ends_on_signals  # SIGINT / SIGTERM: one line, exit 130 / 143
def main(argv=None) -> int:
    parser = CommandParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", required=True)
    parser.add_argument("--rig", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--sequence", default=None, help="default: the first")
    parser.add_argument("--frame", type=int, default=4, help="index of the frame in each camera's sequence")
    parser.add_argument("--vmin", type=float, default=0.3)
    parser.add_argument("--vmax", type=float, default=10.0)
    parser.add_argument("--scale", type=float, default=1.0, help="resize the picture (0.5: half size)")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    if args.out.exists() and not args.overwrite:
        raise SystemExit(f"error: {args.out} exists; pass --overwrite to replace it")
    layout = RigLayout(args.rig)
    sequence = args.sequence or layout.sequences()[0]
    module = FisheyeDepthModule.from_checkpoint(args.ckpt)
    columns = []
    for name, spec in layout.cameras.items():
        frame = layout.frames(sequence, name)[args.frame]
        bgr = read_image(layout.image(sequence, name, frame)).bgr
        rgb = torch.from_numpy(bgr[..., ::-1].copy()).permute(2, 0, 1)[None].float() / 255.0
        distance = DistancePredictor(module, spec.camera)(rgb)[0, 0].numpy()
        colour = colourise(distance, args.vmin, args.vmax, invalid=~np.isfinite(distance))[..., ::-1]
        cv2.putText(bgr, name, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2)
        columns.append(np.concatenate([bgr, colour], axis=0))
        print(f"{name}: median distance {np.nanmedian(distance):.2f} m")
    picture = np.concatenate(columns, axis=1)
    picture = colour_bar(picture[..., ::-1], args.vmin, args.vmax)[..., ::-1]
    if args.scale != 1.0:
        size = (round(picture.shape[1] * args.scale), round(picture.shape[0] * args.scale))
        picture = cv2.resize(picture, size, interpolation=cv2.INTER_AREA)
    atomic_write_png(args.out, picture)
    print(f"written {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
