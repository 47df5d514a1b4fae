#!/usr/bin/env python
"""Collect results.json files into the paper's Table 1 and Table 2 (Markdown, and LaTeX with --latex).

    python scripts/research/make_tables.py outputs/ multirun/ [--protocol full] [--tables 1 2] [--latex]
        [--out F]
    python scripts/research/make_tables.py docs/records/table2_world34_e20
        [--heldout heldout_kitti360_seed1001]

Each argument is a results.json file, a run record (``docs/records/**/*.json``: one JSON per kept run,
its final results, held-out results, overrides and per-epoch curves) or a folder searched recursively
for both. ``--heldout NAME`` tabulates the runs' scores on a held-out world instead: a run folder's
``NAME/results.json``, a record's ``heldout[NAME]``. Rows are matched by experiment
name; with several runs of one experiment (seeds) the metrics are averaged and the count is shown.
Real-scale methods are scored unscaled; scale-less ones (PoseNet) median-scaled, and DNet with its
camera-height scale recovery. The paper's KITTI-360 numbers are printed alongside for reference.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

METRICS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")
PAPER = {
    "table1_dnet": (0.558, 1.746, 1.802, 0.560, 0.443, 0.691, 0.838),
    "table1_fsnet": (0.464, 1.117, 1.125, 0.339, 0.613, 0.768, 0.868),
    "table1_fsnet_rs": (0.435, 1.012, 0.937, 0.309, 0.633, 0.792, 0.871),
    "ablation_baseline": (0.602, 1.804, 1.788, 0.563, 0.426, 0.685, 0.835),
    "ablation_fft_only": (0.205, 0.547, 1.066, 0.266, 0.726, 0.903, 0.971),
    "ablation_fft_rs": (0.115, 0.672, 1.163, 0.173, 0.912, 0.972, 0.987),
    "ablation_fft_mc": (0.126, 0.647, 1.150, 0.180, 0.893, 0.969, 0.987),
    "ablation_full": (0.106, 0.407, 0.927, 0.170, 0.920, 0.975, 0.989),
}
# Table 1's Monodepth2 and FisheyeDepth rows are Table 2's baseline and full model: one experiment each
TABLE1 = [
    ("ablation_baseline", "Monodepth2"),
    ("table1_dnet", "DNet"),
    ("table1_fsnet", "FSNet"),
    ("table1_fsnet_rs", "FSNet (real scale)"),
    ("ablation_full", "FisheyeDepth"),
]
TABLE2 = [
    ("ablation_baseline", "Monodepth2 baseline"),
    ("ablation_fft_only", "FFT"),
    ("ablation_fft_rs", "FFT + RS"),
    ("ablation_fft_mc", "FFT + MC"),
    ("ablation_full", "FFT + RS + MC"),
]


def is_record(data) -> bool:
    """A kept run's record (``docs/records``), as opposed to a ``results.json``."""
    return isinstance(data, dict) and "format" in data and "curves" in data and "heldout" in data


def records_under(path: Path) -> list[Path]:
    """The run records at or below ``path`` (a record file or a folder of them), sorted."""
    files = [path] if path.is_file() else sorted(path.rglob("*.json"))
    out = []
    for f in files:
        if f.name.startswith("results") and f.parent.name != "records":
            continue  # a run folder's results.json
        try:
            if is_record(json.loads(f.read_text())):
                out.append(f)
        except (OSError, ValueError):
            continue
    return out


def find(paths: list[str]) -> list[Path]:
    """results.json files and run records at or below each path."""
    out = []
    for p in map(Path, paths):
        if p.is_file():
            out.append(p)
            continue
        out += sorted(p.rglob("results*.json")) + records_under(p)
    return out


def load_results(files: list[Path], heldout: str | None = None) -> list[dict]:
    """The results (``results.json`` content) each file holds: a record's final results or, with
    ``heldout``, its score on that held-out world; a results.json as it is (with ``heldout``, only one
    inside a folder of that name). Files without such results are left out."""
    out = []
    for f in files:
        data = json.loads(f.read_text())
        if is_record(data):
            res = data["heldout"].get(heldout) if heldout else data["results"]
        else:
            res = data if heldout is None or f.parent.name == heldout else None
        if res is not None:
            out.append(res)
    return out


def scaling_for(record: dict) -> str:
    if record["experiment"] == "table1_dnet":
        return "dnet"
    return "none" if record["model"]["real_scale"] else "median"


def spread_of(values: list[float]) -> float | None:
    """Sample standard deviation over seeds (None for a single run)."""
    if len(values) < 2:
        return None
    mean = sum(values) / len(values)
    return (sum((v - mean) ** 2 for v in values) / (len(values) - 1)) ** 0.5


