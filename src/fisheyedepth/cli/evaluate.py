"""``python eval.py ckpt_path=PATH [split=test] [data=...]``: a checkpoint on a split with ground truth,
at the ground truth's native resolution, into ``results.json``."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path
from typing import Any

import yaml
from hydra.utils import instantiate
from omegaconf import DictConfig
from rich.console import Console
from rich.table import Table

from ..evaluation import evaluate
from ..module import FisheyeDepthModule
from ..utils import atomic_write_text
from . import free_path, prepare_data


def _git_commit() -> str | None:
    try:
        return subprocess.run(
            ["git", "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
            cwd=Path(__file__).parent,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def print_table(results: dict[str, Any], title: str) -> None:
    """The headline rows, then one row per camera when the split has more than one (mixed rigs)."""
    keys = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")
    table = Table(title=title)
    for col in ("protocol", "scaling", "camera", *keys, "images"):
        table.add_column(col, justify="right")
    for name, res in results.items():
        for scaling in (k for k in res if k in ("none", "median", "dnet")):
            rows = {"all": res[scaling]}
            per_camera = res.get(f"{scaling}_by_camera", {})
            if len(per_camera) > 1:
                rows |= per_camera
            for camera, m in rows.items():
                table.add_row(name, scaling, camera, *(f"{m[k]:.3f}" for k in keys), str(m["images"]))
    Console(width=140).print(table)


def run_evaluation(
    cfg: DictConfig,
    module: FisheyeDepthModule,
    datamodule,
    out_dir: Path,
    ckpt: str | None,
    extra: dict[str, Any],
    split: str = "test",
) -> dict[str, Any]:
    """Evaluate ``split`` at the ground truth's native resolution, the network at the size it was
    trained at (its checkpoint's ``input_size``); write ``results.json``."""
    train_size = module.hparams.get("input_size") or datamodule.size
    native = instantiate(cfg.data.datamodule, size=None, augment=None, batch_size=4, num_workers=0)
    loader = native.dataloader(split)
    results = evaluate(
        module,
        loader,
        train_size,
        list(cfg.eval.protocols),
        list(cfg.eval.scalings),
        cfg.eval.get("camera_height"),
        out_dir / "predictions",
        int(cfg.eval.pictures),
    )
    record = {
        "experiment": cfg.get("experiment_name"),
        "checkpoint": ckpt,
        "model": {
            k: module.hparams[k] for k in ("fisheye_projection", "real_scale", "multi_channel", "attention")
        }
        | {"upsample": module.depth_net.upsample},
        "data": str(cfg.data.datamodule.root),
        "split": split,
        "train_size": list(train_size) if train_size else None,
        "results": results,
        "commit": _git_commit(),
        "written": time.strftime("%Y-%m-%d %H:%M:%S"),
        **extra,
    }
    path = free_path(out_dir / "results.json")  # a resumed run keeps the earlier run's results
    atomic_write_text(path, json.dumps(record, indent=2) + "\n")
    print_table(results, f"{record['experiment']}: {path}")
    return record


def experiment_of(ckpt_path: str | Path) -> str | None:
    """The experiment a checkpoint was trained by, from its run folder's ``.hydra/config.yaml``
    (``RUN/checkpoints/X.ckpt``); None when the checkpoint sits elsewhere."""
    config = Path(ckpt_path).resolve().parent.parent / ".hydra" / "config.yaml"
    if not config.is_file():
        return None
    try:
        data = yaml.safe_load(config.read_text())
    except yaml.YAMLError as err:
        raise ValueError(f"{config}: not readable YAML ({err})") from err
    return data.get("experiment_name") if isinstance(data, dict) else None


def eval_checkpoint(cfg: DictConfig) -> dict[str, Any]:
    out_dir = Path(cfg.paths.output_dir)
    experiment = cfg.get("experiment_name") or experiment_of(cfg.ckpt_path)
    prepare_data(cfg)
    module = FisheyeDepthModule.from_checkpoint(cfg.ckpt_path).to(cfg.get("device", "cpu"))
    if cfg.get("upsample") is not None:  # only how a distance at the training size reaches the GT's size
        module.depth_net.upsample = str(cfg.upsample)  # recorded in results.json
    datamodule = instantiate(cfg.data.datamodule)
    return run_evaluation(
        cfg,
        module,
        datamodule,
        out_dir,
        str(cfg.ckpt_path),
        {"experiment": experiment},
        str(cfg.get("split", "test")),
    )
