#!/usr/bin/env python
"""Building a KITTI-360 dataset must cost O(frames) with a small constant: an index, no per-frame work.
Measures, in a fresh process per size, the time and peak resident memory of ``FisheyeDataModule.setup``
(train, val and test) of the data module that ``data=kitti360`` configures (``conf/data/kitti360.yaml``:
``ground_truth: lidar``; this benchmark's root, splits, size and cache), and the time of the first
training sample and the first scored (test) sample; then extrapolates to 80,000 frames (BENCHMARKS.md
"Dataset at scale").

Usage: python scripts/bench/bench_dataset.py [--frames 200 2000] [--baseline OLD_CHECKOUT]
           [--no-write] [--quick]

The datasets use the KITTI-360 layout with the sizes that matter, the counts: pose rows, images and
Velodyne scans, 80 % in a training drive, 10 % in a validation drive (every 10th row of the left camera)
and 10 % in a test drive (every 5th row of the left camera). Images and scans are hard links to the
synthetic default world's (rendered on first use by ``make train``), so they cost no disk. With
``--baseline``, the same measurement runs on another checkout's ``src`` (e.g. a ``git worktree`` of an
older commit), side by side; the configuration is this checkout's, less the options the other code does
not have.
"""

from __future__ import annotations

import inspect
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from omegaconf import OmegaConf

from _benchmarks import (
    WORLD,
    bench_parser,
    child_result,
    markers,
    parse_args,
    peak_rss_kb,
    publish,
    run_child,
)
from _compose import compose_config

START, END = markers("bench_dataset")
DRIVES = {"train": (2, 0.8, 1), "val": (10, 0.1, 10), "test": (0, 0.1, 5)}  # drive, share, row stride
TARGET = 80_000


def drive(number: int) -> str:
    return f"2013_05_28_drive_{number:04d}_sync"


def make_dataset(root: Path, frames: int) -> None:
    """A KITTI-360-layout dataset of ``frames`` pose rows, images and scans hard-linked from the world."""
    images = {
        c: sorted((WORLD / "data_2d_raw").glob(f"*/{c}/data_rgb/*.png")) for c in ("image_02", "image_03")
    }
    scans = sorted((WORLD / "data_3d_raw").glob("*/velodyne_points/data/*.bin"))
    if not scans or not all(images.values()):
        raise FileNotFoundError(
            f"{WORLD}: no rendered world; run `make train` (or fisheyedepth-synthetic) first"
        )
    shutil.copytree(WORLD / "calibration", root / "calibration")
    n = 0
    for number, share, _ in DRIVES.values():
        rows, seq = int(frames * share), drive(number)
        poses = root / "data_poses" / seq / "poses.txt"
        poses.parent.mkdir(parents=True)
        lines = []
        for row in range(rows):
            key = 3 * row  # KITTI-360's frame indices are sparse
            lines.append(f"{key} 1 0 0 {0.5 * row:.3f} 0 1 0 0 0 0 1 0")
            for camera, files in images.items():
                dst = root / "data_2d_raw" / seq / camera / "data_rgb" / f"{key:010d}.png"
                dst.parent.mkdir(parents=True, exist_ok=True)
                os.link(files[n % len(files)], dst)
            velo = root / "data_3d_raw" / seq / "velodyne_points" / "data" / f"{key:010d}.bin"
            velo.parent.mkdir(parents=True, exist_ok=True)
            os.link(scans[n % len(scans)], velo)
            n += 1
        poses.write_text("\n".join(lines) + "\n")


def splits() -> dict:
    return {
        split: [
            {
                "sequence": drive(number),
                "stride": stride,
                **({} if split == "train" else {"cameras": ["image_02"]}),
            }
        ]
        for split, (number, _, stride) in DRIVES.items()
    }


def datamodule_config(root: Path, cache: Path) -> dict:
    """``data=kitti360``'s data module on this benchmark's dataset, as plain values (``_target_`` and
    the constructor's arguments), with the sources the model warps."""
    from fisheyedepth.config import source_offsets

    cfg = compose_config(
        ["data=kitti360"],
        {
            "data.datamodule.root": root,
            "data.datamodule.splits": splits(),
            "data.datamodule.size": [64, 64],
            "data.datamodule.cache_dir": cache,
        },
    )
    node = OmegaConf.to_container(cfg.data.datamodule, resolve=True)
    return node | {"offsets": source_offsets(cfg)}


def peak_rss_mb() -> float:
    return peak_rss_kb() / 1024


