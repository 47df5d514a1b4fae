"""``python train.py [+experiment=...]``: train, then evaluate the checkpoint with the lowest
self-supervised validation loss on the test split."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import lightning as L
from hydra.utils import instantiate
from lightning.pytorch.utilities.exceptions import SIGTERMException
from omegaconf import DictConfig

from ..checkpoints import check_resumable
from ..module import FisheyeDepthModule
from . import EXIT_SIGTERM, prepare_data
from .evaluate import run_evaluation

log = logging.getLogger("fisheyedepth")


def train(cfg: DictConfig) -> dict[str, Any] | None:
    out_dir = Path(cfg.paths.output_dir)
    if cfg.get("ckpt_path"):
        check_resumable(cfg.ckpt_path)
    L.seed_everything(cfg.seed, workers=True)
    prepare_data(cfg)
    datamodule = instantiate(cfg.data.datamodule)
    module = instantiate(cfg.model, _convert_="all")
    logger = instantiate(cfg.logger) if cfg.get("logger") else False
    callbacks = [instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c is not None]
    trainer: L.Trainer = instantiate(
        cfg.trainer, logger=logger, callbacks=callbacks, default_root_dir=str(out_dir)
    )
    try:
        try:
            trainer.fit(module, datamodule=datamodule, ckpt_path=cfg.get("ckpt_path"))
        except SIGTERMException:
            # Lightning stops at a batch boundary and raises SystemExit(None), i.e. exit 0: a job
            # scheduler, make or a shell script would take the run for finished.
            last = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
            log.error(
                "terminated by SIGTERM at step %d; no results.json. Resume with ckpt_path=%s",
                trainer.global_step,
                last if last.is_file() else "<a checkpoint of this run>",
            )
            raise SystemExit(EXIT_SIGTERM) from None
        record = None
        if cfg.get("test") and trainer.is_global_zero and not trainer.fast_dev_run:
            ckpt = getattr(trainer.checkpoint_callback, "best_model_path", "") or None
            best = FisheyeDepthModule.from_checkpoint(ckpt) if ckpt else module
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
