"""``fisheyedepth-synthetic`` (``python -m fisheyedepth.cli.synthetic``): render a synthetic fisheye
dataset."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..options.kinds import check_options
from ..signals import Terminated, stopped_by
from ..synthetic.folder import is_empty_dir, made_by_generator
from ..synthetic.rig import RIGS
from ..synthetic.sensor import EFFECTS
from ..synthetic.spec import GENERATE_OPTIONS, SPEC_FIELDS, WorldSpec
from ..synthetic.traffic import MAX_TRAFFIC
from ..synthetic.world import SCENES
from ..synthetic.writer import generate
from . import CommandParser


def flag(option: str) -> str:
    """The command line's spelling of a generation parameter: ``random_cameras`` -> ``--random-cameras``."""
    return "--" + option.replace("_", "-")


def check_flags(args: argparse.Namespace) -> None:
    """The flags that are generation parameters, by the kinds and ranges of ``data.generate``
    (:data:`~.spec.GENERATE_OPTIONS`), named as typed: ``--traffic: 1000.0 is not a number in [0, 8]``."""
    given = {flag(k): v for k, v in vars(args).items()}
    check_options(given, {flag(k): kind for k, kind in GENERATE_OPTIONS.items()})


def _announce_replacement(out: Path) -> None:
    """``--overwrite`` is explicit, but say what it is about to replace."""
    if not out.exists() or is_empty_dir(out):
        return
    if not out.is_dir():
        what = "a file, NOT a dataset made by fisheyedepth"
    elif made_by_generator(out):
        what = "a synthetic dataset made by fisheyedepth"
    else:
        what = f"NOT a dataset made by fisheyedepth: its {sum(1 for _ in out.iterdir())} entries are deleted"
    print(f"--overwrite: {out} ({what}) is replaced once rendering finishes", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    p = CommandParser(description="Render a synthetic multi-camera fisheye dataset in the KITTI-360 layout.")
    p.add_argument("--out", required=True, help="output folder (must be absent or empty unless --overwrite)")
    p.add_argument("--rig", default="kitti360", choices=RIGS)
    p.add_argument("--frames", type=int, default=200, help="frames per camera over train/val/test together")
    p.add_argument("--size", type=int, default=256, help="image width and height in pixels (multiple of 8)")
    p.add_argument("--seed", type=int, default=0, help="world layout, textures and trajectory")
    p.add_argument("--supersample", type=int, default=2, help="antialiasing: NxN rays per pixel")
    p.add_argument("--workers", type=int, default=0, help="worker processes (0: render in this process)")
    p.add_argument("--no-lidar", action="store_true", help="skip the Velodyne scans")
    p.add_argument("--lane", default="right", choices=("right", "left"), help="the lane the car keeps to")
    p.add_argument("--scene", default="street", choices=SCENES, help="a city street, or a furnished room")
    p.add_argument(
        "--random-cameras",
        action="store_true",
        help="draw every camera (model family, intrinsics, mounting height and tilt) from --seed",
    )
    p.add_argument(
        "--traffic",
        type=float,
        default=0.0,
        help=f"density of moving cars and pedestrians (0: none; 1: busy; at most {MAX_TRAFFIC:g})",
    )
    p.add_argument(
        "--effects",
        nargs="*",
        default=[],
        choices=EFFECTS,
        metavar="EFFECT",
        help=f"camera effects, any of: {', '.join(EFFECTS)}",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset at --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    a = p.parse_args(argv)
    try:
        check_flags(a)
        spec = WorldSpec(**{name: getattr(a, name) for name in SPEC_FIELDS})
        if a.overwrite:
            _announce_replacement(Path(a.out))
        rendering = {"workers": a.workers, "lidar": not a.no_lidar, "progress": not a.quiet}
        out = generate(a.out, spec, overwrite=a.overwrite, **rendering)
    except (OSError, ValueError) as exc:  # a full disk: folder.NoSpaceLeft, naming the folder
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except (Terminated, KeyboardInterrupt) as stop:
        why, status = stopped_by(stop)
        print(f"error: {why}; the workers were stopped and the partial dataset removed", file=sys.stderr)
        return status
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
