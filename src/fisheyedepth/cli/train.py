"""``python train.py [+experiment=...]``: train, then evaluate the selected checkpoint on the test
split: the last one (``select=last``, the default: the end of the schedule) or the one with the lowest
self-supervised validation loss (``select=best``). Neither uses ground truth."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig

from ..checkpoints import CheckpointError, check_resumable, weights_mismatch
from ..config import (
    check_options,
    configured_model,
    named_option,
    resolve_base_focal,
    resolve_precision,
    rig_offsets,
    source_offsets,
)
from . import EXIT_SIGTERM, INPUT_ERRORS, prepare_data, prepare_process
from .run_folder import run_folder

log = logging.getLogger("fisheyedepth")
SELECT = ("last", "best")


def selected_checkpoint(callbacks: list[Any], select: str) -> str | None:
    """The checkpoint to test, from the run's ``ModelCheckpoint`` callbacks: ``last`` is the end of
    the schedule (the unmonitored one, saved every epoch; as Monodepth2 evaluates), ``best`` has the
    lowest monitored self-supervised validation loss. None: the weights in memory (no checkpoint)."""
    if select not in SELECT:
        raise ValueError(f"select={select!r}: expected one of {SELECT}")
    monitored = [c for c in callbacks if getattr(c, "monitor", None)]
    if select == "best":
        if not monitored:
            raise ValueError("select=best needs a ModelCheckpoint with a monitor (callbacks.checkpoint)")
        return monitored[0].best_model_path or None
    latest = [c for c in callbacks if not getattr(c, "monitor", None)]
    if latest:
        return latest[0].best_model_path or None  # unmonitored: its one kept checkpoint is the newest
    return None  # the weights in memory are the last ones


def build_model(cfg: DictConfig, **resolved):
    """The configured module, its option groups passed as plain dicts (the optimiser and scheduler are
    built when training starts); an option it refuses is named ``model.<group>.<option>`` (Hydra wraps
    the error)."""
    try:
        return instantiate(cfg.model, **resolved, _convert_="all", _recursive_=False)
    except InstantiationException as exc:
        cause = exc.__cause__
        if not isinstance(cause, INPUT_ERRORS):
            raise
        message = str(cause.args[0] if cause.args else cause)
        named = named_option(cfg, message) if isinstance(cause, ValueError) else None
        if named is not None:
            raise ValueError(named) from None
        raise cause from None


def train(cfg: DictConfig) -> dict[str, Any] | None:
    out_dir = Path(cfg.paths.output_dir)
    check_options(cfg)  # sizes, switches and numbers by kind and range, before any folder, render or fit
    ckpt_path = cfg.get("ckpt_path")
    # the model's class (and Lightning with it) is imported only for a checkpoint that can be resumed
    resumed = check_resumable(ckpt_path, lambda: configured_model(cfg)) if ckpt_path else None
    with run_folder(out_dir, ckpt_path):  # one run per folder; before any checkpoint is touched
        return fit_and_test(cfg, out_dir, resumed)


def fit_and_test(cfg: DictConfig, out_dir: Path, resumed: dict[str, Any] | None) -> dict[str, Any] | None:
    select = cfg.get("select", "last")
    prepare_process(cfg)
    prepare_data(cfg)
    # Lightning, the module and the metrics (about 4 s to import) only now: a refused folder, checkpoint
    # or option above is answered at once
    import lightning as L
    from lightning.pytorch.callbacks import ModelCheckpoint
    from lightning.pytorch.utilities.exceptions import SIGTERMException

    from ..module import FisheyeDepthModule
    from ..training import AtomicCheckpointIO
    from .evaluate import run_evaluation

    L.seed_everything(cfg.seed, workers=True)
    offsets = {"offsets": source_offsets(cfg), "rig_offsets": rig_offsets(cfg)}
    datamodule = instantiate(cfg.data.datamodule, **offsets)
    resolved = {}
    if cfg.model.net.get("base_focal") == "auto":  # stored as a number in the checkpoint's hparams
        resolved["net"] = {"base_focal": resolve_base_focal(datamodule, resumed)}
    module = build_model(cfg, **resolved)
    if resumed is not None and (mismatch := weights_mismatch(module.state_dict(), resumed["state_dict"])):
        raise CheckpointError(cfg.ckpt_path, f"cannot resume it with this model: weights {mismatch}")
    logger = instantiate(cfg.logger) if cfg.get("logger") else False
    callbacks = [instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c is not None]
    checkpointers = [c for c in callbacks if isinstance(c, ModelCheckpoint)]
    selected_checkpoint(checkpointers, select)  # a bad choice fails now, not after hours of training
    precision = resolve_precision(cfg.trainer.get("precision"), cfg.trainer.get("accelerator"))
    trainer: L.Trainer = instantiate(
        cfg.trainer,
        logger=logger,
        callbacks=callbacks,
        default_root_dir=str(out_dir),
        precision=precision,
        plugins=[AtomicCheckpointIO()],  # a kill while saving leaves the previous checkpoint whole
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
            ckpt = selected_checkpoint(checkpointers, select)
            tested = FisheyeDepthModule.from_checkpoint(ckpt) if ckpt else module
            record = run_evaluation(
                cfg,
                tested,
                datamodule,
                out_dir,
                ckpt,
                {
                    "resumed_from": cfg.get("ckpt_path"),
                    "global_step": trainer.global_step,
                    "select": select,
                    "skipped_batches": module.skipped_batches,
                },
                device=trainer.strategy.root_device,  # a checkpoint loads on the CPU
            )
        return record
    finally:
        if logger and type(logger).__name__ == "WandbLogger":
            import wandb

            wandb.finish()  # one wandb run per job, also inside a multirun sweep
