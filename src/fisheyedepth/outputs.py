"""Files written as a pair with their ``.json`` record, and never over another command's: what
``export.py`` needs when two runs write one output at once. One run at a time holds the output's lock
(:func:`output_lock`); the file and its record are written in full beside their targets, then put in
place together (:func:`place`), hard-linked where nothing may be replaced, so a file that appeared
meanwhile is refused, not overwritten; a folder that refuses writes is named (:func:`writable`)."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from .files import WRITE_ERRORS, drop_lock, place_new, take_lock, temporary_beside


def record_path(path: Path) -> Path:
    """The ``.json`` record beside an exported file: what it is, where from, its parity and its sha256."""
    return path.with_suffix(path.suffix + ".json")


def refuse_existing(path: Path, overwrite: bool) -> None:
    """Without ``overwrite``: a FileExistsError when the file or its record is there already."""
    for taken in (path, record_path(path)):
        if taken.exists() and not overwrite:
            raise FileExistsError(f"{taken} exists; pass overwrite=true to replace it")


@contextlib.contextmanager
def output_lock(path: Path):
    """Hold ``.NAME.lock`` beside ``path`` (``flock``, waited for) while the block runs: two export.py
    writing one file take turns, so the second sees the first's file (and is refused without
    overwrite=true) or replaces file and record together. The kernel lets the lock go when a process
    ends, however it ends; the lock file is removed by its holder (as the run folders' ``.train.lock``)."""
    lock = path.parent / f".{path.name}.lock"
    with writable(path):  # before the export's work: a folder it cannot write fails at once
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = take_lock(lock, wait=True)
    try:
        yield
    finally:
        drop_lock(fd, lock)


def place(path: Path, data: bytes, record: str, overwrite: bool) -> None:
    """The exported file and its record, written as a pair: both written in full to temporary files
    beside them first (a full disk fails here, replacing nothing), then moved into place one after the
    other, under :func:`output_lock` (no other export.py writes between the two). Without ``overwrite``
    neither may replace a file that appeared after :func:`refuse_existing`: each is hard-linked into
    place, which fails if its name is taken, and the file placed first is taken back if the record
    cannot follow. The record's sha256 tells whether a file and the record beside it belong together."""
    record_file = record_path(path)
    with staged(path, data) as file_tmp, staged(record_file, record.encode()) as record_tmp:
        if overwrite:
            os.replace(file_tmp, path)
            os.replace(record_tmp, record_file)
            return
        place_new(file_tmp, path)
        try:
            place_new(record_tmp, record_file)
        except BaseException:
            path.unlink()
            raise


@contextlib.contextmanager
def staged(path: Path, data: bytes):
    """``data`` in a temporary file beside ``path`` (:func:`~fisheyedepth.files.temporary_beside`);
    removed when the block ends, unless it was moved into place."""
    with temporary_beside(path) as tmp:
        tmp.write_bytes(data)
        yield str(tmp)


@contextlib.contextmanager
def writable(path: Path):
    """A folder that cannot be written (:data:`~fisheyedepth.files.WRITE_ERRORS`) is a ValueError naming
    ``path`` and why, not a traceback: the output option is at fault, as a missing checkpoint is."""
    try:
        yield
    except OSError as err:
        if err.errno not in WRITE_ERRORS:
            raise
        where = f": {err.filename}" if err.filename and Path(err.filename) != path else ""
        raise ValueError(
            f"{path}: cannot be written ({err.strerror}{where}); choose another output=FILE"
        ) from None
