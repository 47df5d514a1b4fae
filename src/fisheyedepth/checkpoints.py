"""Reading checkpoints safely, with one clear line naming the file when one cannot be used.

Checkpoints are read with ``torch.load(weights_only=True)``: a malicious pickle executes nothing. A file
that is empty, truncated, random bytes, another project's checkpoint, or a FisheyeDepth checkpoint of
incompatible shape raises :class:`CheckpointError` with the path and what is wrong with it, instead of
``PytorchStreamReader failed``, ``EOFError`` or a ``KeyError`` deep inside Lightning.
"""

from __future__ import annotations

import os
import pickle
import zipfile
from pathlib import Path
from typing import Any

import torch

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
    return ckpt


# 2026-11-23: clipping is the trainer's gradient_clip_val only; 2026-11-24: the distance search (a
# training-only loss, commit a350cf1) was measured and removed (BENCHMARKS.md, "Time to accuracy");
# 2026-11-25: the same for the hint search (commit c54b83b, another training-only loss), and for the
# plane-sweep hints (commit cca14f3, hint_weight)
RETIRED_HPARAMS = (
    *("grad_clip", "bin_search", "bin_search_scale"),
    *("hints", "hint_candidates", "hint_spread", "hint_margin", "hint_weight"),
)
# 2026-11-23: one name for the evaluation cap, as in the protocols and DepthMetrics
RENAMED_HPARAMS = {("eval_min", "eval_max"): "eval_cap"}


def module_arguments(path: str | os.PathLike, ckpt: dict[str, Any]) -> dict[str, Any]:
    """The checkpoint's hyper-parameters as constructor arguments (retired keys dropped)."""
    missing = [k for k in ("state_dict", "hyper_parameters") if k not in ckpt]
    if missing:
        raise CheckpointError(path, f"not a FisheyeDepth checkpoint (no {' / '.join(missing)})")
    hparams = dict(ckpt["hyper_parameters"])
    hparams["weights"] = None  # the ImageNet file of the training machine is not needed: weights follow
    for key in RETIRED_HPARAMS:  # checkpoints written before a key was retired still load
        hparams.pop(key, None)
    for old, new in RENAMED_HPARAMS.items():
        if all(k in hparams for k in old):
            hparams[new] = tuple(hparams.pop(k) for k in old)
    return hparams


def check_resumable(path: str | os.PathLike) -> dict[str, Any]:
    """Refuse, before training starts, a checkpoint Lightning cannot resume from; returns it."""
    ckpt = read_checkpoint(path)
    missing = [k for k in RESUME_KEYS if k not in ckpt]
    if missing:
        raise CheckpointError(
            path, f"cannot resume from it: no {', '.join(missing)} (not a Lightning training checkpoint)"
        )
    return ckpt
