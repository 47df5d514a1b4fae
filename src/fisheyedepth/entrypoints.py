"""Hydra entry points (``train.py``, ``eval.py``): the only place configs become objects.

The library never sees an OmegaConf object: everything below is instantiated here and handed over as
plain Python values.
"""

from __future__ import annotations

import json
import logging
import subprocess
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from rich.console import Console
from rich.table import Table

from .data.synthetic import generate, is_complete
from .evaluation import evaluate
from .module import FisheyeDepthModule
from .utils import atomic_write_text

log = logging.getLogger("fisheyedepth")


def prepare_data(cfg: DictConfig) -> None:
    """Render the synthetic dataset on first use (``data.generate``); a finished one is reused."""
    gen = cfg.data.get("generate")
    if not gen:
        return
    root = Path(cfg.data.datamodule.root)
    if is_complete(root):
        return
    log.info("rendering the synthetic dataset into %s (first use)", root)
    generate(root, **OmegaConf.to_container(gen, resolve=True), overwrite=root.exists())


def load_module(path: str | Path) -> FisheyeDepthModule:
    """A trained module from a Lightning checkpoint, read with ``weights_only=True``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint not found")
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    if "state_dict" not in ckpt or "hyper_parameters" not in ckpt:
        raise ValueError(f"{path}: not a FisheyeDepth checkpoint (no state_dict / hyper_parameters)")
    module = FisheyeDepthModule(**dict(ckpt["hyper_parameters"]))
    module.load_state_dict(ckpt["state_dict"])
    return module


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
    table = Table(title=title)
    for col in ("protocol", "scaling", "abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3", "images"):
        table.add_column(col, justify="right")
    for name, res in results.items():
        for scaling in (k for k in res if k in ("none", "median", "dnet")):
            m = res[scaling]
            table.add_row(
                name,
                scaling,
                *(f"{m[k]:.3f}" for k in ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")),
                str(m["images"]),
            )
    Console(width=130).print(table)


def run_evaluation(
    cfg: DictConfig,
    module: FisheyeDepthModule,
    datamodule,
    out_dir: Path,
    ckpt: str | None,
    extra: dict[str, Any],
) -> dict[str, Any]:
    """Evaluate on the test split at the ground truth's native resolution; write ``results.json``."""
    train_size = datamodule.size
    native = instantiate(cfg.data.datamodule, size=None, augment=None, batch_size=4, num_workers=0)
    loader = native.test_dataloader()
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
        },
        "data": str(cfg.data.datamodule.root),
        "train_size": list(train_size) if train_size else None,
        "results": results,
        "commit": _git_commit(),
        "written": time.strftime("%Y-%m-%d %H:%M:%S"),
        **extra,
    }
    path = out_dir / "results.json"
    atomic_write_text(path, json.dumps(record, indent=2) + "\n")
    print_table(results, f"{record['experiment']}: {path}")
    return record


def train(cfg: DictConfig) -> dict[str, Any] | None:
    out_dir = Path(cfg.paths.output_dir)
    L.seed_everything(cfg.seed, workers=True)
    prepare_data(cfg)
    datamodule = instantiate(cfg.data.datamodule)
    module = instantiate(cfg.model, _convert_="all")
    logger = instantiate(cfg.logger) if cfg.get("logger") else False
    callbacks = [instantiate(c) for c in (cfg.get("callbacks") or {}).values()]
    trainer: L.Trainer = instantiate(
        cfg.trainer, logger=logger, callbacks=callbacks, default_root_dir=str(out_dir)
    )
    try:
        trainer.fit(module, datamodule=datamodule, ckpt_path=cfg.get("ckpt_path"))
        record = None
        if cfg.get("test") and trainer.is_global_zero and not trainer.fast_dev_run:
            ckpt = getattr(trainer.checkpoint_callback, "best_model_path", "") or None
            best = load_module(ckpt) if ckpt else module
            record = run_evaluation(
                cfg,
                best,
                datamodule,
                out_dir,
                ckpt,
                {
                    "resumed_from": cfg.get("ckpt_path"),
                    "global_step": trainer.global_step,
                    "skipped_batches": module.skipped_batches,
                },
            )
        return record
    finally:
        if logger and type(logger).__name__ == "WandbLogger":
            import wandb

            wandb.finish()  # one wandb run per job, also inside a multirun sweep


def eval_checkpoint(cfg: DictConfig) -> dict[str, Any]:
    out_dir = Path(cfg.paths.output_dir)
    prepare_data(cfg)
    module = load_module(cfg.ckpt_path).to(cfg.get("device", "cpu"))
    datamodule = instantiate(cfg.data.datamodule)
    return run_evaluation(cfg, module, datamodule, out_dir, str(cfg.ckpt_path), {})
