#!/usr/bin/env python
"""Reproduce Tables 1 and 2 on the synthetic world at a CPU budget, and write them into BENCHMARKS.md.

    python scripts/research/reproduce.py [--epochs 20] [--size 96] [--tables 1 2] [--seeds 0 1]
        [--world-seed 34]
    python scripts/research/reproduce.py --runs RUN_OR_SWEEP... [--tables 2]   # trained elsewhere
    python scripts/research/reproduce.py --runs docs/records/table2_world34_e20   # the kept runs' records

Runs ``train.py -m`` over the experiments and seeds (each trains, then evaluates its last checkpoint,
selected without ground truth, on the test split into results.json), then ``make_tables.py`` on the
sweep folder (mean and spread over seeds), and ``plot_curves.py``: every row's validation loss,
photometric error and PoseNet pose errors per epoch, written beside the tables
(``docs/figures/reproduce_curves.png``), so a row that has not flattened is seen, not guessed.

The budget is the one every Table 2 row converges in (BENCHMARKS.md): 96x96 input, 20 epochs, the
learning rate decayed x0.1 after 80 % of them (``--lr-step``, 16 of 20). On 2 CPU cores one run takes
15-45 minutes; ``--runs`` builds the tables and the figure from runs trained in parallel (other
processes, a cluster) with the same overrides, without training anything, or from the kept runs'
records (``docs/records``: their results, overrides and per-epoch curves).

The world is the synthetic kitti360 rig (200 frames: the tables' kept runs) rendered with ``--world-seed``,
34 by default: its training segment turns (180 degrees over 57 frames) and so does its validation
segment (46 degrees). In the default world (seed 0) the training segment drives straight while the
validation segment turns, so a PoseNet never sees a rotation in training and its validation
photometric error stays flat, whatever its depth does (BENCHMARKS.md).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import shutil
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import yaml

import make_tables
import plot_curves
from make_tables import find, is_record, load_results

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))  # scripts/bench/, for _benchmarks
from _benchmarks import publish  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
START, END = "<!-- reproduce:start -->", "<!-- reproduce:end -->"
FIGURE = ROOT / "docs" / "figures" / "reproduce_curves.png"
TABLES = {
    "1": ["ablation_baseline", "table1_dnet", "table1_fsnet", "table1_fsnet_rs", "ablation_full"],
    "2": ["ablation_baseline", "ablation_fft_only", "ablation_fft_rs", "ablation_fft_mc", "ablation_full"],
}


def _check(main, argv: list[str]) -> None:
    """Run another script's ``main`` in this process (no second interpreter start); stop on failure."""
    code = main(argv)
    if code:
        raise SystemExit(f"{main.__module__}.py {' '.join(argv)}: exit status {code}")


