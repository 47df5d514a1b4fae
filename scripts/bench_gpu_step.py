#!/usr/bin/env python
"""The full model's training step on a GPU (BENCHMARKS.md, "Time to accuracy"): the
network in float32 against bf16 autocast (``trainer.precision`` auto on a GPU), and ``gpu_10min``'s
step (bf16, compiled kernels off) against the same with ``model.compile_kernels`` on. The variants take
turns within every round, on one batch of a small rendered world (batch 4 at 256x256, two sources,
4 scales, channels_last, loss at native resolution: ``cpu_30min``'s model; Adam as
``bench_training.py`` makes it, not the fused one that training uses on a GPU).

    python scripts/bench_gpu_step.py [--device cuda] [--rounds 5] [--steps 20] [--variants NAME ...]

Prints a Markdown table: each variant's warm-up (its compilation included) and its median time per
step; the ratios are against the first variant measured. Nothing is written: paste the table into
BENCHMARKS.md with the command and the device.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch

from bench_training import make_batch, make_module, step
from fisheyedepth.data.synthetic import generate

VARIANTS = {  # name: (bf16 autocast, compiled kernels)
    "float32": (False, False),
    "bf16 autocast (gpu_10min)": (True, False),
    "bf16 autocast + compiled kernels": (True, True),
}


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=20, help="steps timed together in each round")
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    with tempfile.TemporaryDirectory() as tmp:
        root = generate(
            Path(tmp) / "d", "kitti360", frames=20, size=args.size, seed=0, lidar=False, progress=False
        )
        batch = make_batch(root, args.size, args.batch, Path(tmp) / "cache").to(device)
    runs, warmup = {}, {}
    for name in args.variants:
        bf16, compiled = VARIANTS[name]
        module, optimizer = make_module("FFT + RS + MC (full)", True, "native", compiled)
        module.to(device)  # the optimiser holds the same parameters; its state is made at the first step
        synchronize(device)
        t0 = time.perf_counter()
        for _ in range(args.warmup):
            step(module, optimizer, batch, bf16)
        synchronize(device)
        warmup[name] = time.perf_counter() - t0
        runs[name] = (module, optimizer, bf16)
    times: dict[str, list[float]] = {name: [] for name in runs}
    names = list(runs)
    for r in range(args.rounds):
        for name in names[r % len(names) :] + names[: r % len(names)]:
            module, optimizer, bf16 = runs[name]
            synchronize(device)
            t0 = time.perf_counter()
            for _ in range(args.steps):
                step(module, optimizer, batch, bf16)
            synchronize(device)
            times[name].append((time.perf_counter() - t0) / args.steps)
    where = (
        torch.cuda.get_device_name(device)
        if device.type == "cuda"
        else f"{device} ({torch.get_num_threads()} threads)"
    )
    print(
        f"{where}, torch {torch.__version__}; batch {args.batch} at {args.size}x{args.size}; "
        f"median of {args.rounds} interleaved rounds of {args.steps} steps"
    )
    print("| variant | warm-up s (compilation included) | ms per step | against the first |")
    print("|---|---|---|---|")
    first = names[0]
    for name in names:
        ratio = statistics.median(a / b for a, b in zip(times[name], times[first], strict=True))
        print(f"| {name} | {warmup[name]:.1f} | {1000 * statistics.median(times[name]):.1f} | {ratio:.2f}x |")


if __name__ == "__main__":
    main()
