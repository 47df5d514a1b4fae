"""The commands behind ``train.py``, ``eval.py``, ``predict.py`` and ``export.py``: the only place where
configs become objects (``hydra.utils.instantiate``). One small module per command; this one holds what
they share: how an input error ends a command, process-wide settings, the first-use rendering of the
synthetic data, and output paths that never replace an earlier run's file."""

from __future__ import annotations

import logging
import os
import sys
import warnings
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from ..checkpoints import released_checkpoint
from ..runtimes import OnnxRuntime, TorchRuntime, TrainedDepthNet
from ..synthetic import ensure_datasets
from ..utils import WRITE_ERRORS, keep_freed_memory

log = logging.getLogger("fisheyedepth")

EXIT_SIGTERM = 128 + 15  # the shell's status for a process ended by SIGTERM
EXIT_USAGE = 2
# Errors about the user's input (files, options): one line naming the file or option, no traceback.
INPUT_ERRORS = (FileNotFoundError, FileExistsError, NotADirectoryError, ValueError, KeyError)


def model_file_alias(argv: list[str]) -> list[str]:
    """``model=FILE.onnx`` on the command line of ``predict.py`` and ``eval.py``, which choose no model
    config group: Hydra reads ``model=`` as a choice from ``conf/model/`` wherever that group exists, so
    their entry points pass it on as ``model_file=`` (the config key)."""
    return ["model_file=" + a[len("model=") :] if a.startswith("model=") else a for a in argv]


# Warnings Lightning prints on every training run that say nothing about the run: the module's own
# ``transfer_batch_to_device`` (cameras are values on no device) is the one meant with a DataModule,
# and Lightning 2.6's ``_pytree`` calls a torch API that torch 2.13 deprecates.
QUIET_WARNINGS = (
    r"You have overridden `transfer_batch_to_device` in `LightningModule` but have passed in a",
    r"`isinstance\(treespec, LeafSpec\)` is deprecated",
)


def prepare_process(cfg: DictConfig) -> None:
    """Process-wide settings, before any work: :data:`QUIET_WARNINGS` silenced, ``keep_freed_memory``
    (glibc keeps the memory of freed tensors for reuse instead of unmapping it;
    :func:`fisheyedepth.utils.keep_freed_memory`)."""
    for message in QUIET_WARNINGS:
        warnings.filterwarnings("ignore", message=message)
    if cfg.get("keep_freed_memory"):
        log.info("keep_freed_memory: %s", "on" if keep_freed_memory() else "not glibc, nothing changed")


def run_command(command, cfg: DictConfig):
    """Run an entry point; an input error prints one line (``error: <file>: <what>``) and exits 2.
    ``FISHEYEDEPTH_TRACEBACK=1`` shows the full traceback instead."""
    try:
        return command(cfg)
    except (*INPUT_ERRORS, OSError) as exc:
        if os.environ.get("FISHEYEDEPTH_TRACEBACK") or not is_input_error(exc):
            raise
        if isinstance(exc, KeyError) and exc.args:
            message = exc.args[0]
        elif type(exc) in (OSError, PermissionError) and exc.filename:  # OSError's str() puts it last
            message = f"{exc.filename}: cannot write there ({exc.strerror})"
        else:
            message = exc
        print(f"error: {message}", file=sys.stderr)
        raise SystemExit(EXIT_USAGE) from None


def is_input_error(exc: BaseException) -> bool:
    """An error about the user's input: one of :data:`INPUT_ERRORS`, or a write the filesystem refused
    at a path the user chose (:data:`WRITE_ERRORS`)."""
    if isinstance(exc, INPUT_ERRORS):
        return True
    return isinstance(exc, OSError) and exc.errno in WRITE_ERRORS and exc.filename is not None


def prepare_data(cfg: DictConfig) -> None:
    """Render the synthetic dataset on first use (``data.generate``); a finished one is reused. A folder
    that is not a synthetic dataset made by this project is refused and left untouched."""
    gen = cfg.data.get("generate")
    if not gen:
        return
    root = cfg.data.datamodule.root  # one folder, or a list (a mixed dataset: one world per folder)
    root = OmegaConf.to_container(root, resolve=True) if OmegaConf.is_list(root) else str(root)
    ensure_datasets(root, OmegaConf.to_container(gen, resolve=True), log)


def free_path(path: Path) -> Path:
    """``path``, or ``name_1.ext``, ``name_2.ext`` ... when it exists: an earlier run's file is kept."""
    candidate, n = path, 0
    while candidate.exists():
        n += 1
        candidate = path.with_name(f"{path.stem}_{n}{path.suffix}")
    return candidate


def checkpoint_path(cfg: DictConfig) -> str:
    """``ckpt_path``, or the released weights (``weights/``, checked against their checksum) when none
    is given: metric distance from a calibrated camera without training."""
    if cfg.get("ckpt_path"):
        return str(cfg.ckpt_path)
    path = released_checkpoint()
    log.info("no ckpt_path: the released weights %s (weights/README.md)", path)
    return str(path)


def load_runtime(cfg: DictConfig, ckpt_path: str | None = None):
    """The network ``predict.py`` and ``eval.py`` run: ``runtime=torch`` (``ckpt_path``, ``precision``,
    ``device``, ``upsample``, ``size``) or ``runtime=onnx`` (``model_file``, typed ``model=FILE.onnx``:
    an ``export.py`` file, which fixes the input size; ``threads``); either with ``post_process``.
    ``ckpt_path``: the checkpoint :func:`checkpoint_path` already chose for ``cfg``, if a caller did."""
    runtime, size = str(cfg.get("runtime", "torch")), cfg.get("size")
    if runtime == "onnx":
        if not cfg.get("model_file"):
            raise ValueError("model: runtime=onnx needs the exported file, model=FILE.onnx (export.py)")
        if cfg.get("upsample") not in (None, "distance"):
            raise ValueError(
                f"upsample: {cfg.upsample!r}; an exported file upsamples its distance (upsample=distance)"
            )
        onnx = OnnxRuntime(cfg.model_file, cfg.get("threads"), str(cfg.get("post_process", "none")))
        if size and tuple(size) != tuple(onnx.input_size):
            raise ValueError(
                f"size: {list(size)}, but {cfg.model_file} was exported at {list(onnx.input_size)}"
            )
        return onnx
    if runtime != "torch":
        raise ValueError(f"runtime: {runtime!r} is not one of torch, onnx")
    if cfg.get("model_file"):
        raise ValueError("model: a file is for runtime=onnx (runtime=onnx model=FILE.onnx)")
    module = TrainedDepthNet.from_checkpoint(ckpt_path or checkpoint_path(cfg))
    if cfg.get("upsample") is not None:  # only how a distance at the training size reaches a larger image
        module.depth_net.upsample = str(cfg.upsample)  # recorded in results.json
    size = tuple(size) if size else None
    precision, post_process = str(cfg.get("precision", "fp32")), str(cfg.get("post_process", "none"))
    return TorchRuntime(module, size, precision, cfg.get("device", "cpu"), post_process)
