#!/usr/bin/env python
"""Streaming over a long video: ``predict.py`` end to end (decode, network, every output written) for a
short and a long clip of the same frames, in each runtime; its fps and its peak resident memory, which
must not grow with the video's length (BENCHMARKS.md "Streaming").

Usage: python scripts/bench/bench_streaming.py --ckpt CKPT [--frames 50 1000] [--size 384] [--threads 2]
           [--calibration DIR] [--no-write] [--quick]

The clip repeats rendered frames of the synthetic default world (rendered on first use by ``make train``)
resized to ``--size``; each runtime's network runs at ``--size`` too (``export.py size=``).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2

from _benchmarks import ROOT, WORLD, bench_parser, markers, parse_args, peak_rss_of, publish

START, END = markers("bench_streaming")


def write_clip(path: Path, frames: int, size: int) -> None:
    sources = sorted((WORLD / "data_2d_raw").glob("*/image_02/data_rgb/*.png"))[:40]
    if not sources:
        raise FileNotFoundError(
            f"{WORLD}: no rendered frames; run `make train` (or fisheyedepth-synthetic) first"
        )
    images = [cv2.resize(cv2.imread(str(p)), (size, size), interpolation=cv2.INTER_LINEAR) for p in sources]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (size, size))
    for i in range(frames):
        writer.write(images[i % len(images)])
    writer.release()


def peak_run(args: list[str], threads: int) -> tuple[float, dict]:
    """Peak RSS (MB) of ``python predict.py ARGS`` and its summary.json."""
    command = [sys.executable, ROOT / "predict.py", *args]
    peak = peak_rss_of(command, env={"OMP_NUM_THREADS": str(threads)}, cwd=ROOT)
    out = next(a.split("=", 1)[1] for a in args if a.startswith("output="))
    return peak / 1024.0, json.loads((Path(out) / "summary.json").read_text())


def main(argv=None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--ckpt", required=True)
    parser.add_argument("--frames", nargs=2, type=int, default=[50, 1000])
    parser.add_argument("--size", type=int, default=384)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--calibration", type=Path, default=WORLD / "data_2d_raw")
    args = parse_args(parser, argv, quick={"frames": [2, 4], "size": 64})
    calib = WORLD / "calibration" / "image_02.yaml"
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        size = f"[{args.size},{args.size}]"
        for quantize in (None, "int8"):
            extra = [f"quantize={quantize}", f"calibration={args.calibration}"] if quantize else []
            name = f"{quantize or 'fp32'}.onnx"
            subprocess.run(
                [sys.executable, str(ROOT / "export.py"), f"ckpt_path={args.ckpt}", f"size={size}",
                 f"output={tmp / name}", f"hydra.run.dir={tmp / ('export_' + name)}", *extra],
                check=True, capture_output=True, cwd=ROOT,
            )  # fmt: skip
        runtimes = {
            "PyTorch float32": [f"ckpt_path={args.ckpt}", f"size={size}"],
            "PyTorch bf16": [f"ckpt_path={args.ckpt}", f"size={size}", "precision=bf16"],
            "ONNX Runtime float32": ["runtime=onnx", f"model={tmp / 'fp32.onnx'}", f"threads={args.threads}"],
            "ONNX Runtime int8": ["runtime=onnx", f"model={tmp / 'int8.onnx'}", f"threads={args.threads}"],
        }
        clips = {}
        for n in args.frames:
            clips[n] = tmp / f"clip{n}.avi"
            write_clip(clips[n], n, args.size)
        for label, options in runtimes.items():
            peaks, fps = {}, {}
            for n, clip in clips.items():
                out = tmp / f"out_{label.replace(' ', '_')}_{n}"
                run_args = [*options, f"input={clip}", f"camera={calib}", f"output={out}", "batch_size=1",
                            f"hydra.run.dir={out}_hydra"]  # fmt: skip
                peaks[n], summary = peak_run(run_args, args.threads)
                fps[n] = summary["fps"]
                for f in out.iterdir():  # outputs of 1,000 frames: several GB on a small disk
                    f.unlink()
            short, long = args.frames
            rows.append(
                f"| {label} | {fps[long]:.1f} | {peaks[short]:.0f} | {peaks[long]:.0f} | "
                f"{peaks[long] - peaks[short]:+.0f} |"
            )
            print(rows[-1], flush=True)
    short, long = args.frames
    lines = [
        START,
        "## Streaming (`scripts/bench/bench_streaming.py`)",
        "",
        f"Command: `python scripts/bench/bench_streaming.py --ckpt CKPT --frames {short} {long} "
        f"--size {args.size} --threads {args.threads}`  ",
        f"{time.strftime('%Y-%m-%d')}; `predict.py` end to end on an MJPG clip at {args.size}x{args.size} "
        "(decode, network at the same size, and every output of every frame written: distance .npy and "
        "uint16 .png, colour .png), batch 1 as for a live camera. Peak RSS of the whole process.",
        "",
        f"| runtime | fps ({long} frames, with writing) | peak RSS, {short} frames (MB) | "
        f"peak RSS, {long} frames (MB) | growth (MB) |",
        "|---|---|---|---|---|",
        *rows,
        END,
    ]
    publish("\n".join(lines) + "\n", args.output, START, END, write=not args.no_write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
