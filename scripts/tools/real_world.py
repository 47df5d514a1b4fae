#!/usr/bin/env python
"""Score checkpoints (.ckpt) or exported files (.onnx) on every real fisheye frame with metric ground
truth under the real data folder (``--root``, else ``FISHEYEDEPTH_REALDATA``; ``make realscore``
defaults to ``../shared/realdata``): the KITTI-360 frame against its LiDAR (80 m, inside the body
mask), the ScanNet++ frame and four Aria Digital Twin SLAM frames against their rendered depth (capped
at the frame's range), and each camera of the DDAD scene's first sample against its LiDAR sweep (80 m,
every pixel: DDAD ships no body mask). Real cameras, never trained on.

    python scripts/tools/real_world.py MODEL [MODEL ...] [--root DIR] [--frames kitti360 scannetpp adt ddad]
                                 [--pictures DIR] [--json OUT] [--force] [--post-process flip]
                                 [--no-multiview] [--matcher sgbm|sweep]
    python scripts/tools/real_world.py --from-records docs/records/real_photographs   # kept scores
    python scripts/tools/real_world.py --from-records --multiview RECORD               # stereo's, kept

Prints one Markdown row per model and frame: abs_rel, a1 and rmse unscaled, then median-scaled (and
the ratio ground truth / prediction), beside a constant map at the ground truth's median distance,
the score any real-world result must beat; then the published zero-shot anchors on KITTI-360. The
network runs at its input size on the image and camera resized alike, its distance upsampled to the
frame's size. ``--pictures``: input | prediction | ground truth | error per model and frame;
``--json``: every number (the kitti360 protocol under 8 m for the KITTI-360 frame too). Exit status
1 when a frame's files are missing (each is named in the table), 2 on a malformed file or option, or
without a real data folder.
Then stereo (fisheyedepth.stereo, untrained; ``--matcher``: sgbm, the default, or sweep) on every real
frame with a partner: the ADT SLAM pairs, frames 0 and 1, each camera as the reference, the pair's
rotation refined from its images first; and Middlebury 2014 Motorcycle (scikit-image). Each is scored on
the reference's overlap with its partner, checked and dense, beside the constant map and each model on the
same pixels (``--no-multiview``: not).
``--from-records``: the MODEL arguments are run records (files or folders, ``docs/records``) whose
``real_world`` scores are printed as kept, nothing re-scored.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor

from fisheyedepth.cameras import load_json
from fisheyedepth.cli import CommandParser
from fisheyedepth.files import atomic_write_bytes, atomic_write_text
from fisheyedepth.options.tables import POST_PROCESSING
from fisheyedepth.realworld.frames import FRAME_SETS, RAYS, Missing, RealFrame, load_frames
from fisheyedepth.realworld.scores import constant_map, protocols, score, scored_pixels
from fisheyedepth.realworld.stereo import multiview_records_table, multiview_scores
from fisheyedepth.runtimes import OnnxRuntime, TorchRuntime, TrainedDepthNet
from fisheyedepth.signals import ends_on_signals
from fisheyedepth.stereo.matchers import MATCHERS
from fisheyedepth.viz import panel

ROOT_VARIABLE = "FISHEYEDEPTH_REALDATA"  # the real data folder, when --root is not given
# metres: the near end of the pictures' colour scale (its far end is the frame's range), by the ground
# truth: a LiDAR scan outdoors, a dense map indoors
NEAR = {"lidar": 0.5, None: 0.2}
# Published zero-shot metric distance on KITTI-360's fisheye frames, 80 m cap (abs_rel, a1; None where
# the paper gives none): what a real-world score is read against.
ANCHORS = (
    ("Depth Any Camera", 0.149, 0.822),
    ("UniDAC", 0.141, 0.836),
    ("Metric3D v2", 0.200, None),
    ("UniK3D", 0.244, None),
)


def data_root(root: Path | None) -> Path:
    """``--root``, else ``$FISHEYEDEPTH_REALDATA``; a ValueError naming both when neither is given."""
    if root is not None:
        return Path(root)
    if os.environ.get(ROOT_VARIABLE):
        return Path(os.environ[ROOT_VARIABLE])
    raise ValueError(f"--root: no real data folder given; pass --root DIR or set {ROOT_VARIABLE}")


# ------------------------------------------------------------------ the pictures
def picture(frame: RealFrame, pred: Tensor, scored: Tensor, width: int = 350) -> np.ndarray:
    """Input | prediction | ground truth (the ``scored`` pixels, :func:`scored_pixels`; a sparse scan's
    nearest point per block, so it stays visible) | relative error, ``width`` px a tile, BGR uint8. The
    colour scale runs over the frame's range."""
    H, W = pred.shape
    size = (width, round(H * width / W))
    image = cv2.resize(frame.image[0].permute(1, 2, 0).numpy(), size, interpolation=cv2.INTER_AREA)
    has_ray = RAYS.get(frame.camera)[1].numpy().astype(np.uint8)
    small = cv2.resize(pred.cpu().numpy(), size, interpolation=cv2.INTER_AREA)
    small[cv2.resize(has_ray, size, interpolation=cv2.INTER_NEAREST) == 0] = 0
    gt = torch.where(scored, frame.distance, torch.full_like(frame.distance, np.inf))
    k = max(1, W // width)
    near = -torch.nn.functional.max_pool2d(-gt[None, None], k, k)[0, 0]
    near = cv2.resize(near.numpy(), size, interpolation=cv2.INTER_NEAREST)
    near[~np.isfinite(near)] = 0
    tiles = panel(
        torch.from_numpy(image).permute(2, 0, 1),
        torch.from_numpy(small)[None],
        torch.from_numpy(near)[None],
        NEAR[frame.source],
        frame.cap,
    )
    return np.ascontiguousarray(tiles[..., ::-1])


# ------------------------------------------------------------------ models, names, the table, the record
def load_model(path: Path, post_process: str = "none"):
    """A runtime for ``path``: an exported ``.onnx`` file (:class:`OnnxRuntime`), else a checkpoint
    (:class:`TorchRuntime`, float32 on the CPU, at the checkpoint's input size)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such checkpoint or exported file")
    if path.suffix.lower() == ".onnx":
        return OnnxRuntime(path, post_process=post_process)
    if path.suffix.lower() in (".pt", ".ts"):
        raise ValueError(
            f"{path}: a TorchScript file has no runtime here; score its checkpoint or an ONNX export"
        )
    return TorchRuntime(TrainedDepthNet.from_checkpoint(path), post_process=post_process)


def model_names(paths: Sequence[Path]) -> list[str]:
    """A short unique name per model file: a run's folder for ``RUN/checkpoints/last.ckpt``
    (``RUN_best-000`` for another checkpoint of it), else the file's stem; on a repeat the file's
    suffix is added (``model_onnx``), then ``_2``, ``_3``."""
    names: list[str] = []
    for path in map(Path, paths):
        if path.parent.name == "checkpoints":
            name = path.parent.parent.name + ("" if path.stem == "last" else f"_{path.stem}")
        else:
            name = path.stem
        if name in names and path.suffix:
            name = f"{name}_{path.suffix.lstrip('.').lower()}"
        base, n = name, 1
        while name in names:
            n += 1
            name = f"{base}_{n}"
        names.append(name)
    return names


HEADER = (
    "| model | frame | scored pixels | cap | abs_rel, a1, rmse | median-scaled: abs_rel, a1, rmse (ratio) "
    "| constant map: abs_rel, a1, rmse (at) |"
)


def _cell(metrics: dict[str, Any]) -> str:
    return f"{metrics['abs_rel']:.3f}, {metrics['a1']:.3f}, {metrics['rmse']:.2f}"


def row(
    model: str, frame: RealFrame | Missing, results: dict | None = None, constant: dict | None = None
) -> str:
    """One line of the table: the frame's first protocol, unscaled, median-scaled and its constant map."""
    if isinstance(frame, Missing):
        return f"| {model} | {frame.name} | missing: {frame.path} | | | | |"
    protocol = protocols(frame)[0]
    r = results[protocol.name]
    return (
        f"| {model} | {frame.name} | {constant['pixels']:,} | {protocol.cap[1]:g} m "
        f"| {_cell(r['none'])} "
        f"| {_cell(r['median'])} (x{r['median']['scale_ratio']:.2f}) "
        f"| {_cell(constant['none'])} ({constant['distance']:.2f} m) |"
    )


def records_table(paths: Sequence[Path], sets: Sequence[str] = FRAME_SETS) -> list[str]:
    """The scores kept in run records (``docs/records``: files, or folders searched for ``*.json``) that
    hold a ``real_world`` entry, one row per record and frame of ``sets`` (its first protocol), nothing
    re-scored."""
    files: list[Path] = []
    for path in map(Path, paths):
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such run record or folder")
        files += [path] if path.is_file() else sorted(path.rglob("*.json"))
    lines = [
        "| run | frame | abs_rel, a1, rmse | median-scaled: abs_rel, a1, rmse (ratio) "
        "| constant map: abs_rel, a1, rmse (at) |",
        "|---|---|---|---|---|",
    ]
    for file in files:
        real = load_json(file.read_bytes(), file).get("real_world")
        if real is None:
            continue
        for frame, r in real["frames"].items():
            if "/" in frame or not frame.startswith(tuple(sets)):  # "/": a second protocol, the JSON only
                continue
            c = real["constant_map"][frame]
            lines.append(
                f"| {file.stem} | {frame} | {_cell(r['none'])} "
                f"| {_cell(r['median'])} (x{r['median']['scale_ratio']:.2f}) "
                f"| {_cell(c)} ({c['distance']:.2f} m) |"
            )
    if len(lines) == 2:
        raise ValueError(f"{', '.join(map(str, paths))}: no run record with real-world scores")
    return lines


def anchors_table() -> list[str]:
    """The published anchors as printed beside the scores (and in docs/real-data.md, "Real photographs")."""
    lines = ["| published, zero-shot on KITTI-360 fisheyes (80 m) | abs_rel | a1 |", "|---|---|---|"]
    for method, abs_rel, a1 in ANCHORS:
        lines.append(f"| {method} | {abs_rel:.3f} | {'-' if a1 is None else f'{a1:.3f}'} |")
    return lines


def _frame_record(frame: RealFrame | Missing, constant: dict | None) -> dict[str, Any]:
    if isinstance(frame, Missing):
        return {"missing": str(frame.path)}
    return {
        "files": [str(p) for p in frame.files],
        "camera": frame.camera.to_dict(),
        "protocols": [dataclasses.asdict(p) for p in protocols(frame)],
        "constant_map": constant,
    }


def outputs(
    pictures: Path | None, json_out: Path | None, models: Sequence[str], frames, force: bool
) -> list[Path]:
    """The files a run writes; a FileExistsError before any work when one exists and not ``force``."""
    paths = [Path(json_out)] if json_out is not None else []
    if pictures is not None:
        paths += [
            Path(pictures) / f"{m}_{f.name}.png" for m in models for f in frames if isinstance(f, RealFrame)
        ]
    if not force:
        taken = [p for p in paths if p.exists()]
        if taken:
            raise FileExistsError(f"{taken[0]} exists; pass --force to replace it (or choose another path)")
    return paths


def score_models(
    model_paths: Sequence[Path],
    root: Path,
    sets: Sequence[str] = FRAME_SETS,
    pictures: Path | None = None,
    json_out: Path | None = None,
    force: bool = False,
    post_process: str = "none",
    echo=print,
    more=None,
) -> dict[str, Any]:
    """Every model on every frame of ``sets`` under ``root``: the table through ``echo`` line by line,
    pictures ``<model>_<frame>.png`` into ``pictures``, the record (returned) into ``json_out`` when
    given. ``more(record, predictions)``: further scores added to the record before it is written, given
    each model's predicted distance per frame (``{model: {frame: [H, W]}}``)."""
    root = Path(root)
    for path in map(Path, model_paths):  # before the frames are read
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such checkpoint or exported file")
    frames = load_frames(root, sets)
    names = model_names(model_paths)
    outputs(pictures, json_out, names, frames, force)
    scored = {f.name: scored_pixels(f) for f in frames if isinstance(f, RealFrame)}
    constants = {f.name: constant_map(f, scored[f.name]) for f in frames if isinstance(f, RealFrame)}
    present = sum(isinstance(f, RealFrame) for f in frames)
    echo(f"Real frames under {root}: {present} with ground truth, {len(frames) - present} missing")
    echo(HEADER)
    echo("|---|---|---|---|---|---|---|")
    record: dict[str, Any] = {
        "format": 1,
        "root": str(root),
        "written": time.strftime("%Y-%m-%d %H:%M:%S"),
        "post_process": post_process,
        "frames": {f.name: _frame_record(f, constants.get(f.name)) for f in frames},
        "models": {},
        "anchors": [{"method": m, "abs_rel": a, "a1": b} for m, a, b in ANCHORS],
    }
    predictions: dict[str, dict[str, Tensor]] = {}
    for path, name in zip(model_paths, names, strict=True):
        runtime = load_model(Path(path), post_process)
        entry = {"file": str(path), "model": runtime.describe(), "frames": {}}
        predictions[name] = {}
        for frame in frames:
            if isinstance(frame, Missing):
                entry["frames"][frame.name] = {"missing": str(frame.path)}
                echo(row(name, frame))
                continue
            results, pred = score(runtime, frame)
            predictions[name][frame.name] = pred
            entry["frames"][frame.name] = results
            echo(row(name, frame, results, constants[frame.name]))
            if pictures is not None:
                ok, encoded = cv2.imencode(".png", picture(frame, pred, scored[frame.name]))
                if not ok:
                    raise OSError(f"{pictures}: could not encode the picture of {frame.name}")
                atomic_write_bytes(Path(pictures) / f"{name}_{frame.name}.png", encoded.tobytes())
        record["models"][name] = entry
    echo("")
    for line in anchors_table():
        echo(line)
    if more is not None:
        more(record, predictions)
    if json_out is not None:
        atomic_write_text(json_out, json.dumps(record, indent=1) + "\n")
    return record


# ------------------------------------------------------------------ the command
@ends_on_signals  # SIGINT / SIGTERM: one line, exit 130 / 143
def main(argv=None) -> int:
    parser = CommandParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("models", nargs="+", type=Path, help="checkpoints (.ckpt) or exported files (.onnx)")
    parser.add_argument("--root", type=Path, help=f"real data folder (default: ${ROOT_VARIABLE})")
    parser.add_argument("--frames", nargs="+", choices=FRAME_SETS, default=list(FRAME_SETS))
    parser.add_argument("--pictures", type=Path, help="write <model>_<frame>.png here")
    parser.add_argument("--json", type=Path, help="write every number to this JSON file")
    parser.add_argument("--force", action="store_true", help="replace existing pictures and JSON")
    parser.add_argument("--post-process", default="none", choices=POST_PROCESSING)
    parser.add_argument("--from-records", action="store_true", help="MODEL...: run records; score nothing")
    parser.add_argument("--no-multiview", action="store_true", help="score the models only, not stereo")
    parser.add_argument(
        "--matcher", choices=MATCHERS, default="sgbm", help="the stereo matcher (default sgbm)"
    )
    parser.add_argument("--multiview", action="store_true", help="with --from-records: the stereo table")
    args = parser.parse_args(argv)
    if args.from_records:
        try:
            table = multiview_records_table if args.multiview else records_table
            print("\n".join(table(args.models) if args.multiview else table(args.models, args.frames)))
        except (OSError, ValueError) as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        return 0
    echo = lambda line: print(line, flush=True)  # noqa: E731

    try:
        root = data_root(args.root)

        def multiview(record, predictions):
            record["multiview"] = multiview_scores(
                root, predictions, args.pictures, echo, matcher=args.matcher
            )

        if args.pictures is not None and not args.force and not args.no_multiview:
            taken = sorted(Path(args.pictures).glob("multiview_*.png"))
            if taken:
                raise FileExistsError(f"{taken[0]} exists; pass --force to replace it")
        record = score_models(
            args.models, root, args.frames, args.pictures, args.json, args.force, args.post_process,
            echo=echo, more=None if args.no_multiview else multiview,
        )  # fmt: skip
    except (OSError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    missing = [name for name, frame in record["frames"].items() if "missing" in frame]
    if missing:
        print(f"missing: {', '.join(missing)} (their rows name the path)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
