"""Memory an option would need, checked against the machine's before any work: one refusal naming the
option (or the file), what it needs and what the machine has (:func:`check_memory`); each bound a formula
of what the option allocates, kept beside its reader."""

from __future__ import annotations

import os
from typing import Any


# ------------------------------------------------------------------------------------------ memory
def machine_memory() -> int:
    """This machine's physical memory in bytes (``psutil`` where installed, else ``sysconf``)."""
    try:
        import psutil

        return int(psutil.virtual_memory().total)
    except ImportError:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def in_bytes(n: float) -> str:
    """``n`` bytes for a reader: ``512 MiB``, ``15.6 GiB``, ``8.4 TiB``."""
    for unit, scale in (("PiB", 2**50), ("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n:.0f} bytes"


def check_memory(name: str, value: Any, needed: float, what: str) -> None:
    """A ValueError ``<name>: <value> needs <bytes> of memory (<what>); this machine has <bytes>`` when
    ``needed`` bytes, what the option makes a command allocate, exceed this machine's physical memory
    (:func:`machine_memory`): refused at once, not after hours of swapping or by the kernel's OOM killer."""
    total = machine_memory()
    if needed > total:
        have = in_bytes(total)
        raise ValueError(
            f"{name}: {value!r} needs {in_bytes(needed)} of memory ({what}); this machine has {have}"
        )
