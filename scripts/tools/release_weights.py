#!/usr/bin/env python
"""Write a trained run's checkpoint as the released weights: its weights in float16 and its
hyper-parameters (no optimiser or loop state), atomically, beside an updated ``SHA256SUMS``.

    python scripts/tools/release_weights.py RUN/checkpoints/last.ckpt [--out weights] [--name FILE.ckpt]
                                            [--overwrite]

``predict.py``, ``eval.py`` and ``export.py`` load ``weights/fisheyedepth_mobile_mixed.ckpt`` when no
``ckpt_path`` is given, after checking it against ``weights/SHA256SUMS``. An existing file is kept
unless ``--overwrite``. Exit status 2 on a checkpoint that cannot be read.
"""

from __future__ import annotations

import argparse
import io
import sys
from pathlib import Path

import torch

from fisheyedepth.checkpoints import (
    CHECKSUMS,
    RELEASED,
    WEIGHTS_DIR,
    CheckpointError,
    read_checkpoint,
    read_checksums,
    release_checkpoint,
    sha256,
)
from fisheyedepth.cli import CommandParser
from fisheyedepth.files import atomic_write_bytes, atomic_write_text
from fisheyedepth.module import FisheyeDepthModule
from fisheyedepth.signals import ends_on_signals


def release(ckpt: Path, out: Path, name: str = RELEASED, overwrite: bool = False) -> tuple[Path, str]:
    """The released file and its sha256."""
    target = out / name
    if target.exists() and not overwrite:
        raise FileExistsError(f"{target} exists; pass --overwrite to replace it")
    sums_path = out / CHECKSUMS
    sums = read_checksums(sums_path) if sums_path.is_file() else {}  # refused before anything is written
    slim = release_checkpoint(read_checkpoint(ckpt))
    buffer = io.BytesIO()
    torch.save(slim, buffer)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(target, buffer.getvalue())
    FisheyeDepthModule.from_checkpoint(target)  # it loads as the commands will load it
    sums[name] = digest = sha256(target)
    atomic_write_text(sums_path, "".join(f"{d}  {file}\n" for file, d in sorted(sums.items())))
    return target, digest


@ends_on_signals  # SIGINT / SIGTERM: one line, exit 130 / 143
def main(argv=None) -> int:
    parser = CommandParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ckpt", type=Path, help="a training checkpoint (RUN/checkpoints/last.ckpt)")
    parser.add_argument("--out", type=Path, default=WEIGHTS_DIR, help="folder (%(default)s)")
    parser.add_argument("--name", default=RELEASED, help="file name (%(default)s)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing file")
    args = parser.parse_args(argv)
    try:
        target, digest = release(args.ckpt, args.out, args.name, args.overwrite)
    except (CheckpointError, FileExistsError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{target}: {target.stat().st_size / 2**20:.1f} MiB, sha256 {digest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
