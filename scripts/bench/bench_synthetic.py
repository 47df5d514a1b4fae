#!/usr/bin/env python
"""Synthetic-world rendering speed; results go into BENCHMARKS.md (between this script's markers).

Camera-frames per second at 256x256 with 2x2 supersampling on 2 CPU cores (target >= 5, stretch 20):
1. rendering alone, in this process with 2 threads (colour, exact distance, body mask; no files);
2. the whole generator (`generate`: rendering, LiDAR, PNG/NPY/BIN files), in one process with 2 threads
   and with 2 worker processes of 1 thread each;
3. the same with traffic (density 1), and with traffic and every camera effect (motion blur renders
   each frame's colour 5 times), beside the still street in the same run, with each dataset's size;
4. where rendering's time goes: milliseconds per camera-frame casting the supersampled rays, shading
   them (of which the procedural textures' value noise), and casting the pixel centres for the exact
   distance, in the rendering-only run's process.

Usage: python scripts/bench/bench_synthetic.py [--frames 24] [--size 256] [--no-write] [--quick]
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import torch

from fisheyedepth.synthetic import WorldSpec, generate, make_rig, make_trajectory, make_world, shading
from fisheyedepth.synthetic.raycast import scene_tensors
from fisheyedepth.synthetic.render import CameraRenderer

from _benchmarks import bench_parser, cpu_name, markers, parse_args, publish, timed

START, END = markers("bench_synthetic")


def street(frames: int, size: int, supersample: int):
    """World 0, its scene tensors, ``frames + 2`` poses and the kitti360 rig's camera renderers."""
    world, rig = make_world(0), make_rig("kitti360", size)
    renderers = [CameraRenderer(cam, rig.cam_to_pose[name], supersample) for name, cam in rig.cameras.items()]
    return world, scene_tensors(world), make_trajectory(world, frames + 2, 0), renderers


def render_only(frames: int, size: int, supersample: int) -> float:
    world, scene, poses, renderers = street(frames, size, supersample)
    for r in renderers:  # warm-up
        r.render(scene, world, poses[0])
    seconds = timed(lambda: [r.render(scene, world, pose) for pose in poses[2:] for r in renderers])
    return frames * len(renderers) / seconds


def stages(frames: int, size: int, supersample: int) -> dict[str, float]:
    """Milliseconds per camera-frame of each stage of :meth:`CameraRenderer.render`."""
    world, scene, poses, renderers = street(frames, size, supersample)
    totals = dict.fromkeys(("fine cast", "shading", "of which value noise", "centre cast"), 0.0)
    noise_seconds = [0.0]

    def counted(fn):
        def wrapper(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                noise_seconds[0] += time.perf_counter() - t0

        return wrapper

    originals = (shading.fbm2, shading.fbm3, shading.hash01)
    shading.fbm2, shading.fbm3, shading.hash01 = (counted(f) for f in originals)
    try:
        for pose in poses[2:]:
            for r in renderers:
                t0 = time.perf_counter()
                origin, dirs, hit = r.fine.cast(scene, pose)
                t1 = time.perf_counter()
                noise_seconds[0] = 0.0
                shading.shade(world, hit, origin, dirs, r.pixel_angle)
                t2 = time.perf_counter()
                r.truth(scene, pose)
                t3 = time.perf_counter()
                totals["fine cast"] += t1 - t0
                totals["shading"] += t2 - t1
                totals["of which value noise"] += noise_seconds[0]
                totals["centre cast"] += t3 - t2
    finally:
        shading.fbm2, shading.fbm3, shading.hash01 = originals
    n = frames * len(renderers)
    return {name: seconds / n * 1e3 for name, seconds in totals.items()}


def end_to_end(frames: int, size: int, supersample: int, workers: int, **world) -> tuple[float, float]:
    """Camera-frames per second of ``generate``, and the dataset's megabytes per 100 camera-frames."""
    with tempfile.TemporaryDirectory() as tmp:
        spec = WorldSpec("kitti360", frames=frames, size=size, supersample=supersample, **world)
        seconds = timed(lambda: generate(Path(tmp) / "d", spec, workers=workers, progress=False))
        size_bytes = sum(f.stat().st_size for f in (Path(tmp) / "d").rglob("*") if f.is_file())
        return frames * 2 / seconds, size_bytes / 2**20 / (frames * 2) * 100


def main(argv=None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--supersample", type=int, default=2)
    args = parse_args(parser, argv, quick={"frames": 9, "size": 64, "supersample": 1})
    torch.set_num_threads(2)
    shape = (args.frames, args.size, args.supersample)
    everything = ["exposure", "white_balance", "vignetting", "noise", "motion_blur"]
    rows = [
        ("rendering only, 1 process x 2 threads", (render_only(*shape), None)),
        ("generate(), 1 process x 2 threads", end_to_end(*shape, 0)),
        ("generate(), 2 worker processes x 1 thread", end_to_end(*shape, 2)),
        ("generate(), 2 workers, traffic 1", end_to_end(*shape, 2, traffic=1.0)),
        (
            "generate(), 2 workers, traffic 1 and every effect",
            end_to_end(*shape, 2, traffic=1.0, effects=everything),
        ),
    ]
    lines = [
        START,
        "## Synthetic world (`scripts/bench/bench_synthetic.py`)",
        "",
        f"Command: `python scripts/bench/bench_synthetic.py --frames {args.frames} --size {args.size}"
        f" --supersample {args.supersample}`  ",
        f"Machine: {os.cpu_count()} CPUs ({cpu_name()}), torch {torch.__version__}; "
        f"{time.strftime('%Y-%m-%d')}. kitti360 rig (2 Mei cameras), {args.size}x{args.size}, "
        f"{args.supersample}x{args.supersample} supersampling; end-to-end runs include LiDAR and files.",
        "",
        "| mode | camera-frames / s | target >= 5 | stretch >= 20 | MB per 100 camera-frames |",
        "|---|---|---|---|---|",
    ]
    for name, (fps, mb) in rows:
        size = "-" if mb is None else f"{mb:.1f}"
        met = f"{'yes' if fps >= 5 else 'NO'} | {'yes' if fps >= 20 else 'no'}"
        lines.append(f"| {name} | {fps:.2f} | {met} | {size} |")
    fps = [row[1][0] for row in rows]
    split = stages(*shape)
    lines += [
        "",
        f"Two worker processes render {fps[2] / fps[1]:.2f}x as fast as one process of two threads. Traffic"
        f" costs {100 * (1 - fps[3] / fps[2]):.0f} %; every effect {fps[3] / fps[4]:.1f}x (motion blur"
        f" renders colour 5 times) and {100 * (rows[4][1][1] / rows[3][1][1] - 1):.0f} % more disk"
        " (noise compresses worse). Where a camera-frame's time goes (1 process x 2 threads): "
        + ", ".join(f"{name} {ms:.0f} ms" for name, ms in split.items())
        + ".",
    ]
    lines.append(END)
    section = "\n".join(lines) + "\n"
    publish(section, args.output, START, END, write=not args.no_write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