def cell(r: dict, m: str) -> str:
    sd = r.get("spread", {}).get(m)
    return f"{r['metrics'][m]:.3f}" + ("" if sd is None else f"±{sd:.3f}")


def collect(records: list[dict], protocol: str) -> dict[str, dict]:
    """Table rows from results (``load_results``), keyed by experiment."""
    runs: dict[str, list] = defaultdict(list)
    for record in records:
        res = record["results"].get(protocol)
        if res is None:
            continue
        scaling = scaling_for(record)
        if scaling not in res:
            continue
        runs[record["experiment"]].append((scaling, res[scaling], res.get(f"{scaling}_by_angle", {})))
    rows = {}
    for name, entries in runs.items():
        mean = {m: sum(e[1][m] for e in entries) / len(entries) for m in METRICS}
        spread = {m: spread_of([e[1][m] for e in entries]) for m in METRICS}
        angle = {}
        for b in entries[0][2]:
            vals = [e[2][b]["abs_rel"] for e in entries if e[2].get(b, {}).get("images")]
            angle[b] = sum(vals) / len(vals) if vals else float("nan")
        rows[name] = {
            "scaling": entries[0][0],
            "runs": len(entries),
            "metrics": mean,
            "spread": spread,
            "abs_rel_by_angle": angle,
        }
    return rows


def markdown(title: str, spec, rows: dict) -> str:
    head = (
        "| method | scaling | runs | "
        + " | ".join(METRICS)
        + " | abs_rel by incidence 0-30/30-60/60-90/>90 | paper abs_rel / a1 |"
    )
    lines = [f"### {title}", "", head, "|" + "---|" * (len(METRICS) + 5)]
    if any(r.get("spread", {}).get("abs_rel") is not None for r in rows.values()):
        lines.insert(1, "\nMean over seeds ± their standard deviation.")
    for key, label in spec:
        paper = PAPER[key]
        if key not in rows:
            lines.append(
                f"| {label} | - | 0 | "
                + " | ".join("-" for _ in METRICS)
                + f" | - | {paper[0]:.3f} / {paper[4]:.3f} |"
            )
            continue
        r = rows[key]
        angles = "/".join(f"{v:.3f}" for v in r["abs_rel_by_angle"].values())
        lines.append(
            f"| {label} | {r['scaling']} | {r['runs']} | "
            + " | ".join(cell(r, m) for m in METRICS)
            + f" | {angles} | {paper[0]:.3f} / {paper[4]:.3f} |"
        )
    return "\n".join(lines) + "\n"


def latex(title: str, spec, rows: dict) -> str:
    lines = [
        f"% {title}",
        "\\begin{tabular}{l" + "c" * len(METRICS) + "}",
        "\\hline",
        "Method & Abs Rel & Sq Rel & RMSE & RMSE$_{\\log}$ & "
        "$\\delta<1.25$ & $\\delta<1.25^2$ & $\\delta<1.25^3$ \\\\",
        "\\hline",
    ]
    for key, label in spec:
        if key in rows:
            lines.append(
                f"{label} & " + " & ".join(f"{rows[key]['metrics'][m]:.3f}" for m in METRICS) + " \\\\"
            )
    lines += ["\\hline", "\\end{tabular}"]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", help="results.json files, run records or folders")
    parser.add_argument("--protocol", default="full")
    parser.add_argument(
        "--heldout", metavar="NAME", help="score on this held-out world, e.g. heldout_kitti360_seed1001"
    )
    parser.add_argument("--latex", action="store_true")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--tables", nargs="+", default=["1", "2"], choices=["1", "2"])
    args = parser.parse_args(argv)
    results = load_results(find(args.runs), args.heldout)
    if not results:
        print(f"no results.json or run record under {args.runs}", file=sys.stderr)
        return 2
    rows = collect(results, args.protocol)
    text = f"Protocol: {args.protocol}; {len(results)} results files.\n\n"
    if args.heldout:
        text = f"Held-out world: {args.heldout}. " + text
    specs = {"1": ("Table 1", TABLE1), "2": ("Table 2 (ablation)", TABLE2)}
    chosen = [specs[t] for t in args.tables]
    text += "\n".join(markdown(title, spec, rows) for title, spec in chosen)
    if args.latex:
        text += "\n```latex\n" + "".join(latex(title, spec, rows) for title, spec in chosen) + "```\n"
    print(text)
    if args.out:
        from fisheyedepth.files import atomic_write_text

        atomic_write_text(args.out, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
