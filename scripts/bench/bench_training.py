#!/usr/bin/env python
"""Training-step time and peak memory for the Table 2 configurations; results go into BENCHMARKS.md.

One step = forward, losses at 4 scales, backward and an Adam step, batch 4 at 256x256 on a synthetic
kitti360 batch (two source frames), 2 CPU threads. Times are measured side by side: configurations
take turns within every round. Peak memory is the peak resident set (VmHWM, Linux) of a fresh process
that ran two steps of one configuration.
Targets: fisheye projection <= 5 % of a step (full model against itself with pinhole projection);
real-scale poses make the step >= 1.6x faster than the same model with a PoseNet.

Then the speed levers of the full model's step, side by side in the same interleaved rounds, each
against the step as it was before them (``avg_pool2d`` SSIM, NCHW weights): box-sum SSIM (adopted),
bf16 autocast of the networks (``trainer.precision=bf16-mixed``;
geometry and losses stay float32), channels_last, the loss at each scale's native resolution and
``torch.compile``'d kernels (the bin expectation and the photometric error; ``model.compile_kernels``),
each a module switch, and the compiled expectation's bin sums as channel reductions, which the compiler
fuses, instead of the 1x1 convolution whose backward it calls as an external kernel (always on with
``compile_kernels``).

Usage: python scripts/bench/bench_training.py [--rounds 5] [--size 256] [--batch 4] [--no-write] [--quick]
To stand for a CPU without AVX-512, prefix ``ONEDNN_MAX_CPU_ISA=AVX2 ATEN_CPU_CAPABILITY=avx2`` (oneDNN's
convolutions and ATen's kernels then use AVX2 only; the machine line says avx2).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import torch
from torch.nn import functional as F

import fisheyedepth.losses.photometric as photometric
from fisheyedepth.data import collate
from fisheyedepth.models import bin_expectation
from fisheyedepth.module import FisheyeDepthModule
from fisheyedepth.synthetic import WorldSpec, generate

from _benchmarks import (
    bench_parser,
    child_result,
    interleaved,
    markers,
    parse_args,
    peak_rss_kb,
    publish,
    run_child,
)
from _compose import build_datamodule, build_module, compose_config

START, END = markers("bench_training")
# Every row's model: ``model=fisheyedepth`` (conf/model/) with these overrides: sources one frame before
# and after the target (the batch's too), no training pictures. Then where a row's switches and levers are.
MODEL = ["model=fisheyedepth", "model.objective.source_offsets=[-1,1]", "model.log_images_every=0"]
SWITCHES = ("model.objective.fisheye_projection", "model.objective.real_scale", "model.net.multi_channel")
CHANNELS_LAST, COMPILE_KERNELS = "model.net.channels_last", "model.compile_kernels"
LOSS_RESOLUTION = "model.objective.loss_resolution"
# The training batch: ``data=synthetic`` on the world given, un-augmented (the same batch every time).
BATCH_DATA = ["data=synthetic", "data.datamodule.augment=null"]
CONFIGS = {  # name: (fisheye_projection, real_scale, multi_channel)
    "Monodepth2 baseline": (False, False, False),
    "FFT": (True, False, False),
    "FFT + RS": (True, True, False),
    "FFT + MC": (True, False, True),
    "FFT + RS + MC (full)": (True, True, True),
    "full, pinhole projection": (False, True, True),
}


def make_batch(root: Path, size: int, batch: int, cache_dir: Path):
    """The first ``batch`` training samples of the synthetic dataset at ``root``, at ``size`` x ``size``."""
    values = {
        "data.datamodule.root": root,
        "data.datamodule.size": [size, size],
        "data.datamodule.cache_dir": cache_dir,
    }
    dataset = build_datamodule(compose_config(BATCH_DATA + MODEL, values)).dataset("train")
    return collate([dataset[i] for i in range(batch)])


# name: (box-sum SSIM, channels_last, bf16 autocast of the networks, compiled kernels, loss at each
#        scale's native resolution, the compiled bin expectation's sums as channel reductions instead of
#        a 1x1 convolution); the first seven rows add their lever to the row above, the last three one
#        lever each to the float32 step with box-sum SSIM (row 2)
LEVERS = {
    "before: avg_pool2d SSIM, NCHW, float32, loss at full resolution": (
        False,
        False,
        False,
        False,
        False,
        False,
    ),
    "+ box-sum SSIM": (True, False, False, False, False, False),
    "+ bf16 autocast of the networks": (True, False, True, False, False, False),
    "+ channels_last": (True, True, True, False, False, False),
    "+ loss at native resolution": (True, True, True, False, True, False),
    "+ compiled kernels (bin expectation, photometric error)": (True, True, True, True, True, False),
    "+ the compiled expectation's bin sums as channel reductions": (True, True, True, True, True, True),
    "float32, box-sum SSIM + channels_last": (True, True, False, False, False, False),
    "float32, box-sum SSIM + loss at native resolution": (True, False, False, False, True, False),
    "float32, box-sum SSIM + compiled kernels": (True, False, False, True, False, True),
}
N_STACKED = 7  # rows of LEVERS that stack
BOX_MEAN3 = photometric.box_mean3


def avg_pool_mean3(x: torch.Tensor) -> torch.Tensor:
    """The 3x3 mean SSIM used before the box-sum lever."""
    return F.avg_pool2d(x, 3, 1)


def make_module(
    config: str, channels_last: bool = False, loss_resolution: str = "full", compiled: bool = False
) -> tuple[FisheyeDepthModule, torch.optim.Optimizer]:
    """Row ``config``'s model with the levers given (base focal unset: depth_scale 1), and an Adam."""
    flags = [*zip(SWITCHES, CONFIGS[config], strict=True), (CHANNELS_LAST, channels_last)]
    flags += [(LOSS_RESOLUTION, loss_resolution), (COMPILE_KERNELS, compiled)]
    overrides = [f"{key}={str(value).lower()}" for key, value in flags]
    torch.manual_seed(0)
    module = build_module(compose_config(MODEL + overrides), base_focal=None)
    module.on_fit_start()  # what the trainer calls first: compiles the kernels when asked
    return module, torch.optim.Adam(module.parameters(), lr=1e-4)


