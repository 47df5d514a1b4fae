#!/usr/bin/env python
"""Peak memory of one stereo pair through the rectified pipeline (``RigStereo``, as
``fisheyedepth-multiview`` matches each pair), per pixel of its images, at growing sizes: the figure
behind the bound the command refuses a recording by (``stereo.sgbm.pair_memory``) before any
work (BENCHMARKS.md, "Memory of a stereo pair", after the stereo section).

Usage: python scripts/bench/bench_stereo_memory.py [--sizes 512 1024 2048] [--quick] [--no-write]

Each size runs twice in a fresh process, with and without the match: the difference of the two peaks
(``VmHWM``: the process's own, not its parent's) is the pair's. Two KITTI-360 fisheyes (Mei, 190
degrees) 0.3 m apart, random images (every window textured: the most the matcher keeps).
"""

from __future__ import annotations

import platform
import sys
import time

from _benchmarks import ROOT, bench_parser, child_result, markers, parse_args, publish, run_child

START, END = markers("bench_stereo_memory")


def child(size: int, match: bool) -> None:
    import numpy as np

    sys.path.insert(0, str(ROOT / "tests"))
    from fisheyedepth.stereo import RigStereo

    from conftest import kitti02

    camera = kitti02().resize(size, size)
    moved = np.eye(4)
    moved[0, 3] = 0.3
    noise = np.random.default_rng(0).integers(0, 255, (2, size, size), dtype=np.uint8)
    if match:
        rig = RigStereo({"a": camera, "b": camera}, {"a": np.eye(4), "b": moved}, threads=1)
        rig({"a": noise[0], "b": noise[1]})
    peak = next(int(x.split()[1]) * 1024 for x in open("/proc/self/status") if x.startswith("VmHWM:"))
    child_result(peak)


def main(argv=None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[512, 1024, 2048])
    args = parse_args(parser, argv, quick={"sizes": [256]})
    if args.child:
        child(int(args.child[0]), args.child[1] == "match")
        return 0
    from fisheyedepth.stereo.sgbm import MEMORY_BASE, MEMORY_PER_PIXEL, pair_memory

    measured = []
    for size in args.sizes:
        start = time.perf_counter()
        grown = run_child(__file__, [size, "match"]) - run_child(__file__, [size, "setup"])
        measured.append((size, grown))
        print(f"{size} px: {grown / 2**20:.0f} MiB ({time.perf_counter() - start:.0f} s)", flush=True)

    mib = " / ".join(f"{grown / 2**20:.0f}" for _, grown in measured)
    sizes = " / ".join(str(size) for size, _ in measured)
    per_pixel = " / ".join(f"{grown / size**2:.0f}" for size, grown in measured)
    share = " / ".join(f"{grown / pair_memory(size**2):.2f}" for size, grown in measured)
    command = f"python scripts/bench/bench_stereo_memory.py --sizes {' '.join(map(str, args.sizes))}"
    bound = f"{MEMORY_BASE // 2**20} MiB + {MEMORY_PER_PIXEL} bytes a pixel"
    section = "\n".join([
        START,
        f"**Memory of a stereo pair** (`{command}`, {time.strftime('%Y-%m-%d')}, {platform.machine()}; two "
        "KITTI-360 fisheyes 0.3 m apart, random images, a fresh process with and without the match): "
        f"**{mib} MiB** at {sizes} px, {per_pixel} bytes a pixel, {share} of the bound "
        f"`fisheyedepth-multiview` refuses by ({bound}).",
        END,
    ])  # fmt: skip
    publish(section, args.output, START, END, not args.no_write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
