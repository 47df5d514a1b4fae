"""A Lightning callback for one GPU run of session 20: after the first epoch (its validation
included) it sets the number of epochs that fits the device time left (``trainer.max_epochs``) and
puts the learning-rate decay at the same fraction of the run as ``cpu_30min`` (8 of 10 epochs).
The run it leaves is the plain command
``train.py +experiment=cpu_30min trainer=gpu trainer.max_epochs=E model.lr_step=S``: StepLR is
changed before its first step can decay, and ``lr_step`` in the checkpoint's hyperparameters is
the one used. Every epoch's time and validation losses go to stdout and to ``record`` (JSON lines).

Added on the command line (the folder on PYTHONPATH):
  +callbacks.fill._target_=fill_budget.FillBudget +callbacks.fill.deadline=UNIX_SECONDS
"""

from __future__ import annotations

import json
import math
import time

from lightning.pytorch.callbacks import Callback


class FillBudget(Callback):
    def __init__(
        self, deadline: float, decay_fraction: float = 0.8, cap: int = 40, record: str | None = None
    ):
        self.deadline, self.decay_fraction = float(deadline), decay_fraction
        self.cap, self.record = cap, record
        self.started = None

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        self.started = time.time()

    def on_validation_end(self, trainer, pl_module) -> None:
        # the end of an epoch's validation, which Lightning runs after on_train_epoch_end: the epoch's
        # whole time, training and validation
        if trainer.sanity_checking or self.started is None:
            return
        now = time.time()
        seconds = now - self.started
        row = {"epoch": trainer.current_epoch, "seconds": round(seconds, 2), "step": trainer.global_step}
        for key in ("train/loss", "val/photometric", "val/abs_rel", "val/a1"):
            if key in trainer.callback_metrics:
                row[key] = round(float(trainer.callback_metrics[key]), 5)
        if trainer.current_epoch == 0:
            # a 5 % margin on the first epoch's time (on the H200 of session 20 the later epochs took
            # 2 % less to 29 % more; the run still ended inside its budget)
            epochs = min(self.cap, 1 + math.floor((self.deadline - now) / (1.05 * seconds)))
            epochs = max(epochs, 3)
            step = max(2, round(self.decay_fraction * epochs))
            scheduler = trainer.lr_scheduler_configs[0].scheduler
            if not hasattr(scheduler, "step_size") or scheduler.last_epoch >= min(scheduler.step_size, step):
                raise RuntimeError(f"the schedule has already moved: {scheduler.state_dict()}")
            scheduler.step_size = step
            pl_module.hparams["lr_step"] = step
            trainer.fit_loop.max_epochs = epochs
            row.update(chosen_max_epochs=epochs, chosen_lr_step=step, seconds_left=round(self.deadline - now))
        print("FILL " + json.dumps(row), flush=True)
        if self.record:
            with open(self.record, "a") as f:
                f.write(json.dumps(row) + "\n")
