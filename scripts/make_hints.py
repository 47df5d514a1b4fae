#!/usr/bin/env python
"""Write distance hints for a dataset's training split (``model.hint_weight``, Depth Hints).

    python scripts/make_hints.py ROOT [--layout kitti360] [--split splits/train.txt] [--size 256 256]
        [--offsets -2 2] [--source-baseline 1.67] [--out FOLDER] [--candidates 48] [--window 7]
        [--ratio 0.8] [--agree 2] [--overwrite]

For each target frame of the split, a plane sweep over ``--candidates`` log-spaced distances along the
fisheye rays against its sources (the training's: the same ``--offsets`` and ``--source-baseline``)
gives a hint where the match is unique and the sources agree (:func:`fisheyedepth.losses.plane_sweep`).
Hints are written to ``OUT/<sequence>/<camera>/<key>.npy`` (float16 metres, 0 = none; OUT defaults to
``ROOT/hints_<W>x<H>``) with the settings in ``OUT/settings.json``. Existing hints are kept and the
run goes on where it stopped; other settings than the folder's are refused unless ``--overwrite``.
Ground truth, where the dataset has it, is only read for the report at the end (coverage, and the
hints' abs_rel and share within 1.25x of it): the hints never see it. Train with
``data.datamodule.hints=OUT model.hint_weight=1``.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from fisheyedepth.cameras import RayCache
from fisheyedepth.data import FisheyeDataset, collate, hint_path
from fisheyedepth.data.datamodule import LAYOUTS
from fisheyedepth.losses import candidate_distances, plane_sweep
from fisheyedepth.utils import atomic_write_bytes, atomic_write_text


def parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("root")
    p.add_argument("--layout", default="kitti360", choices=sorted(LAYOUTS))
    p.add_argument("--split", default="splits/train.txt")
    p.add_argument("--size", type=int, nargs=2, metavar=("W", "H"), default=None)
    p.add_argument("--offsets", type=int, nargs="+", default=[-2, 2])
    p.add_argument("--source-baseline", type=float, default=None)
    p.add_argument("--out", default=None)
    p.add_argument("--candidates", type=int, default=48)
    p.add_argument("--min-distance", type=float, default=0.5)
    p.add_argument("--max-distance", type=float, default=80.0)
    p.add_argument("--window", type=int, default=7)
    p.add_argument("--ratio", type=float, default=0.8)
    p.add_argument("--agree", type=int, default=2)
    p.add_argument(
        "--overwrite", action="store_true", help="recompute existing hints, replace other settings"
    )
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    layout = LAYOUTS[args.layout](args.root, None, None)
    size = tuple(args.size) if args.size else None
    dataset = FisheyeDataset(
        layout,
        args.split,
        size=size,
        offsets=tuple(args.offsets),
        ground_truth="auto",
        source_baseline=args.source_baseline,
    )
    if len(dataset) == 0:
        raise SystemExit(f"{args.root}: split {args.split} has no frame with sources")
    first = dataset[0]["camera"]
    out = Path(args.out or Path(args.root) / f"hints_{first.width}x{first.height}")
    settings = {k: v for k, v in vars(args).items() if k not in ("out", "overwrite")}
    settings_path = out / "settings.json"
    if settings_path.is_file() and not args.overwrite:
        old = json.loads(settings_path.read_text())
        if old != settings:
            changed = sorted(k for k in set(old) | set(settings) if old.get(k) != settings.get(k))
            raise SystemExit(
                f"{settings_path}: written with other settings ({', '.join(changed)}); use --overwrite"
            )
    atomic_write_text(settings_path, json.dumps(settings, indent=1) + "\n")
    candidates = candidate_distances(args.min_distance, args.max_distance, args.candidates).float()
    rays = RayCache()
    report: dict[str, list[float]] = {}
    for item in tqdm(range(len(dataset)), desc="hints", unit="frame"):
        entry = dataset.items[item]
        key = layout.frames(entry.sequence, entry.camera)[entry.row].key
        path = hint_path(out, entry.sequence, entry.camera, key)
        sample = dataset[item]
        if path.is_file() and not args.overwrite:
            hint = torch.from_numpy(np.load(path, allow_pickle=False).astype(np.float32))[None]
            valid = hint > 0
        else:
            batch = collate([sample])
            r, rv = rays.batch(batch.camera, "cpu", torch.float32)
            hint, valid = plane_sweep(
                batch.image,
                batch.sources,
                batch.poses,
                r,
                rv & (batch.mask[:, 0] > 0.5),
                batch.source_camera,
                batch.source_mask,
                candidates,
                args.window,
                args.ratio,
                args.agree,
            )
            buffer = io.BytesIO()
            np.save(buffer, hint[0].numpy().astype(np.float16))
            atomic_write_bytes(path, buffer.getvalue())
        stats = report.setdefault(entry.camera, [0, 0, 0, 0.0, 0])
        usable = sample["mask"][0] > 0.5
        stats[0] += int(usable.sum())
        stats[1] += int((valid[0] & usable).sum())
        if "distance" in sample:
            gt, h = sample["distance"][0], hint[0].float()
            scored = valid[0] & usable & (gt > 0)
            stats[2] += int(scored.sum())
            stats[3] += float(((h - gt).abs() / gt)[scored].sum())
            stats[4] += int((torch.maximum(h / gt, gt / h) < 1.25)[scored].sum())
    lines = {}
    for camera, (n, v, m, rel, good) in sorted(report.items()):
        lines[camera] = {"coverage": v / max(n, 1)}
        if "distance" in sample:  # over the hints that have ground truth (not the sky's)
            lines[camera].update(scored=m / max(v, 1), abs_rel=rel / max(m, 1), within_1_25=good / max(m, 1))
        print(camera, " ".join(f"{k} {x:.3f}" for k, x in lines[camera].items()))
    atomic_write_text(out / "report.json", json.dumps(lines, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
