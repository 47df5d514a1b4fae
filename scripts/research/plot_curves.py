#!/usr/bin/env python
"""Per-epoch validation curves of training runs: does every row learn, and has it flattened?

    python scripts/research/plot_curves.py RUN_OR_SWEEP_OR_RECORD [...] --out curves.png [--csv curves.csv]

Reads each run's ``logs/version_*/metrics.csv`` (a resumed run's versions are joined) and its
``.hydra/config.yaml`` for the experiment name, or a kept run's record (``docs/records/**/*.json``,
a file or a folder of them: its per-epoch ``curves``, ``experiment`` and ``seed``), and plots per
epoch: the self-supervised validation loss and photometric error (what model selection uses), the
PoseNet's rotation and translation-direction errors against the true relative poses (PoseNet rows
only), and the median-scaled abs_rel against the ground truth (for information: never used to
select). ``--csv`` writes the same numbers as a table.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from collections import defaultdict
from pathlib import Path

from fisheyedepth.utils import run_config

PANELS = (
    ("val/loss", "validation loss (self-supervised)"),
    ("val/photometric", "validation photometric error"),
    ("val/pose/rotation_deg", "PoseNet rotation error (deg)"),
    ("val/pose/direction_deg", "PoseNet translation direction error (deg)"),
    ("val/pose/reversed", "PoseNet translations pointing backwards (fraction)"),
    ("val/scaled/abs_rel", "abs_rel, median-scaled (GT, report only)"),
    ("val/abs_rel", "abs_rel, unscaled (GT, report only)"),
)


def records_under(path: Path) -> list[Path]:
    """Run records with per-epoch curves at or below ``path`` (see make_tables.py)."""
    from make_tables import records_under as under

    return [f for f in under(path) if json.loads(f.read_text())["curves"]]


def runs_under(paths: list[str]) -> list[Path]:
    """Run folders (those holding ``logs/``) and run records at or below each path."""
    out: list[Path] = []
    for p in map(Path, paths):
        found = (
            []
            if p.is_file()
            else sorted({m.parents[2] for m in p.rglob("metrics.csv") if m.parent.parent.name == "logs"})
        )
        if p.suffix == ".json" or not found:
            found += records_under(p)
        out += [r for r in found if r not in out]
    return out


def run_name(run: Path) -> str:
    if run.is_file():  # a record
        record = json.loads(run.read_text())
        seed = "?" if record.get("seed") is None else record["seed"]
        return f"{record.get('experiment') or run.stem} s{seed}"
    cfg = run_config(run)
    return f"{cfg.get('experiment_name', run.name)} s{cfg.get('seed', '?')}" if cfg else run.name


def curves(run: Path) -> dict[str, dict[int, float]]:
    """``{metric: {epoch: value}}`` of the validation metrics, over every log version of the run (or
    from its record)."""
    out: dict[str, dict[int, float]] = defaultdict(dict)
    if run.is_file():
        table = json.loads(run.read_text())["curves"]
        for key, _ in PANELS:
            for epoch, value in zip(table.get("epoch", []), table.get(key, []), strict=False):
                if value is not None:
                    out[key][int(epoch)] = float(value)
        return out
    for metrics in sorted((run / "logs").glob("*/metrics.csv")) + sorted((run / "logs").glob("metrics.csv")):
        with metrics.open() as handle:
            for row in csv.DictReader(handle):
                if not row.get("epoch"):
                    continue
                for key, _ in PANELS:
                    if row.get(key) not in (None, ""):
                        out[key][int(float(row["epoch"]))] = float(row[key])
    return out


def main(argv=None) -> int:
    formatter = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=formatter)
    parser.add_argument("runs", nargs="+", help="run folders, sweep folders, run records or their folders")
    parser.add_argument("--out", required=True, help="PNG to write")
    parser.add_argument("--csv", help="also write the numbers as CSV")
    parser.add_argument("--labels", nargs="+", help="one label per run, in order (default: experiment)")
    args = parser.parse_args(argv)
    runs = runs_under(args.runs)
    if not runs:
        print(f"no runs with logs/*/metrics.csv or run records under {args.runs}", file=sys.stderr)
        return 2
    if args.labels and len(args.labels) != len(runs):
        print(f"--labels: {len(args.labels)} labels for {len(runs)} runs", file=sys.stderr)
        return 2
    names = args.labels or [run_name(r) for r in runs]
    data = {
        (f"{name} ({run.name})" if names.count(name) > 1 else name): curves(run)
        for name, run in zip(names, runs, strict=True)
    }

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [(k, title) for k, title in PANELS if any(k in c for c in data.values())]
    cols = min(4, len(shown))
    rows = -(-len(shown) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    for ax in axes.flat[len(shown) :]:
        ax.axis("off")
    for ax, (key, title) in zip(axes.flat, shown, strict=False):
        for i, (name, c) in enumerate(data.items()):  # tab20: a row's two seeds in a dark/light pair
            if key in c:
                epochs = sorted(c[key])
                style = {"color": plt.cm.tab20(i % 20), "linestyle": "-" if i < 20 else "--"}
                ax.plot(epochs, [c[key][e] for e in epochs], marker="o", ms=3, label=name, **style)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("epoch")
        ax.grid(alpha=0.3)
    axes.flat[0].legend(fontsize=7)
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out} ({len(data)} runs)")
    if args.csv:
        with open(args.csv, "w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(["run", "metric", "epoch", "value"])
            for name, c in data.items():
                for key, values in c.items():
                    for epoch in sorted(values):
                        writer.writerow([name, key, epoch, f"{values[epoch]:.6g}"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
