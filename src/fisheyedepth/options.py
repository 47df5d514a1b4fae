"""The options of :class:`~fisheyedepth.module.FisheyeDepthModule`, in the groups of ``conf/model``:
``net`` (the :class:`~fisheyedepth.models.DepthNet`'s keywords), ``objective`` (the
:class:`~fisheyedepth.losses.objective.SelfSupervisedObjective`'s, and the PoseNet's
``pose_translation_scale``), ``optimizer`` and ``scheduler`` (``_target_`` configs), and the module's
own; their defaults (:func:`model_options`) and the check that numbers are numbers
(:func:`check_numbers`)."""

from __future__ import annotations

import inspect
import numbers
from typing import Any

from .losses.objective import SelfSupervisedObjective
from .models import DepthNet


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
# Numeric options: a string (``model.optimizer.lr=abc``) is refused by name, not deep in the optimiser
REALS = (
    *("net.min_distance", "net.max_distance", "net.decoder_width", "objective.smoothness"),
    *("objective.pose_translation_scale", "optimizer.lr", "optimizer.weight_decay", "scheduler.gamma"),
    *("scheduler.eta_min", "objective.truth_weight", "objective.photometric_weight"),
)
INTEGERS = ("net.resnet", "net.n_bins", "objective.rim_margin", "scheduler.step_size", "scheduler.T_max")
INTEGERS += ("log_images_every",)
OPTIONAL = ("objective.pose_translation_scale", "objective.rim_margin")  # None: the default


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
    """A ValueError naming the first of :data:`REALS` and :data:`INTEGERS` in ``options`` (dotted: group
    and key) that is not a number (a whole one), None allowed for :data:`OPTIONAL`."""
    for name in (*REALS, *INTEGERS):
        *group, key = name.split(".")
        values = options[group[0]] if group else options
        if key not in values:
            continue
        value, kind = values[key], numbers.Integral if name in INTEGERS else numbers.Real
        if value is None and name in OPTIONAL:
            continue
        if isinstance(value, bool) or not isinstance(value, kind):
            raise ValueError(
                f"{name}: {value!r} is not a {'whole number' if kind is numbers.Integral else 'number'}"
            )


__all__ = ["INTEGERS", "KEYWORDS", "OPTIONAL", "REALS", "check_numbers", "model_options"]
