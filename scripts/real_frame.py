#!/usr/bin/env python
"""Score checkpoints on the real KITTI-360 frame of ``FISHEYEDEPTH_REALDATA`` (``kitti360_frame/``:
the left fisheye image, its official calibration and body mask, and the Velodyne scan projected into
it as Euclidean distances): a real camera and real LiDAR, never trained on (BENCHMARKS.md, "Time to
accuracy"). One frame is an indicator, not a benchmark: the networks here train on rendered worlds.

    python scripts/real_frame.py CKPT [CKPT ...] [--frame DIR] [--pictures DIR] [--post-process flip]

Prints one Markdown row per checkpoint: the full protocol (every LiDAR point up to 80 m that the
camera can see, the occlusion filter on) as abs_rel, a1 unscaled, then median-scaled abs_rel and the
median ratio (ground truth / prediction), then the kitti360 protocol (under 8 m) unscaled. The network
runs at its checkpoint's input size on the image and camera resized alike, and its distance is
upsampled to the frame's 1400x1400, where the points are scored (as ``eval.py`` does).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import torch

from fisheyedepth.cameras import CameraModel, load_camera
from fisheyedepth.evaluation import PROTOCOLS, Evaluator
from fisheyedepth.images import read_image
from fisheyedepth.module import FisheyeDepthModule
from fisheyedepth.runtimes import POST_PROCESSING, TorchRuntime
from fisheyedepth.utils import atomic_write_bytes
from fisheyedepth.viz import panel

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_FRAME = (
    Path(os.environ.get("FISHEYEDEPTH_REALDATA", ROOT.parent / "shared" / "realdata")) / "kitti360_frame"
)


class RealFrame(NamedTuple):
    image: torch.Tensor  # [1, 3, H, W] RGB in [0, 1]
    camera: CameraModel
    mask: torch.Tensor  # [H, W] bool: usable pixels (not the ego body)
    lidar: torch.Tensor  # [H, W] metres along the ray, 0 without a return


def read_uint16(path: Path) -> np.ndarray:
    """A one-channel 16-bit PNG; a clear error naming the file otherwise."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found")
    data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None or data.dtype != np.uint16 or data.ndim != 2:
        kind = "unreadable" if data is None else f"{data.dtype} with shape {data.shape}"
        raise ValueError(f"{path}: expected a one-channel uint16 PNG (metres * 256), got {kind}")
    return data


def load_frame(folder: Path, camera: str = "image_02") -> RealFrame:
    """``folder``/``camera``_rgb.png, ``camera``.yaml, ``camera``_body_mask.png and
    ``camera``_lidar_distance.png (uint16, metres * 256, 0 = no return), checked against each other."""
    cam = load_camera(folder / f"{camera}.yaml")
    size = (cam.width, cam.height)
    paths = {k: folder / f"{camera}_{k}.png" for k in ("rgb", "body_mask", "lidar_distance")}
    bgr = read_image(paths["rgb"]).bgr
    mask = cv2.cvtColor(read_image(paths["body_mask"]).bgr, cv2.COLOR_BGR2GRAY) > 127
    lidar = read_uint16(paths["lidar_distance"]).astype(np.float32) / 256.0
    for key, array in (("rgb", bgr), ("body_mask", mask), ("lidar_distance", lidar)):
        if array.shape[1::-1] != size:
            raise ValueError(
                f"{paths[key]}: {array.shape[1]}x{array.shape[0]}, but {camera}.yaml says {size[0]}x{size[1]}"
            )
    image = torch.from_numpy(np.ascontiguousarray(bgr[..., ::-1])).permute(2, 0, 1).float()[None] / 255.0
    return RealFrame(image, cam, torch.from_numpy(mask), torch.from_numpy(lidar))


def score(runtime, frame: RealFrame, protocols=("full", "kitti360")) -> tuple[dict, torch.Tensor]:
    """``runtime`` (anything with ``distance(images, cameras)``) on the frame, scored against its LiDAR
    points under each protocol, unscaled and median-scaled; and the predicted distance ``[H, W]``."""
    pred = runtime.distance(frame.image, [frame.camera]).float()[0, 0]
    results = {}
    for name in protocols:
        evaluator = Evaluator(PROTOCOLS[name], ("none", "median"))
        evaluator.update(pred, frame.lidar.to(pred), frame.mask.to(pred.device), frame.camera, source="lidar")
        results[name] = evaluator.compute()
    return results, pred


def picture(frame: RealFrame, pred: torch.Tensor, width: int = 350) -> np.ndarray:
    """Input | prediction | LiDAR (each point grown to a small block) | error, ``width`` px a tile, BGR."""
    H, W = pred.shape
    size = (width, round(H * width / W))
    image = cv2.resize(frame.image[0].permute(1, 2, 0).numpy(), size, interpolation=cv2.INTER_AREA)
    small = cv2.resize(pred.cpu().numpy(), size, interpolation=cv2.INTER_AREA)
    # the nearest return in each block, so the sparse scan stays visible at this size
    lidar = torch.where(frame.mask & (frame.lidar > 0), frame.lidar, torch.full_like(frame.lidar, np.inf))
    k = max(1, W // width)
    near = -torch.nn.functional.max_pool2d(-lidar[None, None], k, k)[0, 0]
    near = cv2.resize(near.numpy(), size, interpolation=cv2.INTER_NEAREST)
    near[~np.isfinite(near)] = 0
    tiles = panel(
        torch.from_numpy(image).permute(2, 0, 1), torch.from_numpy(small)[None], torch.from_numpy(near)[None]
    )
    return np.ascontiguousarray(tiles[..., ::-1])


def row(name: str, results: dict) -> str:
    full, k360 = results["full"], results["kitti360"]
    return (
        f"| {name} | {full['none']['abs_rel']:.3f}, {full['none']['a1']:.3f} "
        f"| {full['median']['abs_rel']:.3f} (x{full['median']['scale_ratio']:.2f}) "
        f"| {k360['none']['abs_rel']:.3f}, {k360['none']['a1']:.3f} |"
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("checkpoints", nargs="+", type=Path)
    parser.add_argument("--frame", type=Path, default=DEFAULT_FRAME, help="default: %(default)s")
    parser.add_argument("--camera", default="image_02")
    parser.add_argument("--pictures", type=Path, help="write <checkpoint's run>_real_frame.png here")
    parser.add_argument("--post-process", default="none", choices=POST_PROCESSING)
    args = parser.parse_args(argv)
    frame = load_frame(args.frame, args.camera)
    points = int(((frame.lidar > 0) & frame.mask).sum())
    print(f"{args.frame / args.camera}: {points} LiDAR points inside the body mask")
    print("| checkpoint | full: abs_rel, a1 | full, median-scaled: abs_rel (ratio) | kitti360: abs_rel, a1 |")
    print("|---|---|---|---|")
    for ckpt in args.checkpoints:
        runtime = TorchRuntime(FisheyeDepthModule.from_checkpoint(ckpt), post_process=args.post_process)
        results, pred = score(runtime, frame)
        name = ckpt.parent.parent.name if ckpt.parent.name == "checkpoints" else ckpt.stem
        print(row(name, results), flush=True)
        if args.pictures is not None:
            args.pictures.mkdir(parents=True, exist_ok=True)
            out = args.pictures / f"{name}_real_frame.png"
            if out.exists():
                raise FileExistsError(f"{out} exists; choose another --pictures folder")
            ok, encoded = cv2.imencode(".png", picture(frame, pred))
            if not ok:
                raise OSError(f"{out}: could not encode the picture")
            atomic_write_bytes(out, encoded.tobytes())


if __name__ == "__main__":
    main()
