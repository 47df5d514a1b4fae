"""``fisheyedepth-estimate-mask --root ROOT --sequence SEQ --camera CAM``: a camera's vehicle-body mask
from a recording (:mod:`fisheyedepth.data.body_mask`)."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from ..data import body_mask
from ..files import path_name
from ..signals import ends_on_signals
from . import CommandParser


@ends_on_signals  # SIGINT / SIGTERM: one line, exit 130 / 143
def main(argv: Sequence[str] | None = None) -> int:
    """Console script ``fisheyedepth-estimate-mask``."""
    parser = CommandParser(
        description="Estimate a camera's vehicle-body mask from a recording: still pixels with a ray "
        "below the horizon are body. Writes a PNG (255 = usable, 0 = body) where the layout reads it.",
        epilog="example: fisheyedepth-estimate-mask --root data/kitti360 "
        "--sequence 2013_05_28_drive_0000_sync --camera image_02",
    )
    parser.add_argument("--root", type=Path, required=True, help="the dataset's root folder")
    parser.add_argument("--layout", choices=("kitti360", "rig"), default="kitti360")
    parser.add_argument("--sequence", required=True)
    parser.add_argument("--camera", required=True, help="e.g. image_02")
    parser.add_argument(
        "--frames", type=int, default=200, help="frames spread evenly over the sequence (default 200)"
    )
    parser.add_argument("--out", type=Path, help="default: where the layout reads the camera's mask")
    parser.add_argument(
        "--threshold", type=float, help="temporal std (exposure-normalised) below which a pixel is body; "
        "default: automatic (minimum-error threshold of the log std)",
    )  # fmt: skip
    parser.add_argument(
        "--sky-elevation", type=float, default=5.0, metavar="DEG",
        help="still pixels whose ray points more than DEG above the horizon are sky, not body (default 5)",
    )  # fmt: skip
    parser.add_argument(
        "--up", type=float, nargs=3, metavar=("X", "Y", "Z"),
        help="the body frame's up direction (default: -z for kitti360, the world's z for a rig)",
    )  # fmt: skip
    parser.add_argument("--overwrite", action="store_true", help="replace an existing mask file")
    args = parser.parse_args(argv)
    try:
        path_name(args.camera, "camera", "--camera")  # folders and the default mask's file name
        path_name(args.sequence, "sequence", "--sequence")
        layout = body_mask.open_layout(args.layout, args.root, args.camera)
        summary = body_mask.write_body_mask(
            layout, args.sequence, args.camera, args.frames, args.out, args.threshold,
            args.sky_elevation, args.up, args.overwrite,
        )  # fmt: skip
    except (FileNotFoundError, FileExistsError, KeyError, ValueError) as err:  # ImageError is a ValueError
        print(f"error: {err.args[0] if isinstance(err, KeyError) else err}", file=sys.stderr)
        return 2
    print(
        f"{args.camera}: {100 * summary['body_fraction']:.1f} % of the pixels with a ray are body "
        f"(std threshold {summary['threshold']:.4g}, {summary['frames']} frames, up {summary['up']})"
    )
    print(f"wrote {summary['mask']}")
    if args.layout == "rig" and layout.mask_paths[args.camera] is None and args.out is None:
        print(f"add 'mask: masks/{args.camera}.png' to camera {args.camera} in {args.root / 'rig.yaml'}")
    return 0
