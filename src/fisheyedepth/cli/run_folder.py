"""One training run per folder: a run folder that holds another run's checkpoints is refused, and so is a
second run started into a folder while one trains there.

:class:`RunFolderGuard` is a Hydra callback (``conf/callbacks/default.yaml``): it runs before Hydra writes
``.hydra/`` and the log into the folder, so a refused run leaves the earlier run's files as they were.
``train()`` claims the folder again itself (a sweep's jobs, a direct call), before it touches a checkpoint.

The lock is ``RUN/.train.lock``, held with ``flock`` for as long as the run lives: the kernel lets it go
when the process ends, however it ends, so a lock file left by a killed run is taken over, never waited on.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import socket
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from ..files import drop_lock, remove_stale_temporaries, take_lock

log = logging.getLogger("fisheyedepth")

LOCK = ".train.lock"
CHECKPOINTS = "checkpoints"  # conf/callbacks/default.yaml: ${paths.output_dir}/checkpoints
_held: dict[Path, int] = {}  # this process's locks: lock file -> its open descriptor


def other_rank() -> bool:
    """A process launched for another rank of the same run (DDP): it shares rank 0's folder and lock."""
    keys = ("RANK", "LOCAL_RANK", "SLURM_PROCID")  # Lightning's order: LOCAL_RANK before SLURM_PROCID
    rank = next((os.environ[k] for k in keys if os.environ.get(k) is not None), "0")
    return int(rank) != 0 or int(os.environ.get("NODE_RANK") or 0) != 0


def acquire(folder: str | os.PathLike) -> bool:
    """Lock ``folder`` for this process; False when this process holds it already. Another live process
    holding it is a :class:`FileExistsError` naming it."""
    path, shown = Path(folder).resolve() / LOCK, Path(folder) / LOCK
    if path in _held:
        return False
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = take_lock(path)
    except BlockingIOError:
        holder = path.read_text(errors="replace").strip() or "?"
        raise FileExistsError(
            f"{shown}: another training run (process {holder}) is writing into this folder; "
            "wait for it to end, or choose another hydra.run.dir"
        ) from None
    left = os.read(fd, 200).decode(errors="replace").strip()
    if left:
        log.warning("%s: taking over the lock of process %s, which ended without removing it", shown, left)
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()} on {socket.gethostname()}\n".encode(), 0)
    _held[path] = fd
    return True


def release(folder: str | os.PathLike) -> None:
    """Remove this process's lock of ``folder`` (nothing when it holds none)."""
    path = Path(folder).resolve() / LOCK
    fd = _held.pop(path, None)
    if fd is not None:
        drop_lock(fd, path)


@atexit.register
def _release_all() -> None:  # a run ended by SystemExit (an input error, SIGTERM) skips on_run_end
    for path in list(_held):
        release(path.parent)


def check_run_folder(folder: str | os.PathLike, ckpt_path: str | os.PathLike | None) -> None:
    """Refuse ``folder`` when it holds another run's checkpoints: a run into it would replace them while
    that run's results.json still names them. Resuming one of them (``ckpt_path`` inside) continues it."""
    folder = Path(folder)
    held = sorted((folder / CHECKPOINTS).glob("*.ckpt"))
    if not held or (ckpt_path and Path(ckpt_path).resolve().is_relative_to(folder.resolve())):
        return
    names = ", ".join(str(p.relative_to(folder)) for p in held[:3]) + (", ..." if len(held) > 3 else "")
    last = folder / CHECKPOINTS / "last.ckpt"
    raise FileExistsError(
        f"{folder}: holds another run's checkpoints ({names}); train into a new folder (another "
        f"hydra.run.dir, or none for a fresh one), or continue that run with ckpt_path={last}"
    )


def claim_run_folder(folder: str | os.PathLike, ckpt_path: str | os.PathLike | None) -> bool:
    """Lock ``folder`` and check it (:func:`check_run_folder`); the checkpoint temporaries of killed
    writers are removed. False when this process had claimed it already or is another rank's."""
    if other_rank() or not acquire(folder):
        return False
    try:
        check_run_folder(folder, ckpt_path)
    except BaseException:
        release(folder)
        raise
    for stale in remove_stale_temporaries(Path(folder) / CHECKPOINTS, "*.ckpt"):
        log.warning("removed %s, a checkpoint half-written by a process that no longer runs", stale)
    return True


@contextlib.contextmanager
def run_folder(folder: str | os.PathLike, ckpt_path: str | os.PathLike | None):
    """:func:`claim_run_folder` for the duration of a ``with`` block (released at its end if taken here)."""
    claimed = claim_run_folder(folder, ckpt_path)
    try:
        yield Path(folder)
    finally:
        if claimed:
            release(folder)


class RunFolderGuard(Callback):
    """Claims ``hydra.run.dir`` before Hydra writes into it; a refusal is one ``error:`` line, exit 2."""

    folder: Path | None = None

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        from . import run_command  # the entry points' error handling, in this package

        folder = Path(str(OmegaConf.select(config, "hydra.run.dir")))
        ckpt_path = OmegaConf.select(config, "ckpt_path", default=None)
        if run_command(lambda _: claim_run_folder(folder, ckpt_path), config):
            self.folder = folder

    def on_run_end(self, config: DictConfig, **kwargs: Any) -> None:
        if self.folder is not None:
            release(self.folder)
