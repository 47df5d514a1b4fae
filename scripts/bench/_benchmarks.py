"""The skeleton every ``scripts/bench/bench_*.py`` shares; each benchmark owns one marked section of
BENCHMARKS.md (``<!-- bench_NAME:start -->`` ... ``<!-- bench_NAME:end -->``).

- :func:`bench_parser` and :func:`parse_args`: the common flags (``--no-write``, ``--output``, ``--quick``:
  the smallest sizes, for a smoke run, never written) and a hidden ``--child`` for measurements that
  need a process of their own;
- :func:`run_child` and :func:`child_result`: one measurement in a fresh Python process (a process-wide
  setting, a clean peak resident set), its result one JSON line;
- :func:`timed`, :func:`repeated` and :func:`interleaved`: wall-clock timing with warm-up and repeats,
  variants taking turns round by round so that machine noise hits all alike; :func:`alternate` and
  :func:`paired_ratio` for two kinds measured by child processes;
- :func:`peak_rss_kb` and :func:`peak_rss_of`: the peak resident set of this process or of a command;
- :func:`markers` and :func:`publish`: a section printed and written between its markers.

Importing it puts ``scripts/`` on ``sys.path``: the benchmarks import ``_compose`` from there, as the
other scripts do.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from fisheyedepth.files import atomic_write_text

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "scripts"))  # for _compose
BENCHMARKS = ROOT / "BENCHMARKS.md"
# The world `make train` renders (conf/data/synthetic.yaml): benchmarks read its frames.
WORLD = ROOT / "data" / "synthetic_kitti360_256_seed0_f600"
HEADER = "# Benchmarks\n\nEach section names the command that produced it.\n\n"


# ------------------------------------------------------------------------------------------- flags
def bench_parser(doc: str | None, write: bool = True) -> argparse.ArgumentParser:
    """The parser every benchmark starts from: its docstring as help, ``--quick`` and, for one that
    writes a section (``write``), ``--no-write`` and ``--output``."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    if write:
        parser.add_argument("--no-write", action="store_true", help="print only; leave the file alone")
        parser.add_argument("--output", type=Path, default=BENCHMARKS, help="default: %(default)s")
    parser.add_argument(
        "--quick", action="store_true", help="the smallest sizes, to check that it runs (never written)"
    )
    parser.add_argument("--child", nargs="*", help=argparse.SUPPRESS)
    return parser


def parse_args(parser: argparse.ArgumentParser, argv=None, quick: Mapping[str, Any] | None = None):
    """Parsed flags; with ``--quick``, the flags in ``quick`` take its values and nothing is written."""
    args = parser.parse_args(argv)
    if args.quick:
        for key, value in (quick or {}).items():
            setattr(args, key, value)
        if hasattr(args, "no_write"):
            args.no_write = True
    return args


