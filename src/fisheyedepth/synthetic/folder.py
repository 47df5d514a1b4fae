"""The folder a synthetic dataset is rendered into, and which folders may be.

A dataset is written into a hidden temporary folder beside ``out`` (:func:`partial_folder`) and renamed
into place only when complete (:func:`finish`), so an interrupted run never looks like a dataset;
``synthetic.json`` is written last. The first file written is the marker ``.fisheyedepth-synthetic``: a
folder that holds it was started by this generator and may be rendered again (:func:`made_by_generator`),
anything else is somebody's data and is never replaced (:func:`refusal`). A temporary folder left behind
by a run that was killed is removed by the next run (:func:`remove_stale`).

A full disk (or quota) removes the temporary folder too and raises :class:`NoSpaceLeft`, naming the
dataset folder.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import socket
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ..files import pid_alive
from .spec import WorldSpec

MARKER = ".fisheyedepth-synthetic"  # the first file of every dataset this generator starts
# The marker's text is part of every dataset's bytes (the street digests of
# tests/test_synthetic_world_mix.py cover it), so it stays byte for byte as they have it, the module
# path it names included; the generator itself is fisheyedepth.synthetic.generate.
MARKER_TEXT = (
    "Rendered by fisheyedepth's synthetic generator (fisheyedepth.data.synthetic.generate).\n"
    "This folder may be deleted and rendered again; see docs/data-format.md.\n"
)
OWNER = ".partial-owner"  # "<host> <pid>" of the rendering run; removed before synthetic.json is written


class NotASyntheticDataset(FileExistsError):
    """A folder that fisheyedepth did not render (no ``synthetic.json``, no marker): it is never replaced."""


class DatasetMismatch(ValueError):
    """A finished synthetic dataset rendered with other generation parameters than the ones asked for."""


class NoSpaceLeft(OSError, ValueError):
    """The disk (or the quota) filled up while rendering; the partial dataset was removed. A ValueError
    too, so that the entry points report it in one line."""

    def __init__(self, out: Path, file: str | None):
        free = shutil.disk_usage(out.parent).free / 2**20 if out.parent.is_dir() else 0.0
        at = f" (writing {Path(file).name})" if file else ""
        super().__init__(
            f"{out}: no space left on device while rendering the synthetic dataset{at}; the partial "
            f"dataset was removed, {free:.0f} MB are free there: free some space or choose another folder"
        )
        self.errno = errno.ENOSPC


# ---------------------------------------------------------------- the temporary folder, renamed when complete


def _left_by_dead_run(folder: Path, pid: int) -> bool:
    """A temporary folder whose rendering run (on this machine) is gone; another machine's is kept."""
    try:
        host = (folder / OWNER).read_text().split()[0]
    except (OSError, IndexError):
        host = None  # killed before the owner file was written, or just before the rename
    return (host is None or host == socket.gethostname()) and not pid_alive(pid)


def remove_stale(out: Path) -> None:
    """Remove the hidden ``.<name>.partial-<pid>`` / ``.<name>.old-<pid>`` folders of ``out`` left behind by
    an earlier run that was killed (SIGKILL, power loss): only those whose process is no longer alive."""
    if not out.parent.is_dir():
        return
    for entry in out.parent.iterdir():
        for kind in ("partial", "old"):
            prefix = f".{out.name}.{kind}-"
            pid = entry.name[len(prefix) :]
            if entry.name.startswith(prefix) and pid.isdigit() and int(pid) != os.getpid():
                if entry.is_dir() and _left_by_dead_run(entry, int(pid)):
                    shutil.rmtree(entry, ignore_errors=True)


def temporary_folder(out: Path) -> Path:
    """This run's hidden ``.<name>.partial-<pid>`` beside ``out``, not yet made: ``out``'s parent made, the
    temporary folders of dead runs and one this process left removed."""
    out.parent.mkdir(parents=True, exist_ok=True)
    remove_stale(out)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    return tmp


