#!/usr/bin/env python
"""Inference speed at a fixed input size for PyTorch eager, TorchScript and ONNX Runtime, side by side.

Frames per second of the full FisheyeDepth network (ResNet-18, multi-channel head), batch 1, measured in
interleaved rounds on the same inputs; results into BENCHMARKS.md. Goal: >= 10 fps at 384x384 on 2 CPU
threads (the paper reports "over 10 FPS" with ONNX on a Jetson AGX Orin GPU).

Usage: python scripts/bench_inference.py [--size 384] [--threads 2] [--rounds 20] [--no-write]
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

from fisheyedepth.inference import ExportableNet
from fisheyedepth.module import FisheyeDepthModule

from _benchmarks import publish

ROOT = Path(__file__).resolve().parents[1]
START, END = "<!-- bench_inference:start -->", "<!-- bench_inference:end -->"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--size", type=int, default=384)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    net = ExportableNet(FisheyeDepthModule().depth_net).eval()
    x = torch.rand(1, 3, args.size, args.size)
    runners = {}
    with torch.no_grad():
        runners["PyTorch eager"] = lambda: net(x)
        scripted = torch.jit.optimize_for_inference(torch.jit.trace(net, x).eval())
        runners["TorchScript (traced, optimised for inference)"] = lambda: scripted(x)
    try:
        import onnxruntime as ort

        tmp = Path(tempfile.mkdtemp()) / "m.onnx"
        torch.onnx.export(
            net,
            (x,),
            str(tmp),
            input_names=["image"],
            output_names=["distance"],
            opset_version=17,
            dynamo=False,
        )
        opts = ort.SessionOptions()
        opts.intra_op_num_threads, opts.inter_op_num_threads = args.threads, 1
        session = ort.InferenceSession(str(tmp), opts, providers=["CPUExecutionProvider"])
        feed = {"image": x.numpy()}
        runners["ONNX Runtime (CPU)"] = lambda: session.run(None, feed)
    except ImportError:
        pass
    times = {name: [] for name in runners}
    with torch.no_grad():
        for run in runners.values():  # warm-up
            for _ in range(3):
                run()
        names = list(runners)
        for r in range(args.rounds):
            for name in names[r % len(names) :] + names[: r % len(names)]:
                t0 = time.perf_counter()
                runners[name]()
                times[name].append(time.perf_counter() - t0)
    lines = [
        START,
        "## Inference (`scripts/bench_inference.py`)",
        "",
        f"Command: `python scripts/bench_inference.py --size {args.size} --threads {args.threads} "
        f"--rounds {args.rounds}`  ",
        f"Machine: {os.cpu_count()} CPUs ({platform.machine()}), torch {torch.__version__}, "
        f"{args.threads} threads; {time.strftime('%Y-%m-%d')}. Full model (ResNet-18, 64-bin head), batch 1, "
        f"{args.size}x{args.size}, "
        "median over interleaved rounds.",
        "",
        "| runtime | ms / frame | fps | goal >= 10 fps |",
        "|---|---|---|---|",
    ]
    for name, ts in times.items():
        med = statistics.median(ts)
        lines.append(
            f"| {name} | {med * 1e3:.1f} | {1 / med:.1f} | {'met' if 1 / med >= 10 else 'NOT met'} |"
        )
    lines.append(END)
    publish("\n".join(lines) + "\n", ROOT / "BENCHMARKS.md", START, END, write=not args.no_write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
