"""Small helpers shared across the package: number checks, the machine's cores and threads, a run's
config, the allocator setting (files: :mod:`.files`; signals: :mod:`.signals`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import yaml


def is_number(value) -> bool:
    """A real number (int or float, NumPy's too), not a bool or a string."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


def is_whole(value) -> bool:
    """A whole number (int, NumPy's too), not a bool."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def cores() -> int:
    """The CPU cores this process may run on (its affinity where the system says; else every core)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def check_threads(value, option: str) -> int:
    """``value`` as a thread count from 1 to :func:`cores`, else a ValueError naming ``option`` (more
    threads than cores only slow a CPU down, and thousands fail inside the thread library)."""
    most = cores()
    if not is_whole(value) or not 1 <= value <= most:
        raise ValueError(f"{option}: {value!r}; a whole number from 1 to {most} (this machine's cores)")
    return int(value)


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