def _printed(main, argv: list[str]) -> str:
    """What another script's ``main`` prints, run in this process."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        _check(main, argv)
    return out.getvalue()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--epochs", type=int, default=20)
    parser.add_argument("--lr-step", type=int, default=None, help="lr decay epoch; default 80%% of --epochs")
    parser.add_argument("--size", type=int, default=96, help="square training input, pixels")
    parser.add_argument("--runs", nargs="+", type=Path, help="tabulate these runs; train nothing")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "reproduce", help="sweeps and figures")
    parser.add_argument("--tables", nargs="+", default=["1", "2"], choices=sorted(TABLES))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--world-seed", type=int, default=34, help="the synthetic world (its turns)")
    parser.add_argument("--extra", nargs="*", default=[], help="more Hydra overrides for every run")
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args(argv)
    experiments = list(dict.fromkeys(e for t in args.tables for e in TABLES[t]))  # shared rows run once
    lr_step = args.lr_step if args.lr_step is not None else round(0.8 * args.epochs)
    budget = [
        f"trainer.max_epochs={args.epochs}",
        f"model.scheduler.step_size={lr_step}",
        f"data.datamodule.size=[{args.size},{args.size}]",
        f"data.generate.seed={args.world_seed}",
        "data.generate.frames=200",  # the tables' world (make train's default renders more)
    ]
    if args.runs:
        missing = [str(r) for r in args.runs if not r.exists()]
        if missing:
            parser.error(f"--runs: no such run or sweep folder: {', '.join(missing)}")
        sweep = args.out / time.strftime("%Y-%m-%d_%H-%M-%S_runs")  # the figure, not the runs
        sweep.mkdir(parents=True)
        sources, minutes = [str(r) for r in args.runs], None
    else:
        sweep = args.out / time.strftime("%Y-%m-%d_%H-%M-%S")
        sources = [str(sweep)]
        cmd = [
            sys.executable,
            str(ROOT / "train.py"),
            "-m",
            f"+experiment={','.join(experiments)}",
            f"seed={','.join(map(str, args.seeds))}",
            *budget,
            f"hydra.sweep.dir={sweep}",
            *args.extra,
        ]
        t0 = time.time()
        subprocess.run(cmd, check=True, cwd=ROOT)
        minutes = (time.time() - t0) / 60
    tables_of = [*sources, "--tables", *args.tables]
    tables = _printed(make_tables.main, [*tables_of, "--protocol", "full"])
    reference = _printed(make_tables.main, [*tables_of, "--protocol", "kitti360"])
    figure = sweep / "curves.png"
    _check(plot_curves.main, [*sources, "--out", str(figure), "--csv", str(figure.with_suffix(".csv"))])
    if not args.no_write:
        FIGURE.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(figure, FIGURE)
    tables_arg = " ".join(args.tables)
    seeds = " ".join(map(str, args.seeds))
    if args.runs:
        command = f"python scripts/research/reproduce.py --runs {' '.join(sources)} --tables {tables_arg}"
        where = "tables and curves of runs trained beforehand with the overrides below"
    else:
        command = (
            f"python scripts/research/reproduce.py --epochs {args.epochs} --lr-step {lr_step} "
            f"--size {args.size} --tables {tables_arg} --seeds {seeds} --world-seed {args.world_seed}"
        )
        where = f"{minutes:.0f} min, 2 CPU cores; runs in `{_shown(sweep)}`"
    if args.extra and not args.runs:
        command += " --extra " + " ".join(args.extra)
    if args.runs:  # what the runs were trained with, not this script's defaults
        budget = _shared_overrides(sources)
    section = (
        "\n".join(
            [
                START,
                "## Tables 1 and 2 on the synthetic world (`scripts/research/reproduce.py`)",
                "",
                f"Command: `{command}` ({where}).",
                f"Budget overrides of every run: `{' '.join(budget)}`.",
                f"Tested checkpoints (selected without ground truth): {_tested(sources)}. "
                "Real-scale methods are scored unscaled, PoseNet methods median-scaled, "
                "DNet with camera-height scale "
                "recovery. Full-range protocol:",
                "",
                tables,
                "KITTI-360 reference protocol (z in 0.3-60 m, range < 8 m):",
                "",
                reference,
                f"Validation curves of every run (`{FIGURE.relative_to(ROOT)}`):",
                "",
                f"![validation curves]({FIGURE.relative_to(ROOT)})",
                END,
            ]
        )
        + "\n"
    )
    publish(section, ROOT / "BENCHMARKS.md", START, END, write=not args.no_write)
    return 0


def _tested(sources: list[str]) -> str:
    """Which checkpoints the tables score, from the runs' results.json: e.g. ``last.ckpt x10``."""
    kinds = Counter(
        "best-NNN.ckpt" if name.startswith("best-") else name
        for name in (Path(r.get("checkpoint") or "in-memory").name for r in load_results(find(sources)))
    )
    return ", ".join(f"{k} x{n}" for k, n in sorted(kinds.items()))


PER_RUN = ("+experiment=", "experiment=", "seed=", "hydra.", "paths.")  # what differs between rows


def _shared_overrides(sources: list[str]) -> list[str]:
    """The Hydra overrides every run under ``sources`` was trained with (``.hydra/overrides.yaml``, or
    a run record's ``overrides``), less the row and seed; overrides that differ between runs are listed
    as ``KEY: differs``."""
    lists = []
    for source in map(Path, sources):
        files = (
            [source] if source.is_file() else sorted(source.rglob("*.yaml")) + sorted(source.rglob("*.json"))
        )
        for f in files:
            if f.name == "overrides.yaml" and f.parent.name == ".hydra":
                lists.append(yaml.safe_load(f.read_text()) or [])
            elif f.suffix == ".json" and not f.name.startswith("results"):
                data = json.loads(f.read_text())
                if is_record(data) and data["overrides"] is not None:
                    lists.append(data["overrides"])
    if not lists:
        return ["(no .hydra/overrides.yaml in the runs)"]
    runs = [{o.split("=", 1)[0]: o for o in overrides if not o.startswith(PER_RUN)} for overrides in lists]
    keys = list(dict.fromkeys(k for r in runs for k in r))
    return [runs[0][k] if all(r.get(k) == runs[0].get(k) for r in runs) else f"{k}: differs" for k in keys]


def _shown(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


if __name__ == "__main__":
    raise SystemExit(main())
