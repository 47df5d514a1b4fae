#!/usr/bin/env python
"""The full model's training step on a GPU (BENCHMARKS.md, "Time to accuracy"): the
network in float32 against bf16 autocast (``trainer.precision`` auto on a GPU), and ``gpu_10min``'s
step (bf16, compiled kernels off) against the same with ``model.compile_kernels`` on. The variants take
turns within every round, on one batch of a small rendered world (batch 4 at 256x256, two sources,
4 scales, channels_last, loss at native resolution: ``cpu_30min``'s model; Adam as
``bench_training.py`` makes it, not the fused one that training uses on a GPU).

    python scripts/bench/bench_gpu_step.py [--device cuda] [--rounds 5] [--steps 20] [--variants NAME ...]
        [--quick]

Prints a Markdown table: each variant's warm-up (its compilation included) and its median time per
step; the ratios are against the first variant measured. Nothing is written: paste the table into
BENCHMARKS.md with the command and the device.
"""

from __future__ import annotations

import statistics
import tempfile
from pathlib import Path

import torch

from bench_training import make_batch, make_module, step
from fisheyedepth.synthetic import WorldSpec, generate

from _benchmarks import bench_parser, interleaved, parse_args, timed

VARIANTS = {  # name: (bf16 autocast, compiled kernels)
    "float32": (False, False),
    "bf16 autocast (gpu_10min)": (True, False),
    "bf16 autocast + compiled kernels": (True, True),
}


def main(argv=None) -> int:
    parser = bench_parser(__doc__, write=False)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=20, help="steps timed together in each round")
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    args = parse_args(parser, argv, quick={"rounds": 1, "steps": 1, "warmup": 1, "size": 64, "batch": 1})
    device = torch.device(args.device)
    sync = (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else None
    with tempfile.TemporaryDirectory() as tmp:
        spec = WorldSpec("kitti360", frames=20, size=args.size, seed=0)
        root = generate(Path(tmp) / "d", spec, lidar=False, progress=False)
        batch = make_batch(root, args.size, args.batch, Path(tmp) / "cache").to(device)
    runs, warmup = {}, {}
    for name in args.variants:
        bf16, compiled = VARIANTS[name]
        module, optimizer = make_module("FFT + RS + MC (full)", True, "native", compiled)
        module.to(device)  # the optimiser holds the same parameters; its state is made at the first step
        runs[name] = lambda m=module, o=optimizer, bf16=bf16: step(m, o, batch, bf16)
        warmup[name] = timed(lambda run=runs[name]: [run() for _ in range(args.warmup)], sync)
    # each round: every variant's block of --steps steps, timed together
    times = interleaved(runs, args.rounds, warmup=0, repeat=args.steps, together=True, sync=sync)
    names = list(runs)
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
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
