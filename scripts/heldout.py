#!/usr/bin/env python
"""Score trained runs on synthetic worlds they never saw, one Markdown row per run (BENCHMARKS.md,
"Time to accuracy").

    python scripts/heldout.py RUN [RUN ...] [--seeds 1001 1002] [--rig kitti360] [--upsample logits]
                              [--post-process flip] [--lane left] [--set KEY=VALUE ...]

RUN is a ``train.py`` output folder. Its ``results.json`` gives the score on its own world's test
split; its ``checkpoints/last.ckpt`` (the end of the schedule, no ground truth used to pick it) is then
scored by ``eval.py`` on the test split of the world rendered with each held-out seed (200 frames,
rendered on first use), into ``RUN/heldout_<rig>_seed<S>/results.json`` (``..._flip`` with
``--post-process flip``, Monodepth2's post-processing); an existing one is reused.
``--lane left`` scores the same worlds with the car in the left lane (rendered into
``synthetic_<rig>_<size>_seed<S>_f200_laneleft``, scored into ``..._laneleft``): the side cameras trade
the near kerb for the far side of the street. ``--set`` passes more Hydra overrides to ``eval.py``
(e.g. ``paths.data_dir=...``). Numbers: full-range abs_rel and a1, then kitti360-protocol abs_rel, all
unscaled (real scale). Choose the held-out seeds before training, and never train or tune on them: the
seed of the world the run trained on (its ``.hydra/config.yaml``, ``data.generate``) is refused for its
rig, in either lane.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import yaml

from fisheyedepth.runtimes import POST_PROCESSING
from fisheyedepth.utils import run_config

ROOT = Path(__file__).resolve().parents[1]
FRAMES = 200  # the held-out worlds as they were named, whatever the training default (--set may differ)


def scores(path: Path) -> str:
    """``abs_rel, a1 / kitti360 abs_rel`` of a results.json, or why there is none."""
    try:
        results = json.loads(path.read_text())["results"]
        full, k360 = results["full"]["none"], results["kitti360"]["none"]
        return f"{full['abs_rel']:.3f}, {full['a1']:.3f} / {k360['abs_rel']:.3f}"
    except (OSError, ValueError, KeyError) as err:
        return f"({path}: {type(err).__name__})"


def trained_world(run: Path) -> tuple[str, int] | None:
    """The rig and seed of the synthetic world ``run`` trained on (None: no synthetic world recorded)."""
    gen = (run_config(run).get("data") or {}).get("generate") or {}
    return (str(gen.get("rig", "kitti360")), int(gen["seed"])) if "seed" in gen else None


def synthetic_root() -> str:
    """The synthetic world's folder as ``conf/data/synthetic.yaml`` names it (Hydra interpolations kept)."""
    return str(yaml.safe_load((ROOT / "conf" / "data" / "synthetic.yaml").read_text())["datamodule"]["root"])


def score_heldout(
    run: Path,
    seed: int,
    rig: str,
    upsample: str | None,
    extra: list[str],
    post_process: str = "none",
    lane: str = "right",
) -> Path:
    """Evaluate the run's last checkpoint on world ``seed``; returns its results.json."""
    if trained_world(run) == (rig, seed):  # the 200-frame world is the start of a longer one's drive
        # (in either lane: the other lane drives the same streets)
        raise ValueError(f"{run}: world {seed} ({rig}) is the world it trained on, not a held-out one")
    suffix = (f"_{upsample}" if upsample else "") + (f"_{post_process}" if post_process != "none" else "")
    suffix += "_laneleft" if lane == "left" else ""
    out = run / f"heldout_{rig}_seed{seed}{suffix}"
    if (out / "results.json").is_file():
        return out / "results.json"
    ckpt = run / "checkpoints" / "last.ckpt"
    if not ckpt.is_file():
        raise FileNotFoundError(f"{ckpt}: no last checkpoint in this run")
    command = [
        sys.executable,
        str(ROOT / "eval.py"),
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
        command += ["++data.generate.lane=left", f"data.datamodule.root={synthetic_root()}_laneleft"]
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
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="more eval.py overrides")
    args = parser.parse_args(argv)
    lane = ", left lane" if args.lane == "left" else ""
    header = ["run", "own test", *(f"world {s} (held out{lane})" for s in args.seeds)]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for run in args.runs:
        cells = [run.name, scores(run / "results.json")]
        for seed in args.seeds:
            try:
                cells.append(
                    scores(
                        score_heldout(
                            run, seed, args.rig, args.upsample, args.set, args.post_process, args.lane
                        )
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