@contextmanager
def partial_folder(tmp: Path, out: Path) -> Iterator[Path]:
    """``tmp`` (:func:`temporary_folder`) made, with the marker and this run's owner file, for the block to
    write ``out``'s dataset into and :func:`finish`. If the block fails (Ctrl-C and ``Terminated``
    included), ``tmp`` is removed; a full disk is raised as :class:`NoSpaceLeft`."""
    try:
        tmp.mkdir()
        (tmp / MARKER).write_text(MARKER_TEXT)
        (tmp / OWNER).write_text(f"{socket.gethostname()} {os.getpid()}\n")
        yield tmp
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise NoSpaceLeft(out, exc.filename) from exc
        raise


def _move_into_place(tmp: Path, out: Path) -> None:
    if not out.exists():
        tmp.rename(out)
        return
    old = out.parent / f".{out.name}.old-{os.getpid()}"
    out.rename(old)
    tmp.rename(out)
    if old.is_dir():
        shutil.rmtree(old, ignore_errors=True)
    else:  # the CLI's --overwrite of a file
        old.unlink(missing_ok=True)


def finish(tmp: Path, out: Path, meta: dict) -> None:
    """The dataset in ``tmp`` complete: its ``synthetic.json`` written last, then renamed to ``out`` (what
    ``out`` held before is removed)."""
    (tmp / OWNER).unlink()
    (tmp / "synthetic.json").write_text(json.dumps(meta, indent=2) + "\n")
    _move_into_place(tmp, out)


# ---------------------------------------------------------------- which folders may be rendered into


def is_complete(root: str | os.PathLike) -> bool:
    """A finished dataset has its ``synthetic.json`` (written last, before the atomic rename)."""
    return (Path(root) / "synthetic.json").is_file()


def made_by_generator(root: str | os.PathLike) -> bool:
    """``root`` was started by this generator: it holds the marker, or (older datasets) a fisheyedepth
    ``synthetic.json``. Such a folder may be rendered again; nothing else is ever replaced unasked."""
    root = Path(root)
    return (root / MARKER).is_file() or _generator_of(root).startswith("fisheyedepth")


def _generator_of(root: Path) -> str:
    try:
        meta = json.loads((root / "synthetic.json").read_text())
    except (OSError, ValueError):
        return ""
    return str(meta.get("generator", "")) if isinstance(meta, dict) else ""


def is_empty_dir(root: Path) -> bool:
    return root.is_dir() and not any(root.iterdir())


def refusal(root: Path) -> NotASyntheticDataset:
    """The error for ``root``, which this generator did not make: it is left untouched."""
    what = "a file" if not root.is_dir() else f"a folder without synthetic.json or {MARKER}"
    return NotASyntheticDataset(
        f"{root} is not a synthetic dataset made by fisheyedepth ({what}), so it was left untouched. "
        "To train on your own data, choose its layout: data=kitti360 (KITTI-360 layout) or data=rig "
        f"(robot recording), e.g. `python train.py data=rig data.datamodule.root={root}`. To render the "
        "synthetic dataset, point data.datamodule.root at an absent or empty folder."
    )


def check_parameters(root: Path, spec: WorldSpec) -> None:
    """A finished dataset is used only if it was rendered with the spec asked for."""
    path = root / "synthetic.json"
    try:
        meta = json.loads(path.read_text())
    except ValueError as exc:
        raise DatasetMismatch(f"{path} is not valid JSON ({exc}); delete {root} to render it again") from exc
    if not isinstance(meta, dict) or not str(meta.get("generator", "")).startswith("fisheyedepth"):
        raise refusal(root)
    differ = spec.differences(meta)
    if differ:
        raise DatasetMismatch(
            f"{root} holds a synthetic dataset rendered with other parameters than asked: "
            f"{', '.join(differ)}. Ask for the same ones (data.generate.*), point data.datamodule.root at "
            f"another folder, or delete {root} to render it again."
        )
