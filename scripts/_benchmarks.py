"""Shared by the benchmark scripts: each owns one marked section of BENCHMARKS.md."""

from __future__ import annotations

import sys
from pathlib import Path

from fisheyedepth.utils import atomic_write_text

# The world `make train` renders (conf/data/synthetic.yaml): benchmarks read its frames.
WORLD = Path(__file__).resolve().parents[1] / "data" / "synthetic_kitti360_256_seed0_f600"
HEADER = "# Benchmarks\n\nEach section names the command that produced it.\n\n"


def write_section(path: Path, start: str, end: str, section: str) -> None:
    """Replace the text between ``start`` and ``end`` markers (or append it), atomically."""
    text = path.read_text() if path.exists() else HEADER
    if start in text and end in text:
        head, rest = text.split(start, 1)
        tail = rest.split(end, 1)[1].lstrip("\n")
        text = head + section + ("\n" + tail if tail else "")
    else:
        text = text.rstrip("\n") + "\n\n" + section
    atomic_write_text(path, text)


def publish(section: str, path: Path, start: str, end: str, write: bool) -> None:
    """Print the section and, unless told not to, store it in ``path``."""
    print(section)
    if write:
        write_section(path, start, end, section)
        print(f"written to {path}", file=sys.stderr)


def peak_rss_kb() -> int:
    """This process's peak resident set in kB (``VmHWM``, Linux; ``ru_maxrss`` would include a forked
    parent's)."""
    status = Path("/proc/self/status").read_text()
    return next(int(line.split()[1]) for line in status.splitlines() if line.startswith("VmHWM:"))
