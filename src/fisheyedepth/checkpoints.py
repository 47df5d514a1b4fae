"""Reading and writing checkpoints safely, with one clear line naming the file when one cannot be used.

Checkpoints are read with ``torch.load(weights_only=True)``: a malicious pickle executes nothing. A file
that is empty, truncated, random bytes, another project's checkpoint, or a FisheyeDepth checkpoint of
incompatible shape raises :class:`CheckpointError` with the path and what is wrong with it, instead of
``PytorchStreamReader failed``, ``EOFError`` or a ``KeyError`` deep inside Lightning. So does one whose
weights are not all finite (a network that predicts no distance, scored as NaN), and one whose
hyper-parameters lack the network's group or contradict each other (``net.min_distance`` not below
``net.max_distance``: one distance everywhere), wherever it is read: predict, eval, export and resume.

Checkpoints are written by :func:`write_checkpoint` (in training through
:class:`~fisheyedepth.training.AtomicCheckpointIO`):
beside their target under a hidden name with the writer's pid, flushed to disk, then renamed over the
target, so a kill at any moment leaves the previous file whole;
:func:`~fisheyedepth.files.remove_stale_temporaries` removes what killed writers left.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import pickle
import re
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from .files import atomic_target
from .migration import FLAT_KEYS, current_hparams, nested_hparams
from .models.depth_net import check_network_memory
from .options.defaults import check_combinations, net_options
from .options.kinds import check_options
from .options.tables import MODEL_OPTIONS
from .signals import signals_deferred

# What Lightning needs to resume a run (global step, optimiser, scheduler, loops).
RESUME_KEYS = ("pytorch-lightning_version", "state_dict", "optimizer_states", "loops", "epoch", "global_step")


class CheckpointError(ValueError):
    """A checkpoint file that cannot be used; the message names the file."""

    def __init__(self, path: str | os.PathLike, reason: str):
        super().__init__(f"{path}: {reason}")
        self.path = str(path)


def read_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """The checkpoint's dictionary, loaded on the CPU with ``weights_only=True``."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(path, "checkpoint not found")
    if path.stat().st_size == 0:
        raise CheckpointError(path, "empty file, not a checkpoint")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:  # a pickle with objects weights_only refuses
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(path, f"refused by the safe loader (weights_only=True): {first}") from None
    except (RuntimeError, EOFError, IndexError, ValueError, KeyError, OSError, zipfile.BadZipFile) as exc:
        raise CheckpointError(
            path, f"not a readable PyTorch checkpoint (truncated or not a checkpoint: {type(exc).__name__})"
        ) from None
    if not isinstance(ckpt, dict):
        raise CheckpointError(path, f"holds a {type(ckpt).__name__}, not a checkpoint dictionary")
    check_finite(path, ckpt.get("state_dict"))
    return ckpt


def check_finite(path: str | os.PathLike, state: Any) -> None:
    """A :class:`CheckpointError` naming ``path`` and the first tensor of the state dict ``state`` that
    holds a NaN or an infinity (a run that diverged): such a network predicts no distance, and its
    scores are NaN."""
    if not isinstance(state, dict):
        return
    for key, value in state.items():
        if isinstance(value, torch.Tensor) and value.is_floating_point():
            bad = int(value.numel() - torch.isfinite(value).sum())
            if bad:
                raise CheckpointError(
                    path,
                    f"weight {key} holds {bad} NaN or infinite value(s) of {value.numel()}; a network with "
                    "them predicts no distance (a diverged run: take an earlier checkpoint)",
                )


# The released weights (weights/README.md): a source checkout has them; predict.py, eval.py and export.py
# use them when no ckpt_path is given.
WEIGHTS_DIR = Path(__file__).resolve().parents[2] / "weights"
RELEASED = "fisheyedepth_mobile_mixed.ckpt"
CHECKSUMS = "SHA256SUMS"
# What a released checkpoint keeps: the weights (float16) and what builds the network around them.
RELEASE_KEYS = ("state_dict", "hyper_parameters", "epoch", "global_step", "pytorch-lightning_version")


def sha256(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_checksums(path: str | os.PathLike) -> dict[str, str]:
    """``sha256sum``'s format: ``<64 hex digits>  <file name>`` per line.
    A file named twice is refused: which of its checksums holds cannot be told."""
    sums, lines = {}, {}
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):
        if not line.strip():
            continue
        parts = line.split()
        if len(parts) != 2 or not re.fullmatch(r"[0-9a-f]{64}", parts[0]):
            raise CheckpointError(path, f"line {n}: not '<sha256>  <file>': {line!r}")
        name = parts[1].lstrip("*")
        if name in sums:
            raise CheckpointError(
                path, f"line {n}: {name} is listed again (first on line {lines[name]}); one checksum per file"
            )
        sums[name], lines[name] = parts[0], n
    return sums