def step(module, optimizer, batch, bf16: bool = False) -> None:
    # as trainer.precision=bf16-mixed, on the batch's device (bench_gpu_step.py runs it on a GPU)
    with torch.autocast(batch.image.device.type, dtype=torch.bfloat16, enabled=bf16):
        loss, _ = module.objective(batch, module(batch.image, batch.camera))  # geometry and loss in float32
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()


class Lever:
    """The full model's step with one set of levers (SSIM's mean is swapped in for its steps)."""

    def __init__(
        self, box: bool, channels_last: bool, bf16: bool, compiled: bool, native: bool, reduced: bool
    ):
        self.box, self.bf16 = box, bf16
        resolution = "native" if native else "full"
        self.module, self.optimizer = make_module("FFT + RS + MC (full)", channels_last, resolution, compiled)
        if compiled and not reduced:  # the compiled expectation as it was first: sums by a 1x1 convolution
            self.module.depth_net.expectation = torch.compile(bin_expectation)

    def __call__(self, batch) -> None:
        photometric.box_mean3 = BOX_MEAN3 if self.box else avg_pool_mean3
        try:
            step(self.module, self.optimizer, batch, self.bf16)
        finally:
            photometric.box_mean3 = BOX_MEAN3


def memory_child(config: str, root: Path, size: int, batch: int) -> None:
    torch.set_num_threads(2)
    data = make_batch(root, size, batch, root.parent / "cache")
    module, optimizer = make_module(config)
    for _ in range(2):
        step(module, optimizer, data)
    child_result(peak_rss_kb())


