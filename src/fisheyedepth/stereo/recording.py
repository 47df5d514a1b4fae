"""``fisheyedepth-multiview ROOT --out OUT [--refine] [--sources rig,time]``: sweep stereo over a recording
in the rig layout (docs/data-format.md, "Robot rig layout"): every image paired with the rig's other cameras
at the same instant (``rig``) and with its own camera a few frames on (``time``, the odometry's motion),
metric because the calibration and the odometry are.

For each image it can pair it writes, under ``OUT/<sequence>/``:
- ``distance/<camera>/<timestamp_ns>.npy``: float32 H x W metres along the ray, 0 where the round trip
  rejects or no partner sees the pixel;
- ``dense/<camera>/<timestamp_ns>.npy``: the same before the check (every pixel a partner sees);
- ``confidence/<camera>/<timestamp_ns>.npy``: float32 in [0, 1];
- ``panels/<camera>/<timestamp_ns>.png``: image | checked | dense [| ground truth];
with ``--refine``, ``OUT/rig.yaml``: the recording's rig.yaml with the refined ``cam_to_body`` (what
changed, and the epipolar error before and after, in the summary); and ``OUT/summary.json``: per image
its partners and, where the folder has ground truth (``<sequence>/distance/<camera>/<timestamp_ns>.npy``),
abs_rel, a1, coverage and the constant map on the same scored pixels; the images with no partner, by name.
Nothing existing is replaced without ``--overwrite``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from tqdm import tqdm

from ..cameras import load_yaml
from ..data.layouts import Frame, RigLayout
from ..geometry.se3 import relative_pose
from ..images import read_image
from ..utils import atomic_write_bytes, atomic_write_text
from ..viz import colourise
from .refine import Matches, match_features, refine_relative_pose
from .sweep import StereoResult, SweepStereo, View

log = logging.getLogger("fisheyedepth")
SOURCES = ("rig", "time")
REFINE = ("rotation", "pose")  # what --refine corrects of each camera's extrinsics (pose: also the direction)


@dataclass(frozen=True)
class Partner:
    camera: str
    frame: Frame


@dataclass(frozen=True)
class Pairing:
    sequence: str
    camera: str
    frame: Frame
    partners: tuple[Partner, ...]

    @property
    def name(self) -> str:
        return f"{self.sequence}/{self.camera}/{self.frame.key}"


def check_sources(sources: tuple[str, ...]) -> tuple[str, ...]:
    if not sources or set(sources) - set(SOURCES):
        raise ValueError(f"--sources: {','.join(sources)!r}; choose from {','.join(SOURCES)}")
    return sources


def _centre(layout: RigLayout, camera: str, frame: Frame) -> np.ndarray:
    return (frame.pose @ layout.cameras[camera].cam_to_body)[:3, 3]


def pairings(
    layout: RigLayout,
    sources: tuple[str, ...] = SOURCES,
    same_instant_ns: int = 1_000_000,
    min_baseline: float = 0.05,
    max_frames_apart: int = 5,
) -> list[Pairing]:
    """Every image of the recording with its partners: each other camera's image within
    ``same_instant_ns`` (``rig``), and the first of the next ``max_frames_apart`` images of its own camera
    (else of the previous ones) whose centre moved ``min_baseline`` metres or more (``time``)."""
    check_sources(sources)
    out = []
    for sequence in layout.sequences():
        frames = {camera: layout.frames(sequence, camera) for camera in layout.cameras}
        for camera, own in frames.items():
            for i, frame in enumerate(own):
                partners: list[Partner] = []
                if "rig" in sources:
                    for other, theirs in frames.items():
                        if other == camera or not theirs:
                            continue
                        nearest = min(theirs, key=lambda f: abs(f.key - frame.key))
                        if abs(nearest.key - frame.key) <= same_instant_ns:
                            partners.append(Partner(other, nearest))
                if "time" in sources:
                    here = _centre(layout, camera, frame)
                    later = own[i + 1 : i + 1 + max_frames_apart]
                    earlier = own[max(0, i - max_frames_apart) : i][::-1]
                    for candidate in (*later, *earlier):
                        if np.linalg.norm(_centre(layout, camera, candidate) - here) >= min_baseline:
                            partners.append(Partner(camera, candidate))
                            break
                out.append(Pairing(sequence, camera, frame, tuple(partners)))
    return out


def _image(layout: RigLayout, sequence: str, camera: str, frame: Frame) -> torch.Tensor:
    bgr = read_image(layout.image(sequence, camera, frame)).bgr
    expected = (layout.cameras[camera].camera.width, layout.cameras[camera].camera.height)
    if (bgr.shape[1], bgr.shape[0]) != expected:
        raise ValueError(
            f"{layout.image(sequence, camera, frame)}: {bgr.shape[1]}x{bgr.shape[0]} pixels, but the "
            f"calibration of camera {camera!r} is {expected[0]}x{expected[1]}"
        )
    return torch.from_numpy(bgr[..., ::-1].copy()).permute(2, 0, 1)[None].float() / 255


def _truth(layout: RigLayout, pairing: Pairing) -> torch.Tensor | None:
    path = layout.distance(pairing.sequence, pairing.camera, pairing.frame)
    if path is None:
        return None
    truth = np.load(path, allow_pickle=False)
    camera = layout.cameras[pairing.camera].camera
    if truth.shape != (camera.height, camera.width) or not np.isfinite(truth).all() or (truth < 0).any():
        raise ValueError(
            f"{path}: expected a finite, non-negative {camera.height} x {camera.width} distance map, got "
            f"shape {truth.shape}"
        )
    return torch.from_numpy(truth.astype(np.float32))


def estimate(layout: RigLayout, pairing: Pairing, sweep: SweepStereo) -> StereoResult:
    """The sweep for one pairing (its image the reference, its partners the sources)."""
    spec = layout.cameras[pairing.camera]
    reference = View(
        _image(layout, pairing.sequence, pairing.camera, pairing.frame), spec.camera, torch.eye(4)
    )
    sources = []
    for partner in pairing.partners:
        theirs = layout.cameras[partner.camera]
        T = relative_pose(
            torch.from_numpy(pairing.frame.pose),
            torch.from_numpy(partner.frame.pose),
            torch.from_numpy(spec.cam_to_body),
            torch.from_numpy(theirs.cam_to_body),
        ).float()
        image = _image(layout, pairing.sequence, partner.camera, partner.frame)
        sources.append(View(image, theirs.camera, T))
    return sweep(reference, sources)


def _same_instants(layout: RigLayout, a: str, b: str, limit: int, same_instant_ns: int = 1_000_000):
    """Up to ``limit`` (sequence, frame of a, frame of b) taken at one instant, spread over the recording."""
    found = []
    for sequence in layout.sequences():
        theirs = layout.frames(sequence, b)
        for frame in layout.frames(sequence, a):
            nearest = min(theirs, key=lambda f: abs(f.key - frame.key), default=None)
            if nearest is not None and abs(nearest.key - frame.key) <= same_instant_ns:
                found.append((sequence, frame, nearest))
    step = max(1, len(found) // limit) if found else 1
    return found[::step][:limit]


def _pair_matches(layout: RigLayout, a: str, b: str, instants: int) -> tuple[Matches, int]:
    """The SIFT matches between cameras ``a`` and ``b`` pooled over up to ``instants`` same-instant images."""
    found, used = [], _same_instants(layout, a, b, instants)
    for sequence, frame_a, frame_b in used:
        found.append(match_features(
            _image(layout, sequence, a, frame_a), layout.cameras[a].camera,
            _image(layout, sequence, b, frame_b), layout.cameras[b].camera,
        ))  # fmt: skip
    return Matches.pooled(found), len(used)


def refine_rig(layout: RigLayout, what: str = "rotation", instants: int = 5, min_inliers: int = 30) -> dict:
    """Each camera's extrinsics refined from its images (:mod:`.refine`): every pair of cameras matched at
    up to ``instants`` shared instants; from the first camera, which is kept, each other camera is reached
    through the pair with the most matches to a camera already placed (a maximum spanning tree), and its
    rotation (``what="pose"``: and its translation's direction) relative to that camera refined, the
    baseline's length kept. ``layout.cameras`` is updated in place; returns what changed, per camera, and
    the cameras left as they were (no pair with ``min_inliers`` matches to the placed ones)."""
    if what not in REFINE:
        raise ValueError(f"--refine: {what!r}; choose from {', '.join(REFINE)}")
    names = list(layout.cameras)
    matches = {}
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            m, used = _pair_matches(layout, a, b, instants)
            if len(m.rays_a) >= min_inliers:
                matches[a, b] = (m, used)
    placed, refined_cameras = [names[0]], {}
    while True:
        edges = [(len(m.rays_a), a, b) for (a, b), (m, _) in matches.items() if (a in placed) ^ (b in placed)]
        if not edges:
            break
        _, a, b = max(edges)
        m, used = matches[a, b]
        if b in placed:  # refine the unplaced camera against the placed one
            a, b, m = b, a, Matches(m.rays_b, m.rays_a, m.uv_b, m.uv_a)
        E_a, E_b = layout.cameras[a].cam_to_body, layout.cameras[b].cam_to_body
        T_a_to_b = torch.from_numpy(np.linalg.inv(E_b) @ E_a)
        focal = float(np.mean(layout.cameras[b].camera.paraxial_focal()))
        refined = refine_relative_pose(m, T_a_to_b, focal, direction=what == "pose")
        layout.cameras[b] = dataclasses.replace(
            layout.cameras[b], cam_to_body=E_a @ np.linalg.inv(refined.T_a_to_b.numpy())
        )
        placed.append(b)
        refined_cameras[b] = {"relative_to": a, "instants": used, "matches": refined.matches,
                     "inliers": refined.inliers, "rotation_deg": round(refined.rotation_deg, 4),
                     "direction_deg": round(refined.direction_deg, 4),
                     "epipolar_px_before": round(refined.error_before_px, 3),
                     "epipolar_px_after": round(refined.error_after_px, 3)}  # fmt: skip
    unrefined = [n for n in names if n not in placed]
    return {"what": what, "kept": names[0], "cameras": refined_cameras, "unrefined": unrefined}


def refined_rig_yaml(layout: RigLayout) -> str:
    """The recording's ``rig.yaml`` with each camera's ``cam_to_body`` replaced by ``layout``'s (its other
    entries, paths relative to the recording, unchanged): a drop-in for the recording's own."""
    import yaml

    rig_file = layout.root / "rig.yaml"
    rig = load_yaml(rig_file.read_text(encoding="utf-8"), rig_file)
    if "cameras" not in rig:  # every camera of the calibration file
        rig["cameras"] = [{"name": name} for name in layout.cameras]
    for entry in rig["cameras"]:
        if str(entry["name"]) in layout.cameras:
            E = layout.cameras[str(entry["name"])].cam_to_body
            entry["cam_to_body"] = [[float(v) for v in row] for row in E]
    return yaml.safe_dump(rig, sort_keys=False, width=120)


