"""The options of :class:`~fisheyedepth.module.FisheyeDepthModule`, in the groups of ``conf/model``:
``net`` (the :class:`~fisheyedepth.models.DepthNet`'s keywords), ``objective`` (the
:class:`~fisheyedepth.losses.objective.SelfSupervisedObjective`'s, and the PoseNet's
``pose_translation_scale``), ``optimizer`` and ``scheduler`` (``_target_`` configs), and the module's
own; their defaults (:func:`model_options`) and the check of each switch and number by kind and range
(:func:`check_numbers`, on :data:`fisheyedepth.option_checks.MODEL_OPTIONS`)."""

from __future__ import annotations

import inspect
from typing import Any

from .losses.objective import SelfSupervisedObjective
from .models import DepthNet
from .option_checks import MODEL_OPTIONS, check_options


def _defaults(function, *leave_out: str) -> dict[str, Any]:
    params = inspect.signature(function).parameters.values()
    return {p.name: p.default for p in params if p.default is not p.empty and p.name not in leave_out}


NET = _defaults(DepthNet.__init__)
# pose_translation_scale: the PoseNet's metres per raw output unit; None keeps Monodepth2's ratio to the
# depth head's initial distance (0.01 m per 0.2 m), so that the PoseNet starts with Monodepth2's parallax
OBJECTIVE = _defaults(SelfSupervisedObjective.__init__, "scales", "pose_net") | {
    "pose_translation_scale": None
}
OPTIMIZER = {"_target_": "torch.optim.Adam", "_partial_": True, "lr": 1e-4, "weight_decay": 1e-5}
SCHEDULER = {"_target_": "torch.optim.lr_scheduler.StepLR", "_partial_": True, "step_size": 8, "gamma": 0.1}


def _group(defaults: dict[str, Any], given: dict[str, Any] | None) -> dict[str, Any]:
    """``given`` over ``defaults``; a ``_target_`` of its own replaces them."""
    given = dict(given or {})
    if given.get("_target_", defaults.get("_target_")) != defaults.get("_target_"):
        return given
    return defaults | given


# the module's own options beside the groups, with their defaults
TOP = {"eval_cap": (1e-3, 80.0), "log_images_every": 200, "input_size": None, "compile_kernels": False}
# every keyword of the module (what a checkpoint's hyper_parameters may hold)
KEYWORDS = ("net", "objective", "optimizer", "scheduler", *TOP)


def model_options(*, net=None, objective=None, optimizer=None, scheduler=None, **rest: Any) -> dict[str, Any]:
    """The module's options with the defaults where ``net``, ``objective``, ``optimizer``, ``scheduler``
    and the other keywords are silent: what ``module.hparams`` holds."""
    groups = {"net": (NET, net), "objective": (OBJECTIVE, objective), "optimizer": (OPTIMIZER, optimizer)}
    groups["scheduler"] = (SCHEDULER, scheduler)
    return {k: _group(*v) for k, v in groups.items()} | TOP | rest


def check_numbers(options: dict[str, Any]) -> None:
    """A ValueError naming the first switch or number of the module's ``options`` (dotted: group and
    key, ``net.n_bins``) that is not of its kind and range (:data:`MODEL_OPTIONS`): a string is refused
    by name (``model.optimizer.lr=abc``), not met deep in the optimiser or the loss."""
    check_options(options, MODEL_OPTIONS)


__all__ = ["KEYWORDS", "check_numbers", "model_options"]
