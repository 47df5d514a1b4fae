#!/usr/bin/env python
"""Geometry benchmarks; results go into BENCHMARKS.md (between this script's markers).

1. Ray-cache build (unprojection of every pixel) for the KITTI-360 image_02 Mei camera in float64,
   at 1400x1400 and at the 384x384 training resolution. Targets: <= 1 s and <= 50 ms on 2 CPU cores.
2. Warp + grid_sample, forward and backward, batch 8 at 256x256, for fisheye models against a pinhole
   camera, interleaved round by round in one run so that machine noise hits all alike. Target: the
   fisheye/pinhole ratio <= 1.05 (fisheye projection costs nothing once rays are cached).

Usage: python scripts/bench/bench_geometry.py [--threads 2] [--rounds 15] [--device cpu]
           [--no-write] [--quick]
"""

from __future__ import annotations

import os
import statistics
import time
from functools import partial

import torch

from fisheyedepth.cameras import (
    DoubleSphereCamera,
    KannalaBrandtCamera,
    MeiCamera,
    RayCache,
    compute_rays,
    pinhole_like,
)
from fisheyedepth.data.kitti360 import kitti360_camera
from fisheyedepth.geometry import axis_angle_to_matrix, make_pose, sample, warp_to_source

from _benchmarks import bench_parser, cpu_name, interleaved, markers, parse_args, publish, repeated

START, END = markers("bench_geometry")

KITTI_02 = kitti360_camera(2)


def synchronizer(device: torch.device):
    """What waits for ``device`` to finish its work (nothing on the CPU)."""
    return (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else None


def bench_ray_cache(device, repeats: int) -> list[tuple[str, float, float]]:
    rows = []
    for size, target in ((1400, 1.0), (384, 0.050)):
        cam = KITTI_02.resize(size, size)
        build = partial(compute_rays, cam, device, torch.float64)
        times = repeated(build, repeats, warmup=1, sync=synchronizer(device))
        rows.append((f"{size}x{size}", statistics.median(times), target))
    return rows


def bench_warp(device, rounds: int, batch: int = 8, size: int = 256) -> dict[str, list[float]]:
    kitti = KITTI_02.resize(size, size)
    fx, fy = kitti.paraxial_focal()
    cams = {
        "pinhole": None,  # filled below: the pinhole with the fisheye's focal and centre
        "mei (KITTI-360, radial)": kitti,
        "mei (radial + tangential)": None,  # filled below
        "kannala_brandt": KannalaBrandtCamera(
            width=size,
            height=size,
            fx=fx,
            fy=fy,
            cx=kitti.u0,
            cy=kitti.v0,
            k1=0.0035,
            k2=0.0007,
            k3=-0.002,
            k4=0.0002,
        ),
        "double_sphere": DoubleSphereCamera(
            width=size,
            height=size,
            fx=fx * 0.83,
            fy=fy * 0.83,
            cx=kitti.u0,
            cy=kitti.v0,
            xi=-0.17,
            alpha=0.59,
        ),
    }
    params = {k: v for k, v in kitti.to_dict().items() if k != "model"}
    cams["mei (radial + tangential)"] = MeiCamera(**{**params, "p1": 4.2e-4, "p2": 4.2e-4})
    cams["pinhole"] = pinhole_like(kitti)

    g = torch.Generator().manual_seed(0)
    image = torch.rand(batch, 3, size, size, generator=g).to(device)
    dist0 = (torch.rand(batch, 1, size, size, generator=g) * 20 + 2).to(device)
    T = make_pose(axis_angle_to_matrix(torch.tensor([0.0, 0.03, 0.0])), torch.tensor([0.05, 0.0, 0.6]))
    T = T.expand(batch, 4, 4).contiguous().to(device)
    cache = RayCache()
    prepared = {}
    for name, cam in cams.items():
        rays, valid = cache.get(cam, device, torch.float32)
        prepared[name] = (cam, rays.expand(batch, -1, -1, -1), valid.expand(batch, -1, -1))

    def step(name):
        cam, rays, valid = prepared[name]
        dist = dist0.clone().requires_grad_(True)
        warp = warp_to_source(rays, valid, dist, T, cam)
        loss = (sample(image, warp.grid) * warp.valid[:, None]).mean()
        loss.backward()

    runs = {name: (lambda name=name: step(name)) for name in cams}
    return interleaved(runs, rounds, warmup=2, sync=synchronizer(device))


def render(cache_rows, warp_times, args, device) -> str:
    lines = [
        START,
        "## Geometry (`scripts/bench/bench_geometry.py`)",
        "",
        f"Command: `python scripts/bench/bench_geometry.py --threads {args.threads} --rounds {args.rounds}"
        f" --device {args.device}`  ",
        f"Machine: {os.cpu_count()} CPUs ({cpu_name()}), torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads, device {device}; {time.strftime('%Y-%m-%d')}.",
        "",
        "Ray-cache build, KITTI-360 image_02 (Mei), float64, median of repeats:",
        "",
        "| resolution | time | target | met |",
        "|---|---|---|---|",
    ]
    for res, t, target in cache_rows:
        lines.append(
            f"| {res} | {t * 1e3:.1f} ms | <= {target * 1e3:.0f} ms | {'yes' if t <= target else 'NO'} |"
        )
    base = warp_times["pinhole"]
    lines += [
        "",
        f"Warp + grid_sample, forward and backward, batch 8 at 256x256, float32; {args.rounds} interleaved",
        "rounds. Ratio: median over rounds of (model time / pinhole time in that round); target <= 1.05:",
        "",
        "| camera | median time | ratio to pinhole | met |",
        "|---|---|---|---|",
    ]
    for name, ts in warp_times.items():
        ratio = statistics.median(t / b for t, b in zip(ts, base, strict=True))
        met = "-" if name == "pinhole" else ("yes" if ratio <= 1.05 else "NO")
        lines.append(f"| {name} | {statistics.median(ts) * 1e3:.1f} ms | {ratio:.3f} | {met} |")
    lines.append(END)
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--device", default="cpu")
    args = parse_args(parser, argv, quick={"rounds": 1, "repeats": 1})
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    cache_rows = bench_ray_cache(device, args.repeats)
    warp_times = bench_warp(device, args.rounds)
    section = render(cache_rows, warp_times, args, device)
    publish(section, args.output, START, END, write=not args.no_write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