def main(argv=None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--data", type=Path, help=argparse.SUPPRESS)
    args = parse_args(parser, argv, quick={"rounds": 1, "size": 64, "batch": 1})
    if args.child:
        memory_child(args.child[0], args.data, args.size, args.batch)
        return 0
    torch.set_num_threads(2)
    with tempfile.TemporaryDirectory() as tmp:
        spec = WorldSpec("kitti360", frames=20, size=args.size, seed=0)
        root = generate(Path(tmp) / "d", spec, lidar=False, progress=False)
        data = make_batch(root, args.size, args.batch, Path(tmp) / "cache")
        modules = {name: make_module(name) for name in CONFIGS}
        levers = {name: Lever(*flags) for name, flags in LEVERS.items()}
        runs = {name: (lambda m=m, o=o: step(m, o, data)) for name, (m, o) in modules.items()}
        runs |= {name: (lambda lever=lever: lever(data)) for name, lever in levers.items()}
        times = interleaved(runs, args.rounds, warmup=1)  # the warm-up compiles too
        peak = {}
        for name in CONFIGS:
            memory = [name, "--data", root, "--size", args.size, "--batch", args.batch]
            peak[name] = run_child(__file__, memory) / 1024

    med = {name: statistics.median(ts) for name, ts in times.items()}

    def paired(a: str, b: str) -> float:
        return statistics.median(x / y for x, y in zip(times[a], times[b], strict=True))

    fisheye_cost = paired("FFT + RS + MC (full)", "full, pinhole projection") - 1
    posenet_speedup = paired("FFT + MC", "FFT + RS + MC (full)")
    lines = [
        START,
        "## Training step (`scripts/bench/bench_training.py`)",
        "",
        f"Command: `python scripts/bench/bench_training.py --rounds {args.rounds} --size {args.size} "
        f"--batch {args.batch}`  ",
        f"Machine: {os.cpu_count()} CPUs ({platform.machine()}, "
        f"{torch.backends.cpu.get_cpu_capability()}, bf16 "
        f"{'native' if torch.cpu._is_avx512_bf16_supported() else 'emulated'}), "
        f"torch {torch.__version__}, 2 threads; "
        f"{time.strftime('%Y-%m-%d')}. Batch {args.batch} at {args.size}x{args.size}, two source frames, "
        f"ResNet-18, 4 scales; median over {args.rounds} interleaved rounds.",
        "",
        "| configuration | fisheye projection | real-scale poses | multi-channel | step time | peak RSS |",
        "|---|---|---|---|---|---|",
    ]
    for name, (fisheye, real, mc) in CONFIGS.items():
        flags = " | ".join("yes" if f else "no" for f in (fisheye, real, mc))
        lines.append(f"| {name} | {flags} | {med[name]:.2f} s | {peak[name]:.0f} MB |")
    before = next(iter(LEVERS))
    lines += [
        "",
        f"Speed levers of the full model's step, in the same rounds. The first {N_STACKED} rows add one "
        f"lever each to the row above; the last {len(LEVERS) - N_STACKED} each add one lever to the "
        "float32 step with box-sum SSIM (row 2). "
        "Speed-up = median over rounds of the paired ratio to the step before the levers:",
        "",
        "| step | time | speed-up |",
        "|---|---|---|",
    ]
    for name in LEVERS:
        lines.append(f"| {name} | {med[name]:.2f} s | {paired(before, name):.2f}x |")
    lines += [
        "",
        f"- Fisheye projection costs {100 * fisheye_cost:+.1f} % of a step (full model against itself with "
        f"pinhole projection, paired per round); target <= 5 %: "
        f"{'met' if fisheye_cost <= 0.05 else 'NOT met'}.",
        f"- Real-scale poses make the step {posenet_speedup:.2f}x faster than the same model with a PoseNet "
        f"(FFT + MC against full); target >= 1.6x: {'met' if posenet_speedup >= 1.6 else 'NOT met'}.",
        END,
    ]
    publish("\n".join(lines) + "\n", args.output, START, END, write=not args.no_write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