def score(distance: torch.Tensor, truth: torch.Tensor, among: torch.Tensor) -> dict[str, Any]:
    """abs_rel, a1 and coverage of ``distance`` on ``among`` (pixels with truth), and the constant map at
    the truth's median on the same scored pixels: a score of nothing is ``None``, never 0."""
    among = among & (truth > 0)
    kept = among & (distance > 0)
    if not kept.any():
        return {"abs_rel": None, "a1": None, "coverage": 0.0, "pixels": 0, "constant_abs_rel": None}
    ratio = distance[kept] / truth[kept]
    constant = truth[kept].median()
    return {
        "abs_rel": round(float((ratio - 1).abs().mean()), 4),
        "a1": round(float((torch.maximum(ratio, 1 / ratio) < 1.25).float().mean()), 4),
        "coverage": round(float(kept.sum() / among.sum().clamp(min=1)), 4),
        "pixels": int(kept.sum()),
        "constant_abs_rel": round(float(((constant - truth[kept]).abs() / truth[kept]).mean()), 4),
    }


def panel(image: torch.Tensor, result: StereoResult, truth: torch.Tensor | None) -> np.ndarray:
    """image | checked | dense [| ground truth], BGR for cv2, on one colour scale."""
    seen = result.dense[0][result.dense[0] > 0]
    vmin, vmax = (0.3, 20.0) if seen.numel() == 0 else (float(seen.min()), float(seen.max()))
    vmin, vmax = max(vmin, 0.05), max(vmax, vmin * 1.5)
    tiles = [(image[0].permute(1, 2, 0).numpy() * 255).astype(np.uint8)]
    tiles += [colourise(result.distance[0], vmin, vmax), colourise(result.dense[0], vmin, vmax)]
    if truth is not None:
        tiles.append(colourise(truth, vmin, vmax))
    return np.concatenate(tiles, axis=1)[..., ::-1]


