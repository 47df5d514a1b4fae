"""Small helpers shared across the package."""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import yaml


def run_config(run: str | os.PathLike) -> dict[str, Any]:
    """A run folder's Hydra config (``RUN/.hydra/config.yaml``) as plain data; {} when it has none."""
    path = Path(run) / ".hydra" / "config.yaml"
    if not path.is_file():
        return {}
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise ValueError(f"{path}: not readable YAML ({err})") from err
    return data if isinstance(data, dict) else {}


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` through a temporary file in the same folder and an atomic rename."""
    return atomic_write_bytes(path, text.encode())


def current_umask() -> int:
    """The process's file-creation mask (read without changing it where Linux allows)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)  # elsewhere: set and restore
    os.umask(mask)
    return mask


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Like :func:`atomic_write_text`, for bytes. The file gets the permissions a plain ``open`` would
    give it (0666 less the umask), not ``mkstemp``'s private 0600."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            os.fchmod(handle.fileno(), 0o666 & ~current_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


@contextlib.contextmanager
def staged_folder(out: str | os.PathLike, label: str):
    """A hidden folder beside ``out`` (the same filesystem, so the final move is a rename) in which an
    importer builds ``out``, with a plain folder's permissions (not ``mkdtemp``'s private 0700); removed
    with whatever is left in it when the block ends, however it ends."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.{label}-", dir=out.parent))
    try:
        staging.chmod(0o777 & ~current_umask())
        yield staging
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def move_into_place(staging: Path, out: Path, parts: list[Path]) -> None:
    """The finished ``staging`` folder becomes ``out`` (one rename), or, where ``out`` holds other files
    already, its ``parts`` (paths relative to both, in order) replace theirs: a folder part whole, so no
    stale file of an earlier import stays; put last the file that marks ``out`` complete."""
    if not out.exists() or not any(out.iterdir()):
        os.replace(staging, out)
        return
    for part in parts:
        (out / part).parent.mkdir(parents=True, exist_ok=True)
        if (out / part).is_dir():  # a folder cannot replace a non-empty one: set the old one aside
            (out / part).rename(staging / ".replaced")
        os.replace(staging / part, out / part)


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this machine (another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def file_key(path: str | os.PathLike, *extra: str) -> str:
    """A cache key for a file's current content, cheap to compute: its resolved path, size and
    modification time (and ``extra``). A file replaced in place gets a new key, unless it keeps both its
    size and its modification time (``cp -p``, ``rsync -t``): delete the cache entry then."""
    path = Path(path)
    stat = path.stat()
    ident = "|".join((str(path.resolve()), str(stat.st_size), str(stat.st_mtime_ns), *extra))
    return hashlib.sha1(ident.encode()).hexdigest()[:20]


# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_MAX = -1, -2, -4


def keep_freed_memory(top_pad: int = 1 << 29, trim_threshold: int = 1 << 30) -> bool:
    """Serve large allocations from the heap and keep freed memory for reuse (glibc only).

    By default glibc gives every allocation above 32 MB (a training step's activations, the warps'
    grids) its own ``mmap`` and returns it to the kernel when freed, so the next step faults in and
    zeroes the same pages again: tens of thousands of page faults per 256 px training step here
    (what they cost: BENCHMARKS.md, "Memory allocator"). With ``mmap`` off (``M_MMAP_MAX`` 0) and a high trim
    threshold, freed blocks stay in the heap and are reused. The process keeps its peak memory.
    Process-wide; the DataLoader's forked workers inherit it. Returns False (and changes nothing)
    where the C library is not glibc."""
    import ctypes
    import platform

    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    settings = ((_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, trim_threshold), (_M_TOP_PAD, top_pad))
    return all(libc.mallopt(param, value) == 1 for param, value in settings)
