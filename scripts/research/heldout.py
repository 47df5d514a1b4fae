#!/usr/bin/env python
"""Score trained runs on synthetic worlds they never saw, one Markdown row per run (BENCHMARKS.md,
"Time to accuracy").

    python scripts/research/heldout.py RUN [RUN ...] [--seeds 1001 1002] [--rig kitti360] [--upsample logits]
                                       [--post-process flip] [--lane left] [--traffic] [--set KEY=VALUE ...]
    python scripts/research/heldout.py --from-records RECORD_OR_FOLDER [...] [--seeds ...] [--rig ...] [...]

RUN is a ``train.py`` output folder. Its ``results.json`` gives the score on its own world's test
split; its ``checkpoints/last.ckpt`` (the end of the schedule, no ground truth used to pick it) is then
scored by ``eval.py`` on the test split of the world rendered with each held-out seed (200 frames,
rendered on first use), into ``RUN/heldout_<rig>_seed<S>/results.json`` (``..._flip`` with
``--post-process flip``, Monodepth2's post-processing); an existing one is reused.
``--lane left`` scores the same worlds with the car in the left lane (rendered into
``synthetic_<rig>_<size>_seed<S>_f200_laneleft``, scored into ``..._laneleft``): the side cameras trade
the near kerb for the far side of the street. ``--set`` passes more Hydra overrides to ``eval.py``
(e.g. ``paths.data_dir=...``). ``--traffic`` scores the worlds of ``data=synthetic_traffic`` (moving
cars and pedestrians, camera effects; scored into ``..._traffic``) and prints full-range abs_rel on the
static pixels, then on the moving ones; ``--curves`` (with ``--from-records``) adds the first and the
last validation photometric error and abs_rel of each record's curves (that the run learned). Numbers
otherwise: full-range abs_rel and a1, then kitti360-protocol abs_rel, all unscaled (real scale).
``--from-records`` prints the same rows from kept run records (``docs/records/**/*.json``, their
``results`` and ``heldout`` scores) and scores nothing: a world a record was not scored on reads ``(not
scored)``. Choose the held-out seeds before training, and never train or tune on them: the seed of the
world the run trained on (its ``.hydra/config.yaml``, ``data.generate``) is refused for its rig, in
either lane.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import yaml

from fisheyedepth.options.tables import POST_PROCESSING
from fisheyedepth.utils import run_config

ROOT = Path(__file__).resolve().parents[2]
FRAMES = 200  # the held-out worlds as they were named, whatever the training default (--set may differ)


def formatted(results: dict) -> str:
    """``abs_rel, a1 / kitti360 abs_rel`` of a results.json's ``results``."""
    full, k360 = results["full"]["none"], results["kitti360"]["none"]
    return f"{full['abs_rel']:.3f}, {full['a1']:.3f} / {k360['abs_rel']:.3f}"


def formatted_motion(results: dict) -> str:
    """``static abs_rel / moving abs_rel`` (full range, unscaled) of a results.json's ``results``."""
    motion = results["full"]["none_by_motion"]
    moving = motion["moving"]["abs_rel"]
    return f"{motion['static']['abs_rel']:.3f} / " + ("-" if moving is None else f"{moving:.3f}")


def scores(path: Path, traffic: bool = False) -> str:
    """The cells of a results.json (:func:`formatted`, or :func:`formatted_motion`), or why there are none."""
    try:
        results = json.loads(path.read_text())["results"]
        return formatted_motion(results) if traffic else formatted(results)
    except (OSError, ValueError, KeyError) as err:
        return f"({path}: {type(err).__name__})"


def folder_name(
    rig: str, seed: int, upsample: str | None, post_process: str, lane: str, traffic: bool = False
) -> str:
    """The held-out score's folder in a run (its key in a record's ``heldout``)."""
    suffix = (f"_{upsample}" if upsample else "") + (f"_{post_process}" if post_process != "none" else "")
    suffix += ("_laneleft" if lane == "left" else "") + ("_traffic" if traffic else "")
    return f"heldout_{rig}_seed{seed}{suffix}"


def learned(curves: dict) -> list[str]:
    """``first -> last`` of a record's validation photometric error and abs_rel."""
    return [
        f"{curves[k][0]:.4f} -> {curves[k][-1]:.4f}" if curves.get(k) else "-"
        for k in ("val/photometric", "val/abs_rel")
    ]


def record_rows(paths: list[Path], seeds: list[int], *where, curves: bool = False) -> list[list[str]]:
    """The table's rows from run records (``docs/records``): nothing is scored."""
    from make_tables import records_under

    rows = []
    for record_file in (f for p in paths for f in records_under(p)):
        record = json.loads(record_file.read_text())
        own = record["results"]
        show = formatted_motion if where[-1] else formatted
        cells = [record["name"].rsplit("/", 1)[-1], show(own["results"]) if own else "(no results)"]
        for seed in seeds:
            held = record["heldout"].get(folder_name(where[0], seed, *where[1:]))
            cells.append(show(held["results"]) if held else "(not scored)")
        rows.append(cells + (learned(record["curves"] or {}) if curves else []))
    return rows


