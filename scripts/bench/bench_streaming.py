#!/usr/bin/env python
"""Streaming over a long video: ``predict.py`` end to end (decode, network, every output written) for a
short and a long clip of the same frames, in each runtime; its fps and its peak resident memory, which
must not grow with the video's length (BENCHMARKS.md "Streaming"). Beside it, the live rig: the Aria Gen2
rig (``realdata/aria_gen2_rig``) replayed through :class:`fisheyedepth.stereo.RigStereo` as
``scripts/tools/live_rig.py`` runs it, instants per second without and with its Rerun recording.

Usage: python scripts/bench/bench_streaming.py [--ckpt CKPT] [--frames 50 1000] [--size 384] [--threads 2]
           [--calibration DIR] [--no-write] [--quick]
Without ``--ckpt`` only the live rig is measured; predict's rows are kept as published.

The clip repeats rendered frames of the synthetic default world (rendered on first use by ``make train``)
resized to ``--size``; each runtime's network runs at ``--size`` too (``export.py size=``).
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))  # live_rig

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


def predict_section(args) -> list[str]:
    """predict.py streaming a short and a long clip in each runtime: the section's lines."""
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
    return [
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
    ]


def published_predict(path: Path) -> list[str]:
    """The predict part of the section as published in ``path`` (everything before the live rig's)."""
    text = path.read_text() if path.exists() else ""
    if START not in text:
        return ["## Streaming (`scripts/bench/bench_streaming.py`)", "", "(predict.py: run with --ckpt)"]
    section = text.split(START, 1)[1].split(END, 1)[0].strip("\n")
    return section.split(RIG_HEADING, 1)[0].rstrip("\n").splitlines()


RIG_HEADING = "**The live rig**"


def rig_section(threads: int, quick: bool) -> list[str]:
    """The Aria Gen2 rig replayed live, without and with the Rerun recording: the section's lines."""
    src = Path(os.environ.get("FISHEYEDEPTH_REALDATA", ROOT.parent / "shared" / "realdata")) / "aria_gen2_rig"
    if not src.is_dir():
        return [RIG_HEADING, "", f"(no {src}: set FISHEYEDEPTH_REALDATA)"]
    from fisheyedepth.rerun3d import RigRecorder
    from fisheyedepth.stereo import RigStereo, SgbmSettings
    from live_rig import body_masks, instants, replay, rig_layout

    measured = {}
    with rig_layout(src) as layout, tempfile.TemporaryDirectory() as tmp:
        found, _ = instants(layout, layout.sequences()[0])
        found = found[:3] if quick else found
        names = list(found[0].images)
        cameras = {n: layout.cameras[n].camera for n in names}
        extrinsics = {n: layout.cameras[n].cam_to_body for n in names}
        for recorded in (False, True):
            stereo = RigStereo(cameras, extrinsics, SgbmSettings(), threads, body_masks(layout, names))
            path = Path(tmp) / "recording.rrd"
            start = time.perf_counter()
            if recorded:
                with RigRecorder(path, "bench") as recorder:
                    recorder.rig(extrinsics)
                    seconds = [s for *_, s in replay(layout, stereo, found, recorder, quiet=True)]
            else:
                seconds = [s for *_, s in replay(layout, stereo, found, quiet=True)]
            total = time.perf_counter() - start  # the recording's closing included
            size = path.stat().st_size / 1e6 if recorded else 0.0
            measured[recorded] = (len(seconds) / total, statistics.median(seconds), size)
            print(f"recorded={recorded}: {measured[recorded]}", flush=True)
    camera = next(iter(cameras.values()))
    (fps, median, _), (fps_recorded, median_recorded, size) = measured[False], measured[True]
    when = f"{time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} cores"
    rig = f"{len(names)} cameras of {camera.width}x{camera.height}, {len(found)} instants"
    return [
        f"{RIG_HEADING} (`python scripts/bench/bench_streaming.py --threads {threads}`, without `--ckpt`; "
        f"{when}): `scripts/tools/live_rig.py`'s loop on the Aria Gen2 rig, {rig}, each camera against the "
        "rig's overlapping cameras and its own image of the latest instant 5 cm or more away, "
        f"{threads} threads: **{fps:.2f} instants per second** (median {median:.2f} s); with the Rerun "
        "recording (every image as JPEG, the kept and the filled maps colourised and in metres, up to "
        f"100,000 world points per map) **{fps_recorded:.2f}** (median {median_recorded:.2f} s), "
        f"{size:.0f} MB.",
    ]


def main(argv=None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--ckpt", default=None, help="predict's rows; without it they are kept as published")
    parser.add_argument("--frames", nargs=2, type=int, default=[50, 1000])
    parser.add_argument("--size", type=int, default=384)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--calibration", type=Path, default=WORLD / "data_2d_raw")
    args = parse_args(parser, argv, quick={"frames": [2, 4], "size": 64})
    predict_lines = predict_section(args) if args.ckpt else published_predict(args.output)
    lines = [START, *predict_lines, "", *rig_section(args.threads, args.quick), END]
    publish("\n".join(lines) + "\n", args.output, START, END, write=not args.no_write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
