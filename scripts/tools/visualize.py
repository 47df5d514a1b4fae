#!/usr/bin/env python
"""Look at what a model sees: panels for a dataset split, and abs_rel against the angle of incidence.

    python scripts/tools/visualize.py --ckpt outputs/train/<run>/checkpoints/last.ckpt [--ckpt OTHER ...] \\
        --data data/synthetic_kitti360_256_seed0_f200 [--data-config synthetic] [--split test] [--out viz] \\
        [--panels 8] [--set KEY=VALUE ...]

The dataset is read as ``train.py data=<--data-config>`` reads it (``conf/data/``: synthetic, kitti360 or
rig), with ``--data`` as its root and ``--set`` as more Hydra overrides
(``data.datamodule.cameras=[image_02]``).

Writes ``panel_XXX.png`` (input | predicted distance | ground truth | relative error) for the first
checkpoint and ``abs_rel_by_angle.png``: one bar group per angle bin (0-30, 30-60, 60-90, >90 degrees)
and one bar per checkpoint. Comparing a fisheye model with a pinhole one shows where fisheye geometry pays.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from fisheyedepth.cli import CommandParser  # noqa: E402
from fisheyedepth.evaluation import ANGLE_BINS, evaluate  # noqa: E402
from fisheyedepth.module import FisheyeDepthModule  # noqa: E402
from fisheyedepth.signals import ends_on_signals  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # scripts/, for _compose
from _compose import ROOT, build_datamodule, compose_config  # noqa: E402

DATA_CONFIGS = sorted(p.stem for p in (ROOT / "conf" / "data").glob("*.yaml"))


@ends_on_signals  # SIGINT / SIGTERM: one line, exit 130 / 143
def main(argv=None) -> int:
    parser = CommandParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", action="append", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument(
        "--data-config", default="synthetic", choices=DATA_CONFIGS, help="conf/data/NAME.yaml"
    )
    parser.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE", help="more Hydra overrides")
    parser.add_argument("--split", default="test")
    parser.add_argument("--protocol", default="full")
    parser.add_argument("--out", type=Path, default=Path("viz"))
    parser.add_argument("--panels", type=int, default=8)
    args = parser.parse_args(argv)
    cfg = compose_config([f"data={args.data_config}", *args.set], {"data.datamodule.root": args.data})
    dm = build_datamodule(cfg)
    labels, scores = [], []
    for i, ckpt in enumerate(args.ckpt):
        module = FisheyeDepthModule.from_checkpoint(ckpt)
        size = module.hparams.get("input_size")
        loader = dm.scoring_loader(args.split)
        res = evaluate(
            module,
            loader,
            tuple(size) if size else None,
            [args.protocol],
            ("none", "median"),
            pictures=args.out if i == 0 else None,
            n_pictures=args.panels,
        )[args.protocol]
        scaling = "none" if module.pose_net is None else "median"  # real-scale poses: no PoseNet
        labels.append(f"{Path(ckpt).parent.parent.name} ({scaling})")
        bands = res[f"{scaling}_by_angle"]  # a band without pixels has no number (None): no bar
        values = [bands[f"{lo}-{hi}"]["abs_rel"] for lo, hi in ANGLE_BINS]
        scores.append([float("nan") if v is None else v for v in values])
    fig, ax = plt.subplots(figsize=(7, 4))
    width = 0.8 / len(scores)
    for k, (label, vals) in enumerate(zip(labels, scores, strict=True)):
        ax.bar([b + k * width for b in range(len(ANGLE_BINS))], vals, width, label=label)
    ax.set_xticks([b + 0.4 - width / 2 for b in range(len(ANGLE_BINS))])
    ax.set_xticklabels([f"{lo}-{hi}°" if hi < 180 else f">{lo}°" for lo, hi in ANGLE_BINS])
    ax.set_xlabel("angle of incidence")
    ax.set_ylabel("abs_rel")
    ax.set_title(f"{args.split} split, {args.protocol} protocol")
    ax.legend()
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out / "abs_rel_by_angle.png", dpi=120)
    print(f"wrote {args.out / 'abs_rel_by_angle.png'} and the panels in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