def released_checkpoint(folder: str | os.PathLike = WEIGHTS_DIR, name: str = RELEASED) -> Path:
    """The released weights, checked against ``SHA256SUMS`` beside them: a damaged copy or a Git LFS
    pointer raises :class:`CheckpointError` naming the file instead of loading wrong weights."""
    folder = Path(folder)
    path, sums = folder / name, folder / CHECKSUMS
    if not path.is_file():
        raise CheckpointError(
            path, "the released weights are not here (they ship with a source checkout); pass ckpt_path=FILE"
        )
    if not sums.is_file():
        raise CheckpointError(sums, f"checksum file not found; it lists {name}")
    expected = read_checksums(sums).get(name)
    if expected is None:
        raise CheckpointError(sums, f"has no checksum for {name}")
    actual = sha256(path)
    if actual != expected:
        raise CheckpointError(
            path, f"sha256 {actual[:16]}... is not {expected[:16]}... of {CHECKSUMS} (a damaged copy?)"
        )
    return path


def release_checkpoint(ckpt: dict[str, Any]) -> dict[str, Any]:
    """A training checkpoint slimmed for release: its weights in float16 (loaded back into float32; the
    released network's real-world abs_rel moves by at most 0.002, weights/README.md) and its
    hyper-parameters; no optimiser, scheduler or loop state, so it loads for inference, not to resume."""
    slim = {k: ckpt[k] for k in RELEASE_KEYS if k in ckpt}
    slim["state_dict"] = {
        k: (v.half() if v.is_floating_point() else v) for k, v in ckpt["state_dict"].items()
    }
    return slim


def module_arguments(path: str | os.PathLike, ckpt: dict[str, Any]) -> dict[str, Any]:
    """The checkpoint's hyper-parameters as constructor arguments (retired keys dropped, flat ones in
    their groups)."""
    missing = [k for k in ("state_dict", "hyper_parameters") if k not in ckpt]
    if missing:
        raise CheckpointError(path, f"not a FisheyeDepth checkpoint (no {' / '.join(missing)})")
    check_hyper_parameters(path, ckpt["hyper_parameters"])
    hparams = current_hparams(ckpt["hyper_parameters"])
    # the ImageNet file of the training machine is not needed: weights follow
    hparams["net"] = {**hparams["net"], "weights": None}
    return hparams


GROUPS = ("net", "objective", "optimizer", "scheduler")  # the module's option groups (fisheyedepth.options)
NET_FLAT = tuple(k for k, name in FLAT_KEYS.items() if name.startswith("net."))


def check_hyper_parameters(path: str | os.PathLike, stored: Any) -> None:
    """A :class:`CheckpointError` naming ``path`` when its hyper-parameters ``stored`` cannot describe its
    network: not a mapping, grouped options without the ``net`` group (the network's options, which
    the module would otherwise fill with today's defaults), or a ``net`` that is no mapping; then each
    option of its kind, the options that contradict each other
    (:func:`~fisheyedepth.options.defaults.check_combinations`) and a network larger than this machine's
    memory (:func:`~fisheyedepth.models.depth_net.check_network_memory`), before any weight is allocated."""
    if not isinstance(stored, dict):
        raise CheckpointError(path, f"its hyper_parameters are a {type(stored).__name__}, not a mapping")
    grouped = any(isinstance(stored.get(g), dict) for g in GROUPS)
    if "net" in stored and not isinstance(stored["net"], dict):
        raise CheckpointError(
            path, f"hyper_parameters.net is a {type(stored['net']).__name__}, not a mapping"
        )
    if "net" not in stored and (grouped or not any(k in stored for k in NET_FLAT)):
        raise CheckpointError(
            path,
            "hyper_parameters has no net group (the network's options: encoder, n_bins, min_distance, "
            "max_distance, scales, ...); its network cannot be built as it was trained",
        )
    try:
        nested = nested_hparams(stored)
        check_options(nested, MODEL_OPTIONS)
        check_combinations(nested)
        check_network_memory(net_options(**nested["net"]), "net.")
    except ValueError as exc:
        raise CheckpointError(path, f"hyper_parameters {exc}") from None


def check_resumable(
    path: str | os.PathLike, model: dict[str, Any] | Callable[[], dict[str, Any]] | None = None
) -> dict[str, Any]:
    """Refuse, before training starts, a checkpoint Lightning cannot resume from; returns it. ``model``:
    the configured constructor arguments, whose network must be the checkpoint's (or what returns them,
    called only for a checkpoint that can be resumed)."""
    ckpt = read_checkpoint(path)
    missing = [k for k in RESUME_KEYS if k not in ckpt]
    if missing:
        raise CheckpointError(
            path, f"cannot resume from it: no {', '.join(missing)} (not a Lightning training checkpoint)"
        )
    if ckpt.get("hyper_parameters") is not None:
        check_hyper_parameters(path, ckpt["hyper_parameters"])
    if callable(model):
        model = model()
    differing = network_differences(ckpt.get("hyper_parameters") or {}, model or {})
    if differing:
        raise CheckpointError(path, f"cannot resume it with another network: {'; '.join(differing)}")
    return ckpt


# The options that shape the weights; n_bins and attention only for the binned head
NETWORK = ("net.encoder", "net.resnet", "net.decoder_width", "net.scales", "net.multi_channel")
NETWORK += ("objective.real_scale",)
BINNED_HEAD = ("net.n_bins", "net.attention")