def child(config: Path, cache: Path) -> dict:
    """One measurement, in this (fresh) process, of the data module ``config`` (a JSON file) describes;
    options the code in use does not take (an older checkout's) are left out, and named."""
    from hydra.utils import get_class, instantiate

    node = json.loads(config.read_text())
    taken = inspect.signature(get_class(node["_target_"]).__init__).parameters
    dropped = sorted(k for k in node if not k.startswith("_") and k not in taken)
    if dropped:
        print(f"left out (not taken by this code): {', '.join(dropped)}", file=sys.stderr)
    before = peak_rss_mb()
    start = time.perf_counter()
    dm = instantiate({k: v for k, v in node.items() if k not in dropped})
    dm.setup("fit")
    dm.setup("test")
    setup = time.perf_counter() - start
    setup_rss = peak_rss_mb() - before
    start = time.perf_counter()
    dm.dataset("train")[0]
    first_train = time.perf_counter() - start
    start = time.perf_counter()
    scored = dm.scoring_loader("test").dataset if hasattr(dm, "scoring_loader") else dm.dataset("test")
    scored[0]  # what evaluation reads first (an older checkout has no scoring loader)
    first_test = time.perf_counter() - start
    return {
        "samples": {s: len(dm.dataset(s)) for s in ("train", "val", "test")},
        "setup_s": setup,
        "setup_rss_mb": setup_rss,
        "first_train_s": first_train,
        "first_test_s": first_test,
        "peak_rss_mb": peak_rss_mb() - before,
        "cache_files": sum(1 for _ in cache.rglob("*.npz")),
    }


def measure(root: Path, src: Path | None) -> dict:
    env = {"OMP_NUM_THREADS": "1"}
    if src is not None:
        env["PYTHONPATH"] = str(src)
    with tempfile.TemporaryDirectory(prefix="fd-bench-cache-") as cache:
        config = Path(cache) / "datamodule.json"  # beside the cache, which counts .npz files only
        config.write_text(json.dumps(datamodule_config(root, Path(cache))))
        return run_child(__file__, [config, cache], env=env)


def extrapolate(a: tuple[int, float], b: tuple[int, float], n: int) -> float:
    (n1, y1), (n2, y2) = a, b
    return y1 + (y2 - y1) / (n2 - n1) * (n - n1)


def report(results: dict[str, dict[int, dict]], frames: list[int], command: str) -> str:
    rows = []
    for name, by_size in results.items():
        for n in frames:
            r = by_size[n]
            rows.append(
                f"| {name} | {n:,} | {r['setup_s']:.2f} | {1e3 * r['setup_s'] / n:.2f} "
                f"| {r['setup_rss_mb']:.0f} | {r['first_train_s']:.2f} | {r['first_test_s']:.2f} "
                f"| {r['peak_rss_mb']:.0f} | {r['cache_files']} |"
            )
        lo, hi = frames[0], frames[-1]
        guess = {
            key: extrapolate((lo, by_size[lo][key]), (hi, by_size[hi][key]), TARGET)
            for key in ("setup_s", "setup_rss_mb", "first_train_s", "first_test_s", "peak_rss_mb")
        }
        rows.append(
            f"| {name} | **{TARGET:,}** (linear from {lo:,} and {hi:,}) | {guess['setup_s']:.1f} | | "
            f"{guess['setup_rss_mb']:.0f} | {guess['first_train_s']:.1f} | {guess['first_test_s']:.1f} "
            f"| {guess['peak_rss_mb']:.0f} | |"
        )
    return "\n".join(
        [
            START,
            "## Dataset at scale",
            "",
            f"`{command}`",
            "",
            "KITTI-360-layout datasets of N pose rows (two fisheye cameras: 2N images, N Velodyne scans; "
            "80 % in a training drive, 10 % each in a validation and a test drive, every 10th and 5th row "
            "of the left camera), `ground_truth: lidar` as `conf/data/kitti360.yaml`. One fresh process "
            "per row, one thread. "
            "Setup = `FisheyeDataModule.setup('fit')` and `setup('test')`; memory above the process's "
            "peak after imports. First train / test sample: reading `dataset(split)[0]` (a scored frame "
            "projects its one scan on first use). Cache files: LiDAR projections on disk afterwards.",
            "",
            "| code | frames N | setup s | ms per frame | setup MB | first train sample s | "
            "first test sample s | peak MB | cache files |",
            "|---|---|---|---|---|---|---|---|---|",
            *rows,
            END,
            "",
        ]
    )


def main(argv=None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--frames", type=int, nargs="+", default=[200, 2000])
    parser.add_argument("--baseline", type=Path, help="another checkout, measured side by side (its src/)")
    args = parse_args(parser, argv, quick={"frames": [20, 40]})
    if args.child:
        child_result(child(*map(Path, args.child)))
        return 0
    codes = {"this commit": None}
    if args.baseline:
        codes[f"baseline ({args.baseline.name})"] = args.baseline / "src"
    results: dict[str, dict[int, dict]] = {name: {} for name in codes}
    with tempfile.TemporaryDirectory(prefix="fd-bench-kitti360-") as tmp:
        for n in args.frames:
            root = Path(tmp) / f"kitti360_{n}"
            make_dataset(root, n)
            for name, src in codes.items():
                results[name][n] = measure(root, src)
                print(name, n, results[name][n], file=sys.stderr)
    command = "python scripts/bench/bench_dataset.py --frames " + " ".join(map(str, args.frames))
    if args.baseline:
        command += " --baseline <a worktree of the commit before>"
    publish(report(results, args.frames, command), args.output, START, END, not args.no_write)
    return 0


if __name__ == "__main__":
    sys.exit(main())
