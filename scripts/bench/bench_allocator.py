#!/usr/bin/env python
"""The memory allocator as a speed lever: the full model's training step with glibc's defaults against
the same step after ``fisheyedepth.utils.keep_freed_memory()`` (``keep_freed_memory: true`` in
``conf/train.yaml``); results go into BENCHMARKS.md.

The setting is process-wide, so each measurement is a fresh child process (2 threads) that takes
``--steps`` steps of the ``cpu_30min`` step: batch 4 at 256x256, two sources, bf16 autocast of the
networks, channels_last, the loss at each scale's native resolution, compiled kernels. The two kinds
of child alternate for ``--rounds`` rounds (the order swapped every round) and the speed-up is the
median over rounds of the paired ratio. Page faults (minor, per step) and the peak resident set say
why. Reads world 0 of ``make train`` (rendered on first use, like ``make train`` does).

Usage: python scripts/bench/bench_allocator.py [--rounds 4] [--steps 8] [--no-write] [--quick]
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

from _benchmarks import (
    WORLD,
    alternate,
    bench_parser,
    child_result,
    markers,
    paired_ratio,
    parse_args,
    peak_rss_kb,
    publish,
    repeated,
    require_world,
    run_child,
)

START, END = markers("bench_allocator")
KINDS = ("glibc defaults", "keep_freed_memory")


def child(kind: str, steps: int, cache: Path) -> None:
    """One measurement: ``steps`` training steps, printed as JSON (median step, faults, peak)."""
    if kind == KINDS[1]:  # before torch allocates anything
        from fisheyedepth.utils import keep_freed_memory

        assert keep_freed_memory(), "keep_freed_memory needs glibc"
    import torch

    from bench_training import make_batch, make_module, step

    torch.set_num_threads(2)
    batch = make_batch(WORLD, 256, 4, cache)
    module, optimizer = make_module("FFT + RS + MC (full)", True, "native", True)  # cpu_30min's step
    for _ in range(2):  # two warm-up steps (compilation, first allocations)
        step(module, optimizer, batch, bf16=True)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    times = repeated(lambda: step(module, optimizer, batch, bf16=True), steps, warmup=0)
    faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults) / steps
    peak = peak_rss_kb() / 1024
    child_result({"step": statistics.median(times), "faults": faults, "peak_mb": peak})


def measure(kind: str, steps: int, cache: Path) -> dict[str, float]:
    return run_child(__file__, [kind, "--steps", steps, "--cache", cache])


def main(argv=None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--cache", type=Path, help=argparse.SUPPRESS)
    args = parse_args(parser, argv, quick={"rounds": 1, "steps": 1})
    if args.child:
        child(args.child[0], args.steps, args.cache)
        return 0
    require_world()
    with tempfile.TemporaryDirectory(prefix="fd-bench-alloc-") as tmp:
        results = alternate(KINDS, args.rounds, lambda kind: measure(kind, args.steps, Path(tmp)))
    ratio = paired_ratio(results[KINDS[0]], results[KINDS[1]], "step")
    lines = [
        START,
        "## Memory allocator (`scripts/bench/bench_allocator.py`)",
        "",
        f"Command: `python scripts/bench/bench_allocator.py --rounds {args.rounds} --steps {args.steps}`  ",
        f"Machine: {os.cpu_count()} CPUs ({platform.machine()}), {platform.libc_ver()[0]} "
        f"{platform.libc_ver()[1]}, 2 threads; {time.strftime('%Y-%m-%d')}. The `cpu_30min` training "
        f"step (batch 4 at 256x256, two sources, bf16, channels_last, native-resolution loss, compiled "
        f"kernels), {args.steps} steps per fresh process after two warm-up steps; the two kinds alternate "
        f"for {args.rounds} rounds.",
        "",
        "| allocator | step time (median of rounds) | minor page faults per step | peak RSS |",
        "|---|---|---|---|",
    ]
    for kind in KINDS:
        rows = results[kind]
        lines.append(
            f"| {kind} | {statistics.median(r['step'] for r in rows):.3f} s | "
            f"{statistics.median(r['faults'] for r in rows):,.0f} | "
            f"{statistics.median(r['peak_mb'] for r in rows):,.0f} MB |"
        )
    lines += ["", f"Speed-up (median of the paired per-round ratios): **{ratio:.2f}x**.", END]
    publish("\n".join(lines) + "\n", args.output, START, END, write=not args.no_write)
    return 0


if __name__ == "__main__":
    sys.exit(main())
