"""What a training config leaves to be worked out: ``auto`` values (``model.net.base_focal``,
``trainer.precision``), keys that two groups must agree on (the source offsets the model warps and the data
loads; ``${mul:...}``, the resolver of the cosine schedule), and checks of options: against the network
(its input sizes, a resumed checkpoint's network) and by kind and range (:func:`check_config`). One
place, so that every command and test resolves a config the same way; nothing here builds an object from
a config (that happens in :mod:`fisheyedepth.cli`)."""

from __future__ import annotations

import logging
import re
from typing import Any

import torch
from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf

from .migration import nested_hparams
from .models.depth_net import check_input_size
from .options.kinds import Kind, check_options
from .options.tables import DATAMODULE_OPTIONS, MODEL_OPTIONS
from .synthetic import GENERATE_OPTIONS

log = logging.getLogger("fisheyedepth")
# ``${mul:a,b}``: a x b, e.g. the cosine schedule's floor, a tenth of the learning rate
OmegaConf.register_new_resolver("mul", lambda a, b: a * b, replace=True)


def resolve_base_focal(datamodule, resumed: dict[str, Any] | None = None) -> float | None:
    """``model.net.base_focal: auto``: the training cameras' mean paraxial focal at the training size. A
    resumed run keeps its checkpoint's number (Lightning restores weights, not constructor arguments), so
    its distance scale cannot change mid-training; a different number from the data now is reported."""
    here = datamodule.base_focal("train")
    if resumed is not None:
        stored = nested_hparams(resumed.get("hyper_parameters") or {})["net"].get("base_focal", here)
        if stored is None or abs(float(stored) - here) > 1e-6 * here:
            log.warning(
                "base_focal auto: the resumed checkpoint keeps its base_focal %s; "
                "the training cameras now give %.3f px",
                stored,
                here,
            )
        return None if stored is None else float(stored)
    log.info("base_focal auto: %.3f px, the mean paraxial focal of the training cameras", here)
    return here


def resolve_precision(precision: Any, accelerator: str | None) -> Any:
    """``trainer.precision: auto``: "bf16-mixed" where bf16 is native (a CPU with AVX-512 BF16, a CUDA
    GPU that supports it; the networks in bf16, geometry and losses float32), else "32-true": on a CPU
    without it, bf16 is emulated and several times slower. Anything else is passed to Lightning."""
    if precision != "auto":
        return precision
    if accelerator in ("gpu", "cuda") or (accelerator == "auto" and torch.cuda.is_available()):
        native = torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    else:
        native = bool(torch.cpu._is_avx512_bf16_supported())
    chosen = "bf16-mixed" if native else "32-true"
    log.info("trainer.precision auto: %s (bf16 %s here)", chosen, "native" if native else "not native")
    return chosen


def source_offsets(cfg: DictConfig) -> list[int]:
    """The source frames of every target: ``model.objective.source_offsets``, which the data module must
    load (the objective's warps and PoseNet follow them). A different ``data.datamodule.offsets`` is
    refused: it once let the model's [-2, 2] train silently on the +-1 neighbours."""
    offsets = [int(o) for o in cfg.model.objective.source_offsets]
    data_offsets = cfg.data.datamodule.get("offsets")
    if data_offsets is not None and [int(o) for o in data_offsets] != offsets:
        raise ValueError(
            f"data.datamodule.offsets={list(data_offsets)} differs from "
            f"model.objective.source_offsets={offsets}; set model.objective.source_offsets only "
            "(the data module loads what the model warps)"
        )
    return offsets


def rig_offsets(cfg: DictConfig) -> list[int]:
    """The time offsets at which the rig's other cameras are sources (``model.objective.rig_offsets``)."""
    return [int(o) for o in cfg.model.objective.get("rig_offsets") or ()]


def check_sizes(cfg: DictConfig) -> None:
    """The training size (and the model's input size, when set apart from it) the network can run at:
    refused now, not as a tensor mismatch deep in the decoder."""
    check_input_size(cfg.data.datamodule.size, "data.datamodule.size")
    if cfg.model.get("input_size") is not None:
        check_input_size(cfg.model.input_size, "model.input_size")


def _configured(node: DictConfig | None, table: dict[str, Kind]) -> dict[str, Any]:
    """The options of ``node`` that ``table`` names, resolved; the others stay unresolved (a recorded
    dataset's ``root: ???`` is its reader's to name)."""
    if node is None:
        return {}
    return {
        key: OmegaConf.to_container(node[key], resolve=True) if OmegaConf.is_config(node[key]) else node[key]
        for key in table
        if key in node
    }


def check_config(cfg: DictConfig) -> None:
    """The sizes (:func:`check_sizes`), then every switch and number of the model (``model.*``), the data
    module (``data.datamodule.*``) and the synthetic renderer (``data.generate.*``) of its kind and range
    (:mod:`fisheyedepth.options`), named as configured: refused before anything is rendered or
    trained, where a wrong kind would otherwise be taken for another (``automask=maybe`` as true,
    ``truth_weight=nan`` as 0)."""
    check_sizes(cfg)
    groups = (
        (cfg.model, MODEL_OPTIONS, "model."),
        (cfg.data.datamodule, DATAMODULE_OPTIONS, "data.datamodule."),
        (cfg.data.get("generate"), GENERATE_OPTIONS, "data.generate."),
    )
    for node, table, prefix in groups:
        check_options(_configured(node, table), table, prefix)


def model_arguments(cfg: DictConfig) -> tuple[str, dict[str, Any]]:
    """The model's class (``model._target_``) and its keywords as configured (resolved, plain values):
    the option groups and the module's own options."""
    given = OmegaConf.to_container(cfg.model, resolve=True)
    return str(given["_target_"]), {k: v for k, v in given.items() if not k.startswith("_")}


def configured_options(target: str, arguments: dict[str, Any]) -> dict[str, Any]:
    """The constructor arguments of the model class ``target``, in their groups (``net``, ``objective``,
    ``optimizer``, ``scheduler``), with its defaults where ``arguments`` are silent (imports the class)."""
    return get_class(target).options(**arguments)


def configured_model(cfg: DictConfig) -> dict[str, Any]:
    """The model's constructor arguments as configured, in their groups, with the module's defaults where
    the config is silent."""
    return configured_options(*model_arguments(cfg))


def named_option(options: dict[str, Any], message: str) -> str | None:
    """``message`` with the option it starts with (``lr: ...``, ``optimizer.lr: ...``) named as
    configured, ``model.GROUP.KEY``, in the model's ``options`` (:func:`configured_options`); None when
    it starts with no option of the model."""
    match = re.match(r"([\w.]+)([:=])", message)
    if match is None:
        return None
    *group, key = match[1].split(".")
    if group:
        found = group if key in (options.get(group[0]) or {}) else []
    else:
        found = [g for g, v in options.items() if isinstance(v, dict) and key in v]
        found = [None] if key in options else found
    if len(found) != 1:
        return None
    name = key if found[0] is None else f"{found[0]}.{key}"
    return f"model.{name}{message[match.end(1) :]}"
