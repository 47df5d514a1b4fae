#!/usr/bin/env python
"""Metric distance from geometry at robot speed: the rectified pipeline (fisheyedepth.stereo) beside
OpenCV's StereoSGBM alone, side by side in one run; results go into BENCHMARKS.md (between this script's
markers). One thread unless said; a pair's rectification tables are built once (per rig pair, per
calibration) and not timed, as a robot builds them once.

1. Rays: every pixel of a 1408x1408 Fisheye624 camera (Aria Digital Twin's RGB calibration) unprojected
   on one thread, the interpolated path beside the model's own iteration at every pixel.
2. Middlebury 2014 Motorcycle (real photographs, scikit-image): the rectified path (remap on the sphere,
   normalisation, SGBM, checks, fill, distance at every pixel) beside StereoSGBM alone on the raw pair
   (same settings and disparity range), taking turns; both scored against the exact disparity on the
   left image's overlap.
3. The ADT SLAM pair (640x480 Fisheye624, ``FISHEYEDEPTH_REALDATA``): both images answered (both
   directions, checks, fill, distance at every pixel), on 2 threads: pairs per second.
4. A 1408 px fisheye with two partners: ADT's RGB camera and its two SLAM cameras (their calibration and
   extrinsics) in the textured room of the tests; the RGB image's distance from both partners, fused.
5. A four-camera rig: the Aria Gen2 rig (512x512 Fisheye624, metric odometry), every camera with its rig
   partners and its own image from the last instant that moved 5 cm or more, through ``RigStereo`` on 2
   threads: instants per second.
6. A car's six 968x608 pinholes moving 1.3 m between instants (DDAD's half-size cameras) in the textured
   room, through ``RigStereo`` on 2 threads with every check: seconds an image, beside StereoSGBM alone.
7. The sweep (``--matcher sweep``: census 7x7, 128 hypotheses, round trip) on the Middlebury pair, once,
   on the CPU and, where there is one, on CUDA.

Usage: python scripts/bench/bench_stereo.py [--rounds 3] [--no-write] [--quick]
"""

from __future__ import annotations

import datetime
import math
import platform
import statistics
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import torch

from fisheyedepth.cameras.rays import compute_rays, pixel_grid
from fisheyedepth.realworld.frames import adt_camera
from fisheyedepth.realworld.pairs import MOTORCYCLE, adt_left_to_right, adt_pairs, motorcycle, overlap
from fisheyedepth.stereo import RigStereo, SgbmSettings, fuse, match_pair, rectify_pair
from fisheyedepth.stereo.match import normalise
from fisheyedepth.stereo.pipeline import grey
from fisheyedepth.stereo.scores import score

from _benchmarks import bench_parser, interleaved, markers, parse_args, publish

START, END = markers("bench_stereo")
ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))  # the tests' textured room

from stereo_world import render, texture_volume  # noqa: E402


def realdata() -> Path:
    import os

    return Path(os.environ.get("FISHEYEDEPTH_REALDATA", ROOT.parent / "shared" / "realdata"))


def threads(n: int) -> None:
    torch.set_num_threads(n)
    cv2.setNumThreads(n)


def rays_section(quick: bool) -> list[str]:
    """Seconds to unproject every pixel of a 1408 px Fisheye624 camera, both ways, one thread."""
    threads(1)
    path = realdata() / "adt_slam" / "adt_sample.json"
    camera = adt_camera(path, "camera-rgb") if path.is_file() else None
    if camera is None:
        return ["(rays: no ADT calibration under FISHEYEDEPTH_REALDATA)"]
    if quick:
        camera = camera.resize(352, 352)
    fast = statistics.median(
        interleaved({"": lambda: compute_rays(camera, dtype=torch.float64)}, 1, warmup=0)[""]
    )
    if quick:
        return [f"Rays of a {camera.width} px Fisheye624: {fast:.2f} s"]
    grid = pixel_grid(camera.width, camera.height, dtype=torch.float64)
    exact = statistics.median(interleaved({"": lambda: camera.unproject(grid)}, 1, warmup=0)[""])
    return [
        f"Every pixel of a {camera.width}x{camera.height} Fisheye624 camera (ADT's RGB calibration, "
        f"{camera.width * camera.height / 1e6:.1f} megapixels) unprojected on one thread, float32 rays as "
        f"the pipeline keeps them: **{fast:.2f} s** (the model's own iteration at every pixel: "
        f"{exact:.2f} s); once per calibration."
    ]


