"""The options of :class:`~fisheyedepth.module.FisheyeDepthModule`, in the groups of ``conf/model``:
``net`` (the :class:`~fisheyedepth.models.DepthNet`'s keywords), ``objective`` (the
:class:`~fisheyedepth.losses.objective.SelfSupervisedObjective`'s, and the PoseNet's
``pose_translation_scale``), ``optimizer`` and ``scheduler`` (``_target_`` configs), and the module's
own.

Their defaults live in one place, the model's YAML (``conf/model/fisheyedepth.yaml`` and the optimiser
and scheduler it names in its ``defaults`` list): :func:`model_defaults` reads it, :func:`model_options`
fills what a caller leaves out from it. The classes declare their keywords without defaults; each
switch and number is checked by kind and range (:func:`check_numbers`, on
:data:`fisheyedepth.options.tables.MODEL_OPTIONS`). Adding an option: a keyword of its class and a line
of the YAML."""

from __future__ import annotations

import copy
import functools
from pathlib import Path
from typing import Any

import yaml

from .kinds import check_options
from .tables import MODEL_OPTIONS

CONF_DIR = Path(__file__).resolve().parents[3] / "conf"  # the Hydra configs of the entry points
MODEL_CONFIG = CONF_DIR / "model" / "fisheyedepth.yaml"
GROUPS = ("net", "objective", "optimizer", "scheduler")


def _read(path: Path) -> dict[str, Any]:
    try:
        with open(path, encoding="utf-8") as f:
            loaded = yaml.safe_load(f)
    except (OSError, yaml.YAMLError) as exc:
        raise FileNotFoundError(f"{path}: the model's default options cannot be read ({exc})") from None
    if not isinstance(loaded, dict):
        raise ValueError(f"{path}: not a mapping of options")
    return loaded


def _tuples(value: Any) -> Any:
    """YAML's lists as tuples (a default nobody can append to), through mappings."""
    if isinstance(value, dict):
        return {k: _tuples(v) for k, v in value.items()}
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


@functools.lru_cache(maxsize=1)
def _defaults() -> dict[str, Any]:
    model = _read(MODEL_CONFIG)
    out: dict[str, Any] = {}
    for entry in model.pop("defaults", []):
        if isinstance(entry, dict):  # ``- optimizer: adam``: conf/model/optimizer/adam.yaml
            (group, name), = entry.items()  # fmt: skip
            out[group] = _read(MODEL_CONFIG.parent / group / f"{name}.yaml")
    model.pop("_target_", None)
    for key, value in model.items():
        # an interpolation (``input_size: ${data.datamodule.size}``) is the entry point's to fill in
        out[key] = None if isinstance(value, str) and value.startswith("${") else value
    out = _tuples(out)
    missing = [g for g in GROUPS if not isinstance(out.get(g), dict)]
    if missing:
        raise ValueError(f"{MODEL_CONFIG}: no {', '.join(missing)} group of options")
    return out


def model_defaults() -> dict[str, Any]:
    """The module's options as ``conf/model/fisheyedepth.yaml`` sets them (a fresh copy; its lists as
    tuples): the groups and the module's own options. ``net.base_focal`` is ``auto`` there, which
    ``train.py`` resolves from the training cameras; a network built without them names its
    ``base_focal`` (None: depth scale 1)."""
    return copy.deepcopy(_defaults())


def _group(defaults: dict[str, Any], given: dict[str, Any] | None) -> dict[str, Any]:
    """``given`` over ``defaults``; a ``_target_`` of its own replaces them."""
    given = dict(given or {})
    if given.get("_target_", defaults.get("_target_")) != defaults.get("_target_"):
        return given
    return defaults | given


def model_options(*, net=None, objective=None, optimizer=None, scheduler=None, **rest: Any) -> dict[str, Any]:
    """The module's options with :func:`model_defaults` where ``net``, ``objective``, ``optimizer``,
    ``scheduler`` and the other keywords are silent: what ``module.hparams`` holds."""
    defaults = model_defaults()
    given = {"net": net, "objective": objective, "optimizer": optimizer, "scheduler": scheduler}
    groups = {g: _group(defaults.pop(g), given[g]) for g in GROUPS}
    return groups | defaults | rest


