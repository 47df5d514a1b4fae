"""What a training config leaves to be worked out: ``auto`` values (``model.base_focal``,
``trainer.precision``), keys that two groups must agree on (the source offsets the model warps and the data
loads), and checks of options against the network (its input sizes, a resumed checkpoint's network). One
place, so that every command and test resolves a config the same way; nothing here builds an object
from a config (that happens in :mod:`fisheyedepth.cli`)."""

from __future__ import annotations

import inspect
import logging
from typing import Any

import torch
from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf

from .models.depth_net import check_input_size

log = logging.getLogger("fisheyedepth")


def resolve_base_focal(datamodule, resumed: dict[str, Any] | None = None) -> float | None:
    """``base_focal: auto``: the training cameras' mean paraxial focal at the training size. A resumed
    run keeps its checkpoint's number (Lightning restores weights, not constructor arguments), so its
    distance scale cannot change mid-training; a different number from the data now is reported."""
    here = datamodule.base_focal("train")
    if resumed is not None:
        stored = resumed.get("hyper_parameters", {}).get("base_focal", here)
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
    """The source frames of every target: ``model.source_offsets``, which the data module must load
    (the module's warps and PoseNet follow them). A different ``data.datamodule.offsets`` is refused:
    it once let ``model.source_offsets=[-2,2]`` train silently on the +-1 neighbours."""
    offsets = [int(o) for o in cfg.model.source_offsets]
    data_offsets = cfg.data.datamodule.get("offsets")
    if data_offsets is not None and [int(o) for o in data_offsets] != offsets:
        raise ValueError(
            f"data.datamodule.offsets={list(data_offsets)} differs from model.source_offsets={offsets}; "
            "set model.source_offsets only (the data module loads what the model warps)"
        )
    return offsets


def check_sizes(cfg: DictConfig) -> None:
    """The training size (and the model's input size, when set apart from it) the network can run at:
    refused now, not as a tensor mismatch deep in the decoder."""
    check_input_size(cfg.data.datamodule.size, "data.datamodule.size")
    if cfg.model.get("input_size") is not None:
        check_input_size(cfg.model.input_size, "model.input_size")


def configured_model(cfg: DictConfig) -> dict[str, Any]:
    """The model's constructor arguments as configured (the constructor's defaults where it is silent)."""
    params = inspect.signature(get_class(cfg.model._target_).__init__).parameters.values()
    defaults = {p.name: p.default for p in params if p.default is not inspect.Parameter.empty}
    given = OmegaConf.to_container(cfg.model, resolve=True)
    return defaults | {k: v for k, v in given.items() if not k.startswith("_")}