def _plain(value: Any) -> Any:
    return tuple(_plain(v) for v in value) if isinstance(value, (list, tuple)) else value


def network_differences(stored: dict[str, Any], configured: dict[str, Any]) -> list[str]:
    """``model.GROUP.KEY is A here, B in the checkpoint`` for each option of :data:`NETWORK` that
    differs; ``stored`` flat or in groups (:func:`nested_hparams`), ``configured`` in groups."""
    stored = nested_hparams(stored) if stored else {}
    multi_channel = stored.get("net", {}).get("multi_channel", True)
    differing = []
    for name in NETWORK + (BINNED_HEAD if multi_channel else ()):
        group, key = name.split(".")
        here, there = configured.get(group) or {}, stored.get(group) or {}
        if key in here and key in there and _plain(here[key]) != _plain(there[key]):
            differing.append(f"model.{name} is {here[key]} here, {there[key]} in the checkpoint")
    return differing


def _listed(keys: list[str], show=str, first: int = 2) -> str:
    more = f", and {len(keys) - first} more" if len(keys) > first else ""
    return ", ".join(show(k) for k in keys[:first]) + more


def weights_mismatch(model: dict[str, Any], found: dict[str, Any]) -> str:
    """'' when the state dict ``found`` fits ``model``'s; else which keys do not, briefly."""

    def shape(state: dict[str, Any], key: str) -> list[int]:
        return list(getattr(state[key], "shape", ()))

    def both(key: str) -> str:
        return f"{key} {shape(found, key)} in the file, {shape(model, key)} in the model"

    reshaped = [k for k in model if k in found and shape(found, k) != shape(model, k)]
    missing = [k for k in model if k not in found]
    unexpected = [k for k in found if k not in model]
    parts = []
    if reshaped:
        parts.append(f"{len(reshaped)} of another shape ({_listed(reshaped, both)})")
    if missing:
        parts.append(f"{len(missing)} missing ({_listed(missing)})")
    if unexpected:
        parts.append(f"{len(unexpected)} unexpected ({_listed(unexpected)})")
    return "; ".join(parts)


def model_from_checkpoint(
    path: str | os.PathLike, build: Callable[..., torch.nn.Module], skip: tuple[str, ...] = ()
) -> torch.nn.Module:
    """``build(**hyper_parameters)`` with the checkpoint's weights, read with ``weights_only=True``;
    weights whose names start with one of ``skip`` are left out. A file that does not hold such a model
    (hyper-parameters ``build`` refuses with a TypeError, weights that do not fit) raises
    :class:`CheckpointError` naming it."""
    ckpt = read_checkpoint(path)
    try:
        model = build(**module_arguments(path, ckpt))
    except TypeError as exc:
        raise CheckpointError(
            path, f"hyper_parameters do not fit FisheyeDepthModule ({exc}); another project's checkpoint?"
        ) from None
    except CheckpointError:
        raise
    except ValueError as exc:  # an option of the wrong kind or range (check_numbers), named by the module
        raise CheckpointError(path, f"hyper_parameters {exc}") from None
    state = ckpt["state_dict"]
    if skip and isinstance(state, dict):
        state = {k: v for k, v in state.items() if not k.startswith(skip)}
    load_weights(model, path, state)
    return model


def load_weights(model: torch.nn.Module, path: str | os.PathLike, state: Any) -> None:
    """``state`` (a checkpoint's ``state_dict``) into ``model``, or a :class:`CheckpointError` naming
    ``path`` and the weights that do not fit."""
    if not isinstance(state, dict):
        raise CheckpointError(path, f"its state_dict is a {type(state).__name__}, not a dictionary")
    mismatch = weights_mismatch(model.state_dict(), state)
    if mismatch:
        raise CheckpointError(path, f"weights do not fit the model its hyper_parameters describe: {mismatch}")
    try:
        model.load_state_dict(state)
    except (RuntimeError, TypeError, AttributeError) as exc:
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        detail = "; ".join(lines[1:3] or lines[:1])
        raise CheckpointError(
            path, f"weights do not fit the model its hyper_parameters describe ({detail[:300]})"
        ) from None


# ------------------------------------------------------------------ writing
def write_checkpoint(checkpoint: dict[str, Any], path: str | os.PathLike) -> Path:
    """``torch.save`` into a temporary file beside ``path``, ``fsync``, then ``os.replace`` over it
    (:func:`~fisheyedepth.files.atomic_target`): the previous file stays whole until the new one is.
    Never through the system temp folder, which may be another filesystem (where a move becomes a copy
    that truncates the target first)."""
    path = Path(path)
    with signals_deferred(), atomic_target(path, sync=True) as tmp, open(tmp, "wb") as handle:
        torch.save(checkpoint, handle)  # Ctrl-C or SIGTERM stop the run once the file is whole
    with contextlib.suppress(OSError):  # the rename itself, on filesystems that sync folders
        folder = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(folder)
        finally:
            os.close(folder)
    return path
