"""The commands behind ``train.py``, ``eval.py``, ``predict.py`` and ``export.py``: the only place where
configs become objects (``hydra.utils.instantiate``). Each command makes its plan from the composed config
(:mod:`fisheyedepth.plan`: every option checked, nothing built yet), then builds from it. One module per
command; this one holds what they share: how an input error ends a command, process-wide settings, the
synthetic data's first rendering, the network predict and eval run, output paths that replace nothing."""

from __future__ import annotations

import argparse
import logging
import os
import sys
import warnings
from pathlib import Path

from omegaconf import DictConfig

from ..files import WRITE_ERRORS
from ..plan import DataPlan, RuntimePlan, thawed
from ..runtimes import OnnxRuntime, TorchRuntime, TrainedDepthNet
from ..signals import Terminated, sigterm_raises, stopped_by
from ..synthetic import ensure_datasets
from ..utils import keep_freed_memory

log = logging.getLogger("fisheyedepth")

EXIT_USAGE = 2
# Errors about the user's input (files, options): one line naming the file or option, no traceback.
INPUT_ERRORS = (FileNotFoundError, FileExistsError, NotADirectoryError, ValueError, KeyError)


class CommandParser(argparse.ArgumentParser):
    """The console scripts' parser: a wrong option is one line, ``error: <what argparse says> (see
    <prog> --help)``, exit 2, as every other refused input (not argparse's usage block)."""

    def error(self, message: str):
        print(f"error: {message} (see {self.prog} --help)", file=sys.stderr)
        raise SystemExit(EXIT_USAGE)


def named_values(values: list[str] | None, option: str, form: str = "NAME=VALUE") -> dict[str, str]:
    """Repeated ``NAME=VALUE`` options (``--camera front=/front/image_raw``) as a mapping; a value without
    its name or its ``=``, or a name given twice (the last would win unseen), refused naming ``option``."""
    out: dict[str, str] = {}
    for value in values or []:
        name, sep, rest = value.partition("=")
        if not sep or not name or not rest:
            raise ValueError(f"{option}: expected {form}, got {value!r}")
        if name in out:
            raise ValueError(f"{option}: {name} given twice ({name}={out[name]} and {value})")
        out[name] = rest
    return out


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


# Lightning's note on SIGTERM, beside train.py's one line (its Ctrl-C note shares its every note's logger)
QUIET_LOGGERS = ("lightning.pytorch.trainer.connectors.signal_connector",)


def prepare_process(keep_memory: bool) -> None:
    """Process-wide settings, before any work: :data:`QUIET_WARNINGS` silenced, with ``keep_memory``
    glibc keeping freed tensors' memory for reuse, not unmapping it (:func:`~..utils.keep_freed_memory`)."""
    for message in QUIET_WARNINGS:
        warnings.filterwarnings("ignore", message=message)
    for name in QUIET_LOGGERS:
        logging.getLogger(name).setLevel(logging.WARNING)
    if keep_memory:
        log.info("keep_freed_memory: %s", "on" if keep_freed_memory() else "not glibc, nothing changed")


def run_command(command, cfg: DictConfig):
    """Run an entry point; an input error prints one line (``error: <file>: <what>``) and exits 2.
    ``FISHEYEDEPTH_TRACEBACK=1`` shows the full traceback instead. SIGINT and SIGTERM end it with one
    line and exit 130 / 143 (what it writes is atomic: nothing partial is left; ``train.py`` and
    ``predict.py`` say what they keep)."""
    try:
        with sigterm_raises():
            return command(cfg)
    except (Terminated, KeyboardInterrupt) as stop:
        why, status = stopped_by(stop)
        print(f"error: {why}", file=sys.stderr)
        raise SystemExit(status) from None
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


def prepare_data(data: DataPlan) -> None:
    """Render the synthetic dataset on first use (``data.generate``); a finished one is reused. A folder
    that is not a synthetic dataset made by this project is refused and left untouched."""
    if data.generate is not None:
        ensure_datasets(thawed(data.root), thawed(data.generate), log)


def free_path(path: Path) -> Path:
    """``path``, or ``name_1.ext``, ``name_2.ext`` ... when it exists: an earlier run's file is kept."""
    candidate, n = path, 0
    while candidate.exists():
        n += 1
        candidate = path.with_name(f"{path.stem}_{n}{path.suffix}")
    return candidate


def load_runtime(runtime: RuntimePlan):
    """The network ``predict.py`` and ``eval.py`` run (:func:`fisheyedepth.plan.runtime_plan`): a
    checkpoint in PyTorch, or an ``export.py`` file in ONNX Runtime, whose input size ``size`` must be."""
    if runtime.kind == "onnx":
        onnx = OnnxRuntime(runtime.model_file, runtime.threads, runtime.post_process)
        if runtime.size and runtime.size != tuple(onnx.input_size):
            exported = list(onnx.input_size)
            raise ValueError(
                f"size: {list(runtime.size)}, but {runtime.model_file} was exported at {exported}"
            )
        return onnx
    module = TrainedDepthNet.from_checkpoint(runtime.checkpoint)
    if runtime.upsample is not None:
        module.depth_net.upsample = runtime.upsample  # recorded in results.json
    return TorchRuntime(module, runtime.size, runtime.precision, runtime.device, runtime.post_process)