def net_options(**given: Any) -> dict[str, Any]:
    """:class:`~fisheyedepth.models.DepthNet`'s keywords: the YAML's, with ``given`` over them."""
    return model_defaults()["net"] | given


def objective_options(**given: Any) -> dict[str, Any]:
    """:class:`~fisheyedepth.losses.objective.SelfSupervisedObjective`'s keywords: the YAML's (less the
    PoseNet's ``pose_translation_scale``), with ``given`` over them; ``scales`` are the network's."""
    defaults = model_defaults()
    objective = defaults["objective"]
    objective.pop("pose_translation_scale")
    return objective | {"scales": defaults["net"]["scales"]} | given


def keywords() -> tuple[str, ...]:
    """Every keyword of the module (what a checkpoint's hyper-parameters may hold)."""
    return tuple(_defaults())


def unknown_options(arguments: dict[str, Any]) -> list[str]:
    """The module's keywords in ``arguments`` that it does not take, and the ``objective.`` options (the
    group read without building the objective, by a network loaded for inference)."""
    unknown = [k for k in arguments if k not in _defaults()]
    objective = _defaults()["objective"]
    return unknown + [f"objective.{k}" for k in arguments.get("objective") or {} if k not in objective]


def check_numbers(options: dict[str, Any]) -> None:
    """A ValueError naming the first switch or number of the module's ``options`` (dotted: group and
    key, ``net.n_bins``) that is not of its kind and range (:data:`MODEL_OPTIONS`): a string is refused
    by name (``model.optimizer.lr=abc``), not met deep in the optimiser or the loss; then options that
    cannot go together (:func:`check_combinations`)."""
    check_options(options, MODEL_OPTIONS)
    check_combinations(options)


def check_combinations(options: dict[str, Any], prefix: str = "") -> None:
    """A ValueError naming (``prefix`` + group + key) the first option, each of its kind already, that
    contradicts another: ``net.scales`` without 0 (the distance the network gives is scale 0's: an empty
    list failed in the first validation, one without 0 at the first prediction), ``net.min_distance``
    not below ``net.max_distance`` (the network predicted one distance everywhere), the cost volume's
    nearest hypothesis not nearer than its farthest, and ``objective`` offsets that name no source frame
    (the photometric loss, which validation computes too, warps at least one)."""
    net, objective = options.get("net") or {}, options.get("objective") or {}
    scales = net.get("scales")
    if scales is not None and 0 not in scales:
        raise ValueError(
            f"{prefix}net.scales: {list(scales)} does not hold 0; the distance the network gives is that of "
            "scale 0 (full resolution): [0], or [0, 1, 2, 3] for the loss at four scales"
        )
    for low, high, what in (
        ("min_distance", "max_distance", "every distance the network gives lies between them"),
        ("cost_volume_min", "cost_volume_max", "the cost volume's hypotheses lie between them"),
    ):
        if low == "cost_volume_min" and not net.get("cost_volume"):
            continue
        if low in net and high in net and net[low] >= net[high]:
            raise ValueError(
                f"{prefix}net.{low}: {net[low]!r} is not below {prefix}net.{high} ({net[high]!r}); {what}"
            )
    if "source_offsets" in objective and not [
        *objective["source_offsets"],
        *(objective.get("rig_offsets") or ()),
    ]:
        raise ValueError(
            f"{prefix}objective.source_offsets: [] with no {prefix}objective.rig_offsets names no source "
            "frame; the photometric loss warps at least one: [-1, 1], or rig_offsets [0] on a rig"
        )


__all__ = [
    "CONF_DIR",
    "check_combinations",
    "check_numbers",
    "keywords",
    "model_defaults",
    "model_options",
    "net_options",
    "objective_options",
    "unknown_options",
]
