#!/usr/bin/env python
"""A top-down picture of a rig's fused points in the world frame: every instant of a rig recording through
the live multi-view API (:class:`fisheyedepth.stereo.RigStereo`, as ``scripts/tools/live_rig.py`` runs it),
each camera's kept distance turned into world points (ray x distance, camera -> body -> world), seen from
above (the world's z axis up, as Aria's odometry frame has it), coloured by height; the body's path in
white and each camera's position at the last instant as a coloured dot.

    python scripts/tools/rig_topdown.py ../shared/realdata/aria_gen2_rig \\
        --out docs/figures/aria_rig_topdown.png [--size 720] [--span 6] [--overwrite]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

from fisheyedepth.cameras import RayCache
from fisheyedepth.cli import CommandParser
from fisheyedepth.files import atomic_write_png
from fisheyedepth.inference import point_cloud
from fisheyedepth.signals import ends_on_signals
from fisheyedepth.stereo import RigStereo, SgbmSettings

sys.path.insert(0, str(Path(__file__).resolve().parent))
from live_rig import body_masks, instants, replay, rig_layout  # noqa: E402

CAMERA_COLOURS = [(0, 160, 255), (60, 220, 60), (255, 120, 60), (220, 60, 220)]  # BGR


RAYS = RayCache()  # each camera's rays, unprojected once for every instant


def world_points(result, camera, cam_to_world: np.ndarray) -> np.ndarray:
    """The kept distance's points (:func:`~fisheyedepth.inference.point_cloud`) in the world frame."""
    local, _ = point_cloud(torch.from_numpy(result.fused.distance), camera, rays=RAYS)
    return local.astype(np.float64) @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]


def draw(
    points: np.ndarray, path: np.ndarray, cameras: list[np.ndarray], size: int, span: float
) -> np.ndarray:
    """``size`` px square, ``span`` metres across, centred on the path's middle."""
    centre = path[:, :2].mean(axis=0)
    scale = size / span

    def pixel(xy: np.ndarray) -> np.ndarray:
        return np.stack(
            ((xy[:, 0] - centre[0]) * scale + size / 2, size / 2 - (xy[:, 1] - centre[1]) * scale), 1
        )

    canvas = np.full((size, size, 3), 24, np.uint8)
    uv = pixel(points[:, :2]).round().astype(int)
    inside = (uv >= 0).all(1) & (uv < size).all(1)
    height = points[inside, 2]
    lo, hi = np.percentile(height, [2, 98]) if len(height) else (0.0, 1.0)
    level = ((np.clip(height, lo, hi) - lo) / max(hi - lo, 1e-6) * 255).astype(np.uint8)
    colours = cv2.applyColorMap(level[:, None], cv2.COLORMAP_VIRIDIS)[:, 0]
    canvas[uv[inside, 1], uv[inside, 0]] = colours
    track = pixel(path[:, :2]).round().astype(np.int32)
    cv2.polylines(canvas, [track], False, (255, 255, 255), 2, cv2.LINE_AA)
    for colour, position in zip(CAMERA_COLOURS, cameras, strict=False):
        cv2.circle(canvas, tuple(int(v) for v in pixel(position[None, :2])[0]), 5, colour, -1, cv2.LINE_AA)
    bar = int(scale)  # one metre
    cv2.line(canvas, (16, size - 20), (16 + bar, size - 20), (255, 255, 255), 2)
    cv2.putText(
        canvas, "1 m", (16, size - 28), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA
    )
    return canvas


@ends_on_signals  # SIGINT / SIGTERM: one line, exit 130 / 143
def main(argv=None) -> int:
    parser = CommandParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("rig", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--size", type=int, default=480)
    parser.add_argument("--points", type=int, default=150_000, help="drawn at most (uniform, seed 0)")
    parser.add_argument("--span", type=float, default=6.0, help="metres across the picture")
    parser.add_argument("--max-distance", type=float, default=8.0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    if args.out.exists() and not args.overwrite:
        print(f"error: {args.out} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    with rig_layout(args.rig) as layout:
        found, _ = instants(layout, layout.sequences()[0])
        names = list(found[0].images)
        cameras = {n: layout.cameras[n].camera for n in names}
        extrinsics = {n: layout.cameras[n].cam_to_body for n in names}
        settings = SgbmSettings(max_distance=args.max_distance)
        stereo = RigStereo(cameras, extrinsics, settings, args.threads, body_masks(layout, names))
        points, path = [], []
        for instant, results, _ in replay(layout, stereo, found, quiet=True):
            body = instant.body_to_world
            path.append(body[:3, 3])
            for name, result in results.items():
                points.append(world_points(result, cameras[name], body @ extrinsics[name]))
    last = [(body @ extrinsics[n])[:3, 3] for n in names]
    every = np.concatenate(points)
    drawn = every[np.random.default_rng(0).permutation(len(every))[: args.points]]
    picture = draw(drawn, np.array(path), last, args.size, args.span)
    atomic_write_png(args.out, picture, compression=9)
    kb = args.out.stat().st_size // 1024
    print(f"{len(drawn)} of {len(every)} points of {len(path)} instants: {args.out} ({kb} KB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
