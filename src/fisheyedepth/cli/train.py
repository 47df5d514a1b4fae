"""``python train.py [+experiment=...]``: train, then evaluate the selected checkpoint on the test
split: the last one (``select=last``, the default: the end of the schedule) or the one with the lowest
self-supervised validation loss (``select=best``). Neither uses ground truth."""

from __future__ import annotations

import logging
import sys
from typing import Any

from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig

from ..checkpoints import CheckpointError, weights_mismatch
from ..config import named_option, resolve_base_focal
from ..plan import ModelPlan, TrainPlan, check_select, describe_accelerator, train_plan
from ..signals import EXIT_SIGINT, EXIT_SIGTERM, sigterm_left_alone
from . import INPUT_ERRORS, prepare_data, prepare_process
from .run_folder import run_folder

log = logging.getLogger("fisheyedepth")


def selected_checkpoint(callbacks: list[Any], select: str) -> str | None:
    """The checkpoint to test, from the run's ``ModelCheckpoint`` callbacks: ``last`` is the end of
    the schedule (the unmonitored one, saved every epoch; as Monodepth2 evaluates), ``best`` has the
    lowest monitored self-supervised validation loss. None: the weights in memory (no checkpoint)."""
    check_select(select)
    monitored = [c for c in callbacks if getattr(c, "monitor", None)]
    if select == "best":
        if not monitored:
            raise ValueError("select=best needs a ModelCheckpoint with a monitor (callbacks.checkpoint)")
        return monitored[0].best_model_path or None
    latest = [c for c in callbacks if not getattr(c, "monitor", None)]
    if latest:
        return latest[0].best_model_path or None  # unmonitored: its one kept checkpoint is the newest
    return None  # the weights in memory are the last ones


def build_model(model: ModelPlan, **resolved):
    """The planned module, its option groups passed as plain dicts (``resolved`` over them; the optimiser
    and scheduler are built when training starts); an option it refuses is named
    ``model.<group>.<option>`` (Hydra wraps the error)."""
    try:
        config = {"_target_": model.target, **model.arguments(**resolved)}
        return instantiate(config, _convert_="all", _recursive_=False)
    except InstantiationException as exc:
        cause = exc.__cause__
        if not isinstance(cause, INPUT_ERRORS):
            raise
        message = str(cause.args[0] if cause.args else cause)
        named = named_option(model.configured(), message) if isinstance(cause, ValueError) else None
        if named is not None:
            raise ValueError(named) from None
        raise cause from None


def train(cfg: DictConfig) -> dict[str, Any] | None:
    plan = train_plan(cfg)  # every option, choice and the resumed checkpoint checked: nothing made yet
    with run_folder(plan.output_dir, plan.resume):  # one run per folder; before any checkpoint is touched
        return fit_and_test(plan)


def fit_and_test(plan: TrainPlan) -> dict[str, Any] | None:
    prepare_process(plan.keep_freed_memory)
    prepare_data(plan.data)
    # Lightning, the module and the metrics (about 4 s to import) only now: a refused folder, checkpoint
    # or option above is answered at once
    import lightning as L
    from lightning.pytorch.callbacks import ModelCheckpoint
    from lightning.pytorch.utilities.exceptions import SIGTERMException

    from ..module import FisheyeDepthModule
    from ..training import AtomicCheckpointIO
    from .evaluate import run_evaluation

    L.seed_everything(plan.seed, workers=True)
    datamodule = instantiate(plan.data.datamodule, **plan.data.arguments())
    resolved, resumed = {}, plan.resumed
    if plan.model.options["net"].get("base_focal") == "auto":  # a number in the checkpoint's hparams
        resolved["net"] = {"base_focal": resolve_base_focal(datamodule, resumed)}
    module = build_model(plan.model, **resolved)
    if resumed is not None and (mismatch := weights_mismatch(module.state_dict(), resumed["state_dict"])):
        raise CheckpointError(plan.resume, f"cannot resume it with this model: weights {mismatch}")
    logger = instantiate(plan.logger) if plan.logger else False
    callbacks = [instantiate(c) for c in plan.callbacks]
    checkpointers = [c for c in callbacks if isinstance(c, ModelCheckpoint)]
    selected_checkpoint(checkpointers, plan.select)  # best without a monitor fails now, not after training
    log.info("accelerator: %s", describe_accelerator(plan.accelerator))
    trainer: L.Trainer = instantiate(
        plan.trainer,
        accelerator=plan.accelerator,  # auto: chosen by what the machine has (plan.choose_accelerator)
        logger=logger,
        callbacks=callbacks,
        default_root_dir=str(plan.output_dir),
        precision=plan.precision,
        plugins=[AtomicCheckpointIO()],  # a kill while saving leaves the previous checkpoint whole
    )
    try:
        try:
            with sigterm_left_alone():  # Lightning's own handler stops at a batch boundary
                trainer.fit(module, datamodule=datamodule, ckpt_path=plan.resume)
        except SIGTERMException:
            # Lightning stops at a batch boundary and raises SystemExit(None), i.e. exit 0: a job
            # scheduler, make or a shell script would take the run for finished.
            stopped(trainer, plan, "terminated (SIGTERM)")
            raise SystemExit(EXIT_SIGTERM) from None
        except SystemExit as exit_:
            if not (trainer.interrupted and exit_.code == 1):
                raise
            # Ctrl-C: Lightning tears the run down and exits with status 1, as it would on an error
            stopped(trainer, plan, "interrupted (SIGINT)")
            raise SystemExit(EXIT_SIGINT) from None
        record = None
        if plan.test and trainer.is_global_zero and not trainer.fast_dev_run:
            ckpt = selected_checkpoint(checkpointers, plan.select)
            tested = FisheyeDepthModule.from_checkpoint(ckpt) if ckpt else module
            record = run_evaluation(
                plan.scoring,
                tested,
                datamodule,
                plan.output_dir,
                ckpt,
                {
                    "resumed_from": plan.resume,
                    "global_step": trainer.global_step,
                    "select": plan.select,
                    "skipped_batches": module.skipped_batches,
                },
                device=trainer.strategy.root_device,  # a checkpoint loads on the CPU
            )
        return record
    finally:
        if logger and type(logger).__name__ == "WandbLogger":
            import wandb

            wandb.finish()  # one wandb run per job, also inside a multirun sweep


def stopped(trainer, plan: TrainPlan, why: str) -> None:
    """The one line of a training run stopped by a signal: where, and the checkpoint to resume from."""
    last = plan.output_dir / "checkpoints" / "last.ckpt"
    resume = last if last.is_file() else "<a checkpoint of this run>"
    print(f"error: {why} at step {trainer.global_step}; no results.json. Resume with ckpt_path={resume}",
          file=sys.stderr)  # fmt: skip