def trained_world(run: Path) -> tuple[str, int] | None:
    """The rig and seed of the synthetic world ``run`` trained on (None: no synthetic world recorded)."""
    gen = (run_config(run).get("data") or {}).get("generate") or {}
    return (str(gen.get("rig", "kitti360")), int(gen["seed"])) if "seed" in gen else None


def synthetic_root(traffic: bool = False) -> str:
    """The synthetic world's folder as ``conf/data/synthetic.yaml`` (``synthetic_traffic.yaml``) names
    it (Hydra interpolations kept)."""
    name = "synthetic_traffic.yaml" if traffic else "synthetic.yaml"
    return str(yaml.safe_load((ROOT / "conf" / "data" / name).read_text())["datamodule"]["root"])


def score_heldout(
    run: Path,
    seed: int,
    rig: str,
    upsample: str | None,
    extra: list[str],
    post_process: str = "none",
    lane: str = "right",
    traffic: bool = False,
) -> Path:
    """Evaluate the run's last checkpoint on world ``seed``; returns its results.json."""
    if trained_world(run) == (rig, seed):  # the 200-frame world is the start of a longer one's drive
        # (in either lane: the other lane drives the same streets)
        raise ValueError(f"{run}: world {seed} ({rig}) is the world it trained on, not a held-out one")
    out = run / folder_name(rig, seed, upsample, post_process, lane, traffic)
    if (out / "results.json").is_file():
        return out / "results.json"
    ckpt = run / "checkpoints" / "last.ckpt"
    if not ckpt.is_file():
        raise FileNotFoundError(f"{ckpt}: no last checkpoint in this run")
    command = [
        sys.executable,
        str(ROOT / "eval.py"),
        *(["data=synthetic_traffic"] if traffic else []),
        f"ckpt_path={ckpt}",
        f"data.generate.rig={rig}",
        f"data.generate.seed={seed}",
        f"hydra.run.dir={out}",
        "eval.pictures=4",
    ]
    if not any(o.startswith("data.generate.frames=") for o in extra):
        command.append(f"data.generate.frames={FRAMES}")
    if upsample:
        command.append(f"upsample={upsample}")
    if post_process != "none":
        command.append(f"post_process={post_process}")
    if lane == "left":  # its own world folder: the right lane's must never be read for it
        command += ["++data.generate.lane=left", f"data.datamodule.root={synthetic_root(traffic)}_laneleft"]
    command += extra
    subprocess.run(command, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    return out / "results.json"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--seeds", nargs="+", type=int, default=[1001, 1002])
    parser.add_argument("--rig", default="kitti360")
    parser.add_argument("--upsample", choices=("distance", "logits"))
    parser.add_argument("--post-process", choices=POST_PROCESSING, default="none")
    parser.add_argument("--lane", choices=("right", "left"), default="right", help="the car's lane")
    parser.add_argument(
        "--traffic", action="store_true", help="worlds with traffic; abs_rel on static / moving pixels"
    )
    parser.add_argument(
        "--curves", action="store_true", help="with --from-records: first and last validation scores"
    )
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="more eval.py overrides")
    parser.add_argument(
        "--from-records", action="store_true", help="RUNs are run records or folders of them: score nothing"
    )
    args = parser.parse_args(argv)
    lane = (", left lane" if args.lane == "left" else "") + (", traffic" if args.traffic else "")
    header = ["run", "own test", *(f"world {s} (held out{lane})" for s in args.seeds)]
    if args.curves:
        if not args.from_records:
            parser.error("--curves reads the records' curves: use it with --from-records")
        header += ["val photometric first -> last", "val abs_rel first -> last"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    if args.from_records:
        where = (args.rig, args.upsample, args.post_process, args.lane, args.traffic)
        for cells in record_rows(args.runs, args.seeds, *where, curves=args.curves):
            print("| " + " | ".join(cells) + " |")
        return 0
    for run in args.runs:
        cells = [run.name, scores(run / "results.json", args.traffic)]
        for seed in args.seeds:
            try:
                cells.append(
                    scores(
                        score_heldout(
                            run,
                            *(seed, args.rig, args.upsample, args.set, args.post_process, args.lane),
                            args.traffic,
                        ),
                        args.traffic,
                    )
                )
            except FileNotFoundError as err:  # a kept record without its checkpoint, not yet scored here
                cells.append(f"({err})")
            except ValueError as err:  # its own training world
                print(f"error: {err}", file=sys.stderr)
                return 2
        print("| " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