def middlebury_section(rounds: int, quick: bool) -> tuple[list[str], float]:
    threads(1)
    pair = motorcycle()
    settings = SgbmSettings(min_distance=1.5, max_distance=10.0)
    rect = rectify_pair(pair.camera, pair.partner_camera, pair.T.numpy(), settings, (True, False))
    a, b = grey(pair.image), grey(pair.partner_image)
    m = settings.sgbm
    seen = np.ones(a.shape, bool)
    raw = [normalise(x, seen, m.normalise_window) for x in (a, b)]
    # the raw pair's disparity range for the same nearest distance (d + doffs = f b / z)
    c = MOTORCYCLE
    raw_range = 16 * math.ceil((c["f"] * c["baseline"] / settings.min_distance - c["doffs"]) / 16)
    sgbm = m.create(raw_range)
    results = {}

    def ours():
        results["ours"] = match_pair(a, b, rect, settings, (True, False))[0]

    def theirs():
        results["theirs"] = sgbm.compute(*raw).astype(np.float32) / 16

    times = interleaved({"ours": ours, "theirs": theirs}, 1 if quick else rounds, warmup=0 if quick else 1)
    ours_s, theirs_s = statistics.median(times["ours"]), statistics.median(times["theirs"])
    scored = overlap(pair).numpy()
    truth = pair.distance.numpy()
    rays, _ = compute_rays(pair.camera)
    d = results["theirs"]
    z = np.where(d > 0, c["f"] * c["baseline"] / np.maximum(d + c["doffs"], 1e-6), 0)
    their_distance = z / rays[..., 2].numpy()
    rows = []
    for name, distance, seconds in (
        (f"rectified on the sphere, SGBM ({m.mode}, {m.block}x{m.block}), checks, fill",
         results["ours"].distance, ours_s),
        (f"OpenCV StereoSGBM alone on the raw pair (same settings, {raw_range} disparities)", their_distance,
         theirs_s),
    ):  # fmt: skip
        s = score(distance, truth, scored)
        rows.append(
            f"| {name} | {s['abs_rel']:.4f} | {s['a1']:.3f} | {100 * s['coverage']:.1f} % | {seconds:.3f} |"
        )
    lines = [
        f"Middlebury 2014 Motorcycle, 741x500, one thread (grid {rect.grid.rows}x{rect.grid.cols}, "
        f"{rect.disparities} disparities), scored on the left image's overlap: the rectified path takes "
        f"**{ours_s / theirs_s:.2f}x** StereoSGBM's time alone.",
        "",
        "| method | abs_rel | a1 | coverage | seconds |",
        "|---|---|---|---|---|",
        *rows,
    ]
    return lines, ours_s / theirs_s


def adt_section(rounds: int, quick: bool) -> list[str]:
    folder = realdata() / "adt_slam"
    if not folder.is_dir():
        return ["(ADT: no adt_slam under FISHEYEDEPTH_REALDATA)"]
    threads(2)
    pair = adt_pairs(folder, adt_left_to_right(folder))[0]
    settings = SgbmSettings(min_distance=0.2, max_distance=10.0)
    rect = rectify_pair(pair.camera, pair.partner_camera, pair.T.numpy(), settings)
    a, b = grey(pair.image), grey(pair.partner_image)
    seconds = statistics.median(
        interleaved({"": lambda: match_pair(a, b, rect, settings)}, 1 if quick else rounds, warmup=1)[""]
    )
    return [
        f"ADT's SLAM pair, 640x480 each, both images answered (grid {rect.grid.rows}x{rect.grid.cols}, "
        f"{rect.disparities} disparities), 2 threads: {seconds:.3f} s, **{1 / seconds:.1f} pairs per "
        "second**."
    ]