def _npy(path: Path, array: torch.Tensor) -> None:
    import io

    buffer = io.BytesIO()
    np.save(buffer, array.detach().cpu().numpy().astype(np.float32))
    atomic_write_bytes(path, buffer.getvalue())


def run(
    root: str | Path,
    out: str | Path,
    sweep: SweepStereo,
    sources: tuple[str, ...] = SOURCES,
    overwrite: bool = False,
    progress: bool = True,
    max_images: int | None = None,
    refine: str | None = None,
) -> dict[str, Any]:
    """The command's work: every pairing of ``root`` swept, its outputs and ``summary.json`` in ``out``;
    with ``refine`` (:data:`REFINE`) the rig's extrinsics are refined from its images first
    (:func:`refine_rig`), swept with, and written to ``out/rig.yaml``; the recording is never modified."""
    layout, out = RigLayout(root), Path(out)
    check_sources(sources)
    if refine is not None and refine not in REFINE:
        raise ValueError(f"--refine: {refine!r}; choose from {', '.join(REFINE)}")
    summary_path = out / "summary.json"
    for path in (summary_path, out / "rig.yaml") if refine else (summary_path,):
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} exists; pass --overwrite to replace the outputs")
    refinement = None
    if refine:
        refinement = refine_rig(layout, refine)
        for name, change in refinement["cameras"].items():
            log.info("%s refined against %s: %.3f degrees; epipolar error %.2f -> %.2f px (%d inliers)",
                     name, change["relative_to"], change["rotation_deg"], change["epipolar_px_before"],
                     change["epipolar_px_after"], change["inliers"])  # fmt: skip
        if refinement["unrefined"]:
            log.warning("not refined (too few matches with the other cameras): %s", refinement["unrefined"])
        atomic_write_text(out / "rig.yaml", refined_rig_yaml(layout))
    planned = pairings(layout, sources)
    paired = [p for p in planned if p.partners][:max_images]
    unpaired = [p.name for p in planned if not p.partners]
    if unpaired:
        log.warning("%d images have no partner and are left out: %s", len(unpaired), ", ".join(unpaired[:5]))
    images = []
    for pairing in tqdm(paired, desc="sweep stereo", unit="image", disable=not progress):
        result = estimate(layout, pairing, sweep)
        folder = out / pairing.sequence
        stem = f"{pairing.camera}/{pairing.frame.key}"
        for what, array in (
            ("distance", result.distance),
            ("dense", result.dense),
            ("confidence", result.confidence),
        ):
            _npy(folder / what / f"{stem}.npy", array[0])
        truth = _truth(layout, pairing)
        image = _image(layout, pairing.sequence, pairing.camera, pairing.frame)
        png = cv2.imencode(".png", panel(image, result, truth))[1].tobytes()
        atomic_write_bytes(folder / "panels" / f"{stem}.png", png)
        record: dict[str, Any] = {
            "image": pairing.name,
            "partners": [f"{p.camera}/{p.frame.key}" for p in pairing.partners],
            "kept": round(float(result.valid.float().mean()), 4),
            "seen": round(float(result.seen.float().mean()), 4),
        }
        if truth is not None:
            seen_by_partner = result.seen[0]
            record["checked"] = score(result.distance[0], truth, seen_by_partner)
            record["dense"] = score(result.dense[0], truth, seen_by_partner)
        images.append(record)
    summary = {
        "root": str(root),
        "sources": list(sources),
        "sweep": {k: getattr(sweep, k) for k in sweep.__dataclass_fields__},
        "refinement": refinement,
        "images": images,
        "unpaired": unpaired,
    }
    atomic_write_text(summary_path, json.dumps(summary, indent=2) + "\n")
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="fisheyedepth-multiview", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    parser.add_argument("root", type=Path, help="a recording in the rig layout")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--sources", default="rig,time", help="rig, time, or both (default)")
    parser.add_argument("--hypotheses", type=int, default=128)
    parser.add_argument("--min-distance", type=float, default=0.3)
    parser.add_argument("--max-distance", type=float, default=80.0)
    parser.add_argument("--cost", choices=("zncc", "census"), default="zncc")
    parser.add_argument("--max-images", type=int, default=None)
    refine_help = "refine the rig's extrinsics from its images first (rotation, the default, or pose: also "
    refine_help += "the translation's direction); writes OUT/rig.yaml"
    parser.add_argument("--refine", nargs="?", const="rotation", choices=REFINE, help=refine_help)
    parser.add_argument("--overwrite", action="store_true")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(message)s")
    try:
        sweep = SweepStereo(args.hypotheses, args.min_distance, args.max_distance, args.cost)
        sources = tuple(args.sources.split(","))
        summary = run(
            args.root, args.out, sweep, sources, args.overwrite, not args.quiet, args.max_images, args.refine
        )
    except (FileNotFoundError, FileExistsError, NotADirectoryError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"{len(summary['images'])} images swept, {len(summary['unpaired'])} without a partner; {args.out}")
    return 0
