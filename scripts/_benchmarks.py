"""Shared by the benchmark scripts: each owns one marked section of BENCHMARKS.md."""

from __future__ import annotations

import statistics
import sys
from collections.abc import Callable, Sequence
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


def alternate(kinds: Sequence[str], rounds: int, measure: Callable[[str], dict]) -> dict[str, list[dict]]:
    """``measure(kind)`` once per kind and round, the order swapped every other round (so neither kind
    always runs first on a warming or cooling machine): ``{kind: [one result per round]}``."""
    results: dict[str, list[dict]] = {k: [] for k in kinds}
    for r in range(rounds):
        for kind in kinds if r % 2 == 0 else kinds[::-1]:
            results[kind].append(measure(kind))
            print(f"round {r}: {kind}: {results[kind][-1]}", file=sys.stderr)
    return results


def paired_ratio(before: list[dict], after: list[dict], key: str) -> float:
    """The median over rounds of ``before[key] / after[key]``: the speed-up, paired per round."""
    return statistics.median(a[key] / b[key] for a, b in zip(before, after, strict=True))