def rgb_section(rounds: int, quick: bool) -> list[str]:
    """ADT's 1408 px RGB camera and its two SLAM cameras in the textured room, their extrinsics."""
    path = realdata() / "adt_slam" / "adt_sample.json"
    if not path.is_file():
        return ["(RGB with partners: no ADT calibration under FISHEYEDEPTH_REALDATA)"]
    import json

    threads(1)
    data = json.loads(path.read_text())
    names = ("camera-rgb", "camera-slam-left", "camera-slam-right")
    cameras = {n: adt_camera(path, n) for n in names}
    if quick:
        cameras = {n: c.resize(c.width // 4, c.height // 4) for n, c in cameras.items()}
    to_device = {n: torch.tensor(data["cameras"][n]["T_device_camera"], dtype=torch.float64) for n in names}
    world = torch.eye(4, dtype=torch.float64)
    world[:3, 3] = torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64)
    images = {n: grey(render(cameras[n], world @ to_device[n], texture_volume(0))[0]) for n in names}
    settings = SgbmSettings(min_distance=0.3, max_distance=20.0)
    rgb_to = {n: (torch.linalg.inv(to_device[n]) @ to_device["camera-rgb"]).numpy() for n in names[1:]}
    rects = {
        n: rectify_pair(cameras["camera-rgb"], cameras[n], T, settings, (True, False))
        for n, T in rgb_to.items()
    }

    def rgb():
        return fuse(
            [
                match_pair(images["camera-rgb"], images[n], rects[n], settings, (True, False))[0]
                for n in names[1:]
            ]
        )

    seconds = statistics.median(interleaved({"": rgb}, 1 if quick else rounds, warmup=1)[""])
    rgb_camera = cameras["camera-rgb"]
    return [
        f"A {rgb_camera.width} px Fisheye624 (ADT's RGB calibration) with its two 640x480 SLAM cameras as "
        f"partners (grids at the SLAM cameras' {math.degrees(rects[names[1]].grid.step):.3f} degrees a "
        "pixel), "
        f"its distance from both, fused, one thread: **{seconds:.2f} s** a frame."
    ]


def rig_section(rounds: int, quick: bool) -> list[str]:
    src = realdata() / "aria_gen2_rig"
    if not src.is_dir():
        return ["(four-camera rig: no aria_gen2_rig under FISHEYEDEPTH_REALDATA)"]
    from fisheyedepth.data.aria import aria_to_rig
    from fisheyedepth.data.layouts import RigLayout

    threads(2)
    with tempfile.TemporaryDirectory() as tmp:
        aria_to_rig(src, Path(tmp) / "rig")
        layout = RigLayout(Path(tmp) / "rig")
        sequence = layout.sequences()[0]
        names = list(layout.cameras)
        frames = {n: layout.frames(sequence, n) for n in names}
        count = min(len(f) for f in frames.values())
        images = [{n: layout.read_image(sequence, n, frames[n][i]) for n in names} for i in range(count)]
        poses = [frames[names[0]][i].pose for i in range(count)]
    cameras = {n: layout.cameras[n].camera for n in names}
    if quick:
        cameras = {n: c.resize(c.width // 2, c.height // 2) for n, c in cameras.items()}
        images = [
            {n: cv2.resize(x, (cameras[n].width, cameras[n].height)) for n, x in i.items()} for i in images
        ]
    rig = RigStereo(cameras, {n: layout.cameras[n].cam_to_body for n in names}, SgbmSettings(), threads=2)
    instants, partners = [], []
    for i in range(count):
        earlier = [j for j in range(i) if np.linalg.norm(poses[i][:3, 3] - poses[j][:3, 3]) >= 0.05]
        if not earlier:
            continue
        j = earlier[-1]
        motion = np.linalg.inv(poses[j]) @ poses[i]
        out = None

        def instant(i=i, j=j, motion=motion):
            nonlocal out
            out = rig(images[i], previous=images[j], motion=motion)

        instants.append(
            statistics.median(interleaved({"": instant}, 1, warmup=1 if i == count - 1 else 0)[""])
        )
        partners.append(sum(len(r.partners) for r in out.values()))
    seconds = statistics.median(instants)
    camera = next(iter(cameras.values()))
    return [
        f"The Aria Gen2 rig: {len(names)} cameras of {camera.width}x{camera.height}, {len(rig.pairs)} "
        "overlapping "
        f"rig pairs, every camera also against its own image of the last instant 5 cm or more away "
        f"({statistics.median(partners):.0f} partner maps an instant), 2 threads, over {len(instants)} "
        "instants: "
        f"{seconds:.2f} s, **{1 / seconds:.1f} instants per second**."
    ]


def car_section(rounds: int, quick: bool) -> list[str]:
    """A car's six 968x608 pinholes (DDAD's half-size cameras: a front one of 1060 px focal length and five
    of 530, 60 degrees apart, 0.6 m from the body's centre) in the textured room, moving 1.3 m between
    instants, through ``RigStereo`` on 2 threads with every check (the motion refined from SIFT, the round
    trip, the row check, the static pixels), beside StereoSGBM alone on one pair of the same size."""
    from fisheyedepth.cameras import PinholeCamera
    from fisheyedepth.geometry.se3 import axis_angle_to_matrix, make_pose

    threads(2)
    w, h = (484, 304) if quick else (968, 608)
    front = PinholeCamera(
        width=w, height=h, fx=1060.0 * w / 968, fy=1060.0 * w / 968, cx=(w - 1) / 2, cy=(h - 1) / 2
    )
    side = PinholeCamera(
        width=w, height=h, fx=530.0 * w / 968, fy=530.0 * w / 968, cx=(w - 1) / 2, cy=(h - 1) / 2
    )
    yaws = {
        "front": 0,
        "front_left": -60,
        "front_right": 60,
        "back_left": -120,
        "back_right": 120,
        "back": 180,
    }
    cameras = {n: front if n == "front" else side for n in yaws}
    cam_to_body = {}
    for name, yaw in yaws.items():
        R = axis_angle_to_matrix(torch.tensor([0.0, math.radians(yaw), 0.0], dtype=torch.float64))
        cam_to_body[name] = make_pose(R, R @ torch.tensor([0.0, 0.0, 0.6], dtype=torch.float64))
    body = [make_pose(torch.eye(3, dtype=torch.float64), torch.tensor([0.0, 0.5, -1.3 + 1.3 * i],
            dtype=torch.float64)) for i in range(2 + rounds)]  # fmt: skip
    volume = texture_volume(0)
    images = [{n: (render(cameras[n], P @ E, volume)[0][0, 0].numpy() * 255).astype(np.uint8)
               for n, E in cam_to_body.items()} for P in body]  # fmt: skip
    rig = RigStereo(cameras, {n: E.numpy() for n, E in cam_to_body.items()}, SgbmSettings(), threads=2)
    rig(images[0])
    rig(images[1], previous=images[0], motion=(torch.linalg.inv(body[0]) @ body[1]).numpy())  # warm
    seconds = []
    for i in range(2, len(body)):
        motion = (torch.linalg.inv(body[i - 1]) @ body[i]).numpy()

        def instant(i=i, motion=motion):
            rig(images[i], previous=images[i - 1], motion=motion)

        seconds.append(statistics.median(interleaved({"": instant}, 1, warmup=0)[""]))
    rig_s = statistics.median(seconds)
    threads(1)
    a, b = (normalise(images[0]["front_left"].astype(np.float32), np.ones((h, w), bool), 15) for _ in (0, 1))
    sgbm = SgbmSettings().sgbm.create(256)
    alone = statistics.median(interleaved({"": lambda: sgbm.compute(a, b)}, max(1, rounds), warmup=1)[""])
    return [
        f"A car's six {w}x{h} pinholes moving 1.3 m between instants (DDAD's half-size cameras in the "
        f"tests' room): {len(rig.pairs)} rig pairs and 6 motion pairs an instant, every check on, 2 threads: "
        f"{rig_s:.2f} s an instant, **{rig_s / 6:.2f} s an image** (StereoSGBM alone on one {w}x{h} pair "
        f"with 256 disparities, one direction, one thread: {alone:.2f} s)."
    ]


def sweep_section(quick: bool) -> list[str]:
    from fisheyedepth.stereo import SweepMatcher, SweepSettings, View

    threads(1)
    pair = motorcycle()
    hypotheses = 16 if quick else 128
    settings = SweepSettings(hypotheses=hypotheses, min_distance=1.5, max_distance=10.0, cost="census")
    sweep = SweepMatcher(settings)
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    cells = []
    for device in devices:
        reference = View(pair.image.to(device), pair.camera, torch.eye(4, device=device))
        source = View(pair.partner_image.to(device), pair.partner_camera, pair.T.float().to(device))
        sync = torch.cuda.synchronize if device == "cuda" else None
        run = {"": lambda reference=reference, source=source: sweep(reference, [source])}
        seconds = statistics.median(interleaved(run, 1, warmup=0 if device == "cpu" else 1, sync=sync)[""])
        cells.append(f"{seconds:.2f} s on {'the CPU, one thread' if device == 'cpu' else 'CUDA'}")
    where = "; ".join(cells)
    return [
        f"The sweep (census 7x7, {hypotheses} hypotheses, round trip) on the Middlebury pair below: {where}."
    ]


def main(argv=None) -> None:
    parser = bench_parser(__doc__)
    parser.add_argument("--rounds", type=int, default=3)
    args = parse_args(parser, argv, quick={"rounds": 1})
    today = datetime.date.today().isoformat()
    middlebury, _ = middlebury_section(args.rounds, args.quick)
    lines = [
        START,
        f"### The rectified pipeline beside StereoSGBM ({today}, {platform.machine()})",
        f"`python scripts/bench/bench_stereo.py --rounds {args.rounds}`: one thread unless said; each pair's "
        "rectification tables built once beforehand, as a robot builds them once per rig pair and "
        "calibration; seconds the median of the rounds, ratios from turns taken in one run.",
        "",
        *(
            f"- {line}"
            for section in (
                rays_section(args.quick),
                adt_section(args.rounds, args.quick),
                rgb_section(args.rounds, args.quick),
                rig_section(args.rounds, args.quick),
                car_section(args.rounds, args.quick),
                sweep_section(args.quick),
            )
            for line in section
        ),
        "",
        *middlebury,
        END,
    ]
    publish("\n".join(lines) + "\n", args.output, START, END, not args.no_write)


if __name__ == "__main__":
    main()