# -------------------------------------------------------------------------------- child processes
def run_child(
    script: str | os.PathLike,
    arguments: Sequence[str],
    env: Mapping[str, str] | None = None,
    cwd: str | os.PathLike | None = None,
) -> Any:
    """``python SCRIPT --child ARGUMENTS`` in a fresh process (``env``: variables set on top of this
    process's), and the last line it printed, read as JSON (:func:`child_result`). A failed child raises,
    with the end of its stderr."""
    command = [sys.executable, str(script), "--child", *map(str, arguments)]
    environment = dict(os.environ, **env) if env is not None else None
    out = subprocess.run(command, capture_output=True, text=True, env=environment, cwd=cwd)
    if out.returncode:
        raise RuntimeError(f"{' '.join(command[1:])}: child failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def child_result(value: Any) -> None:
    """What a child measured, as the one line :func:`run_child` reads."""
    print(json.dumps(value), flush=True)


# ------------------------------------------------------------------------------------------ timing
def timed(fn: Callable[[], object], sync: Callable[[], None] | None = None) -> float:
    """Seconds of one ``fn()``; ``sync`` (e.g. ``torch.cuda.synchronize``) before and after it."""
    if sync is not None:
        sync()
    t0 = time.perf_counter()
    fn()
    if sync is not None:
        sync()
    return time.perf_counter() - t0


def interleaved(
    runs: Mapping[str, Callable[[], object]],
    rounds: int,
    warmup: int = 1,
    repeat: int = 1,
    together: bool = False,
    settle: bool = False,
    sync: Callable[[], None] | None = None,
) -> dict[str, list[float]]:
    """Every run ``warmup`` times (in order), then ``rounds`` rounds in which the runs take turns, the
    order rotated by one every round. A turn: one untimed call first when ``settle`` (the previous run's
    idle threads settle), then ``repeat`` calls, timed one by one (a time each) or ``together`` (their
    mean). ``{name: [seconds, ...]}``."""
    for run in runs.values():
        for _ in range(warmup):
            run()
    names = list(runs)
    times: dict[str, list[float]] = {name: [] for name in names}
    for r in range(rounds):
        for name in names[r % len(names) :] + names[: r % len(names)]:
            run = runs[name]
            if settle:
                run()
            if together:
                times[name].append(timed(lambda run=run: [run() for _ in range(repeat)], sync) / repeat)
            else:
                times[name] += [timed(run, sync) for _ in range(repeat)]
    return times


def repeated(
    fn: Callable[[], object], repeats: int, warmup: int = 1, sync: Callable[[], None] | None = None
) -> list[float]:
    """Seconds of ``repeats`` calls of ``fn`` after ``warmup`` untimed ones."""
    return interleaved({"": fn}, repeats, warmup, sync=sync)[""]


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


def cpu_name(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The CPU's model name and widest vector unit (``AVX-512 BF16``, ``AVX-512``, ``AVX2``; ``AMX``), as
    ``/proc/cpuinfo`` says (Linux); the architecture alone elsewhere."""
    try:
        text = cpuinfo.read_text()
    except OSError:
        return platform.machine()
    fields = dict(line.split(":", 1) for line in text.splitlines() if ":" in line)
    fields = {key.strip(): value.strip() for key, value in fields.items()}
    flags = set(fields.get("flags", "").split())
    isa = next((name for flag, name in _VECTOR_UNITS if flag in flags), "no AVX2")
    amx = ", AMX" if "amx_bf16" in flags else ""
    return f"{fields.get('model name', platform.machine())}, {isa}{amx}"


_VECTOR_UNITS = (("avx512_bf16", "AVX-512 BF16"), ("avx512f", "AVX-512"), ("avx2", "AVX2"))


# ------------------------------------------------------------------------------------------ memory
def peak_rss_kb() -> int:
    """This process's peak resident set in kB (``VmHWM``, Linux; ``ru_maxrss`` would include a forked
    parent's)."""
    status = Path("/proc/self/status").read_text()
    return next(int(line.split()[1]) for line in status.splitlines() if line.startswith("VmHWM:"))


# A small Python process that runs the command and prints the largest resident set of its children.
_PROBE = (
    "import resource, subprocess, sys;"
    "r = subprocess.run(sys.argv[1:], capture_output=True, text=True);"
    "sys.stderr.write(r.stderr[-3000:]);"
    "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss); sys.exit(r.returncode)"
)


def peak_rss_of(
    command: Sequence[str], env: Mapping[str, str] | None = None, cwd: str | os.PathLike | None = None
) -> int:
    """The peak resident set (kB) of ``command``, run to its end; a failure raises with its stderr."""
    environment = dict(os.environ, **env) if env is not None else None
    proc = subprocess.run(
        [sys.executable, "-c", _PROBE, *map(str, command)],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=environment,
    )
    if proc.returncode:
        raise RuntimeError(proc.stderr)
    return int(proc.stdout.strip().splitlines()[-1])


# ---------------------------------------------------------------------------------------- sections
def markers(name: str) -> tuple[str, str]:
    """The markers around benchmark ``name``'s section of BENCHMARKS.md."""
    return f"<!-- {name}:start -->", f"<!-- {name}:end -->"


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


def require_world() -> None:
    """Stop with a message unless world 0 of ``make train`` is rendered."""
    if not (WORLD / "splits" / "train.txt").exists():
        raise SystemExit(f"{WORLD}: render it first (make train renders it on first use)")
