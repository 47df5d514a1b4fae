"""Shared by the scripts: a command's config composed from ``conf/`` as the command composes it, and the
data module and model it describes, built as ``train.py`` builds them. A script names what it changes as
Hydra overrides (``data=kitti360``, ``model=fisheyedepth_lite``, ``data.datamodule.size=[96,96]``), never
a copy of a config's keys, so a renamed or regrouped key changes nothing here.

The scripts in the folders of ``scripts/`` put ``scripts/`` on ``sys.path`` to import this module. The
library is imported where it is used, so that a benchmark's child process can run another checkout's.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

ROOT = Path(__file__).resolve().parents[1]


def compose_config(
    overrides: Sequence[str] = (), values: Mapping[str, Any] | None = None, config_name: str = "train"
) -> DictConfig:
    """``conf/<config_name>.yaml`` with ``overrides`` (Hydra's syntax), then ``values`` set by dotted key
    (file paths go here: no quoting). ``paths.root_dir`` is this checkout, as for a command started in
    it; nothing needs Hydra's runtime."""
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name=config_name, overrides=list(overrides))
    OmegaConf.update(cfg, "paths.root_dir", str(ROOT))
    for key, value in (values or {}).items():
        OmegaConf.update(cfg, key, str(value) if isinstance(value, Path) else value)
    return cfg


def build_datamodule(cfg: DictConfig, **arguments):
    """``cfg.data.datamodule``, loading the sources the model warps (its source and rig offsets, as
    ``train.py`` passes them) unless ``arguments`` say otherwise."""
    from fisheyedepth.config import rig_offsets, source_offsets

    arguments.setdefault("offsets", source_offsets(cfg))
    arguments.setdefault("rig_offsets", rig_offsets(cfg))
    return instantiate(cfg.data.datamodule, **arguments)


def build_module(cfg: DictConfig, datamodule=None, base_focal: Any = "auto"):
    """``cfg.model`` as ``train.py`` instantiates it. Its base focal, wherever the model config keeps
    it: ``auto`` (configured) is worked out from ``datamodule``'s training cameras, as ``train.py`` does;
    a number or None given here replaces the configured value (an untrained network for timing has no
    training cameras: None, depth_scale 1)."""
    from fisheyedepth.cli.train import build_model
    from fisheyedepth.config import resolve_base_focal
    from fisheyedepth.plan import model_plan

    model, path = model_plan(cfg), _find(cfg.model, "base_focal")
    if path is None:
        return build_model(model)
    value = base_focal
    if base_focal == "auto" and OmegaConf.select(cfg.model, ".".join(path)) == "auto":
        if datamodule is None:
            raise ValueError(f"model.{'.'.join(path)}: auto needs the training data (a data module)")
        value = resolve_base_focal(datamodule)
    elif base_focal == "auto":
        return build_model(model)  # a number configured: as it is
    resolved: Any = value
    for key in reversed(path):  # {"net": {"base_focal": value}} for model.net.base_focal
        resolved = {key: resolved}
    return build_model(model, **resolved)


def _find(node: Any, key: str, path: tuple[str, ...] = ()) -> tuple[str, ...] | None:
    """The keys leading to ``key`` in the config ``node`` (the model's options may be nested), or None."""
    if not isinstance(node, DictConfig):
        return None
    for name, value in node.items_ex(resolve=False):
        if name == key:
            return (*path, name)
        found = _find(value, key, (*path, name))
        if found is not None:
            return found
    return None
