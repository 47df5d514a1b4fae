"""``python eval.py ckpt_path=PATH [split=test] [data=...]``: a checkpoint on a split with ground truth,
at the ground truth's native resolution, into ``results.json``."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path
from typing import Any

from hydra.utils import instantiate
from omegaconf import DictConfig
from rich.console import Console
from rich.table import Table

from ..evaluation import evaluate, scored_recording
from ..files import atomic_write_text
from ..options.kinds import SWITCH
from ..plan import Scoring, eval_plan
from ..runtimes import as_runtime
from ..utils import run_config
from . import free_path, load_runtime, prepare_data


def _git_commit() -> str | None:
    git = ["git", "-C", str(Path(__file__).parent), "rev-parse", "HEAD"]
    try:
        return subprocess.run(git, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def print_table(results: dict[str, Any], title: str) -> None:
    """The headline rows, then one row per camera when the split has more than one (mixed rigs), then
    the static and the moving pixels apart when the split has moving objects (synthetic traffic); a
    line below for each protocol that left images unscored (no ground truth in its range)."""
    keys = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")
    table = Table(title=title)
    for col in ("protocol", "scaling", "pixels", *keys, "images"):
        table.add_column(col, justify="right")
    for name, res in results.items():
        for scaling in (k for k in res if k in ("none", "median", "dnet")):
            rows = {"all": res[scaling]}
            per_camera = res.get(f"{scaling}_by_camera", {})
            if len(per_camera) > 1:
                rows |= per_camera
            motion = res.get(f"{scaling}_by_motion", {})
            if motion.get("moving", {}).get("images"):
                rows |= {"static pixels": motion["static"], "moving pixels": motion["moving"]}
            for camera, m in rows.items():
                cells = ("-" if m[k] is None else f"{m[k]:.3f}" for k in keys)
                table.add_row(name, scaling, camera, *cells, str(m["images"]))
    console = Console(width=140)
    console.print(table)
    for name, res in results.items():
        if res.get("unscored_images"):
            console.print(
                f"{name}: {res['unscored_images']} image(s) with no ground truth in range, not scored"
            )


def run_evaluation(
    scoring: Scoring,
    model,
    datamodule,
    out_dir: Path,
    ckpt: str | None,
    extra: dict[str, Any],
    split: str = "test",
    device=None,
    rerun: bool = False,
) -> dict[str, Any]:
    """Evaluate ``split`` by ``scoring`` at the ground truth's native resolution, the network at the size
    it was trained at (its checkpoint's ``input_size``) or exported at; write ``results.json``. ``model``: a
    trained module (run on ``device``, default the module's), or a runtime (an ONNX file, bf16) of
    :mod:`fisheyedepth.runtimes`. ``rerun``: also ``recording.rrd`` (:mod:`fisheyedepth.evaluation`)."""
    runtime = as_runtime(model, device=device)
    if runtime.input_size is None and datamodule.size:  # a checkpoint that stored no input size
        runtime.input_size = tuple(datamodule.size)
    train_size = runtime.input_size
    offsets, rig = runtime.sources or ((), ())
    loader = datamodule.scoring_loader(split, offsets=offsets, rig_offsets=rig)
    recorded = free_path(out_dir / "recording.rrd") if rerun else None  # an earlier run's is kept
    with scored_recording(recorded) as recording:
        results = evaluate(
            runtime,
            loader,
            train_size,
            list(scoring.protocols),
            list(scoring.scalings),
            scoring.camera_height,
            out_dir / "predictions",
            scoring.pictures,
            f"{scoring.data} ({split} split)",
            recording,
        )
    record = {
        "experiment": scoring.experiment,
        "checkpoint": ckpt,
        "model": runtime.describe(),
        "data": scoring.data,
        "split": split,
        "train_size": list(train_size) if train_size else None,
        "results": results,
        "commit": _git_commit(),
        "written": time.strftime("%Y-%m-%d %H:%M:%S"),
        **extra,
    }
    if recorded is not None:
        record["recording"] = str(recorded)
    path = free_path(out_dir / "results.json")  # a resumed run keeps the earlier run's results
    atomic_write_text(path, json.dumps(record, indent=2) + "\n")
    print_table(results, f"{record['experiment']}: {path}")
    return record


def experiment_of(ckpt_path: str | Path) -> str | None:
    """The experiment a checkpoint was trained by, from its run folder's ``.hydra/config.yaml``
    (``RUN/checkpoints/X.ckpt``); None when the checkpoint sits elsewhere."""
    return run_config(Path(ckpt_path).resolve().parent.parent).get("experiment_name")


def eval_checkpoint(cfg: DictConfig) -> dict[str, Any]:
    """``ckpt_path`` in PyTorch (``precision`` fp32 or bf16), or ``runtime=onnx model=FILE.onnx``."""
    plan = eval_plan(cfg)
    prepare_data(plan.data)
    datamodule = instantiate(plan.data.datamodule, **plan.data.arguments())
    model, ckpt = load_runtime(plan.runtime), plan.runtime.checkpoint
    if ckpt is None:  # an exported file
        experiment = plan.scoring.experiment or Path(plan.runtime.model_file).stem
    else:
        experiment = plan.scoring.experiment or experiment_of(ckpt) or Path(ckpt).stem
    extra = {"experiment": experiment}
    SWITCH.check("rerun", cfg.get("rerun", False))
    return run_evaluation(
        plan.scoring,
        model,
        datamodule,
        plan.output_dir,
        ckpt,
        extra,
        plan.split,
        rerun=cfg.get("rerun", False),
    )
