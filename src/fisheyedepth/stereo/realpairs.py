"""Sweep stereo scored on real photographs with metric ground truth (``make realscore``): the Aria
Digital Twin's two SLAM fisheyes (``adt_slam/``: frames 0 and 1, each camera as the reference, the
stored extrinsics refined from the images' feature matches first) and Middlebury 2014 Motorcycle
(:func:`.pairs.motorcycle`, a rectified pinhole pair).

Each pair is scored on the reference's *overlap*: the pixels with ground truth whose ray, at the
ground-truth distance, lands inside the partner's image and field of view, the pixels a partner could
match at all. The checked output (after the round trip) is scored on the overlap pixels it keeps, with
its coverage of the overlap; the dense output (before the check) on every overlap pixel it has; the
constant map at the overlap's median distance on the same pixels as each.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..cameras.io import field
from ..data.realframes import Missing, load_adt, one_match, read_json, read_rgb
from ..geometry.se3 import invert_pose, transform_points
from .pairs import RealPair, motorcycle
from .recording import score
from .refine import Matches, match_features, refine_relative_pose
from .sweep import RAYS, StereoResult, SweepStereo, View

ADT_CAMERAS = ("camera-slam-left", "camera-slam-right")
ADT_REFINE_FRAMES = (0, 1, 2)  # the same-instant image pairs whose matches refine the pair's rotation


class ScoredPair(NamedTuple):
    pair: RealPair
    overlap: Tensor  # [H, W] bool: the pixels scored
    refinement: dict[str, Any] | None  # what the refinement changed, None for a pair taken as calibrated


def overlap(pair: RealPair) -> Tensor:
    """``[H, W]`` bool: reference pixels with ground truth whose point, at the ground-truth distance, the
    source camera sees inside its image."""
    rays, has_ray = RAYS.get(pair.reference.camera)
    points = rays.double() * pair.distance.double()[..., None]
    uv, visible = pair.source.camera.project(transform_points(pair.source.T_ref_to_view.double(), points))
    w, h = pair.source.camera.width, pair.source.camera.height
    inside = (uv[..., 0] >= 0) & (uv[..., 0] <= w - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1)
    return has_ray & visible & inside & (pair.distance > 0)


def adt_extrinsics(path: Path, camera: str) -> Tensor:
    """``cameras.<camera>.T_device_camera`` of ``adt_sample.json``: a 4x4 rigid transform, float64."""
    key = f"cameras.{camera}.T_device_camera"
    value = field(read_json(path), key, path)
    matrix = np.asarray(value, dtype=np.float64) if isinstance(value, list) else np.zeros(0)
    if (
        matrix.shape != (4, 4)
        or not np.isfinite(matrix).all()
        or not np.allclose(matrix[:3, :3] @ matrix[:3, :3].T, np.eye(3), atol=1e-4)
        or not np.allclose(matrix[3], [0, 0, 0, 1])
    ):
        raise ValueError(f"{path}: {key}: expected a 4x4 rigid transform (a rotation and a translation)")
    return torch.from_numpy(matrix)


def adt_pairs(folder: Path, refine: bool = True) -> list[ScoredPair | Missing]:
    """The ADT SLAM pairs with ground truth (frames 0 and 1, left and right each the reference), the
    right camera's rotation relative to the left refined from the matches of every same-instant pair of
    images in the folder (:data:`ADT_REFINE_FRAMES`), once for all four."""
    frames = {f.name: f for f in load_adt(folder)}
    gone = [f for f in frames.values() if isinstance(f, Missing)]
    if gone:
        return gone
    calibration = folder / "adt_sample.json"
    left_to_device, right_to_device = (adt_extrinsics(calibration, c) for c in ADT_CAMERAS)
    T_left_to_right = invert_pose(right_to_device) @ left_to_device
    cameras = {c: frames[f"adt_{c.rsplit('-', 1)[1]}_0"].camera for c in ADT_CAMERAS}
    refinement = None
    if refine:
        found = []
        for index in ADT_REFINE_FRAMES:
            names = [f"adt_{c.rsplit('-', 1)[1]}_{index}" for c in ADT_CAMERAS]
            paths = [one_match(folder, f"{c}_{index}_*.png") for c in ADT_CAMERAS]
            if None not in paths:  # the frames with ground truth are read already
                pairs = zip(names, paths, strict=True)
                a, b = (frames[n].image if n in frames else read_rgb(p) for n, p in pairs)
                found.append(match_features(a, cameras[ADT_CAMERAS[0]], b, cameras[ADT_CAMERAS[1]]))
        matches = Matches.pooled(found)
        focal = float(np.mean(cameras[ADT_CAMERAS[1]].paraxial_focal()))
        refined = refine_relative_pose(matches, T_left_to_right, focal, direction=False)
        T_left_to_right = refined.T_a_to_b
        refinement = {"instants": len(found), **{k: round(v, 4) if isinstance(v, float) else v
                      for k, v in refined._asdict().items() if k != "T_a_to_b"}}  # fmt: skip
    out: list[ScoredPair | Missing] = []
    T_right_to_left = invert_pose(T_left_to_right)
    for index in (0, 1):
        for ref, src, T in (("left", "right", T_left_to_right), ("right", "left", T_right_to_left)):
            a, b = frames[f"adt_{ref}_{index}"], frames[f"adt_{src}_{index}"]
            pair = RealPair(
                f"adt_{ref}_{index}",
                View(a.image, a.camera, torch.eye(4)),
                View(b.image, b.camera, T.float()),
                a.distance * a.mask,
            )
            out.append(ScoredPair(pair, overlap(pair), refinement))
    return out


def middlebury_pair() -> ScoredPair:
    pair = motorcycle()
    return ScoredPair(pair, pair.distance > 0, None)


def score_pair(scored: ScoredPair, sweep: SweepStereo) -> tuple[dict[str, Any], StereoResult]:
    """The sweep on one pair, scored on its overlap: the checked and the dense output, each with the
    constant map on its own scored pixels (:func:`.recording.score`)."""
    pair = scored.pair
    result = sweep(pair.reference, [pair.source])
    truth = pair.distance
    record = {
        "overlap_pixels": int(scored.overlap.sum()),
        "checked": score(result.distance[0], truth, scored.overlap),
        "dense": score(result.dense[0], truth, scored.overlap),
        "refinement": scored.refinement,
    }
    return record, result


# settings chosen by the scene's kind, not tuned on the ground truth: indoors 0.2-10 m (ZNCC, as the
# command's default); Middlebury's scene 1.5-10 m (census, robust to its two exposures)
ADT_SWEEP = SweepStereo(hypotheses=128, min_distance=0.2, max_distance=10.0, cost="zncc")
MIDDLEBURY_SWEEP = SweepStereo(hypotheses=128, min_distance=1.5, max_distance=10.0, cost="census")
SETTINGS = ("hypotheses", "min_distance", "max_distance", "cost")  # kept in the record
HEADER = (
    "| reference frame | its partner | overlap pixels | sweep, checked: abs_rel, a1, coverage "
    "| constant map there | sweep, dense: abs_rel, a1 | constant map there "
    "| models on the overlap: abs_rel, a1 |"
)


def _cell(metrics: dict[str, Any], keys=("abs_rel", "a1", "coverage")) -> str:
    if metrics["abs_rel"] is None:
        return "nothing kept"
    return ", ".join(f"{metrics[k]:.3f}" for k in keys)


def multiview_row(name: str, result: dict[str, Any]) -> str:
    """One line of the table (:data:`HEADER`) from one frame's record."""
    partner = "right" if "_left_" in name else "left" if name.startswith("adt") else "right image"
    models = result.get("models") or {}
    monocular = "; ".join(f"{m}: {_cell(r, ('abs_rel', 'a1'))}" for m, r in models.items()) or "-"
    c, d = result["checked"], result["dense"]
    return (
        f"| {name} | {partner} | {result['overlap_pixels']:,} | {_cell(c)} | {c['constant_abs_rel']} "
        f"| {_cell(d, ('abs_rel', 'a1'))} | {d['constant_abs_rel']} | {monocular} |"
    )


def multiview_records_table(paths) -> list[str]:
    """The sweep's real-world table kept in records (JSON files with a ``multiview`` entry, as
    ``scripts/tools/real_world.py --json`` writes them), nothing re-scored."""
    from ..cameras.io import load_json

    lines = [HEADER, "|---|---|---|---|---|---|---|---|"]
    for path in map(Path, paths):
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such run record")
        kept = load_json(path.read_bytes(), path).get("multiview")
        if not isinstance(kept, dict):
            continue
        for name, result in kept.items():
            lines.append(f"| {name} | missing: {result['missing']} | | | | | | |" if "missing" in result
                         else multiview_row(name, result))  # fmt: skip
    if len(lines) == 2:
        raise ValueError(f"{', '.join(map(str, paths))}: no run record with sweep-stereo scores")
    return lines


def multiview_scores(
    root: Path,
    predictions: dict[str, dict[str, Tensor]] | None = None,
    pictures: Path | None = None,
    echo=print,
    middlebury: bool = True,
) -> dict[str, Any]:
    """Sweep stereo on every real pair (:func:`adt_pairs` under ``root/adt_slam``, refined; Middlebury
    Motorcycle when scikit-image is installed), a table row each through ``echo``, beside each model of
    ``predictions`` (``{model: {frame: [H, W]}}``, as ``scripts/tools/real_world.py`` passes them) scored on
    the same overlap pixels, and panels ``multiview_<frame>.png`` (image | checked | dense | ground
    truth) into ``pictures``. Returns the record: per frame, the scores and the refinement."""
    import cv2

    from ..utils import atomic_write_bytes
    from .recording import panel

    predictions = predictions or {}
    pairs: list[tuple[ScoredPair | Missing, SweepStereo]] = [
        (p, ADT_SWEEP) for p in adt_pairs(Path(root) / "adt_slam")
    ]
    if middlebury:
        try:
            pairs.append((middlebury_pair(), MIDDLEBURY_SWEEP))
        except ImportError as err:
            echo(f"(Middlebury Motorcycle left out: {err})")
    echo("")
    echo(HEADER)
    echo("|---|---|---|---|---|---|---|---|")
    record: dict[str, Any] = {}
    for scored, sweep in pairs:
        if isinstance(scored, Missing):
            record[scored.name] = {"missing": str(scored.path)}
            echo(f"| {scored.name} | missing: {scored.path} | | | | | | |")
            continue
        result, stereo = score_pair(scored, sweep)
        name, truth = scored.pair.name, scored.pair.distance
        models = {
            model: score(frames[name].to(truth), truth, scored.overlap)
            for model, frames in predictions.items()
            if name in frames
        }
        result["models"] = models
        result["sweep"] = {
            k: getattr(sweep, k) for k in ("hypotheses", "min_distance", "max_distance", "cost")
        }
        record[name] = result
        echo(multiview_row(name, result))
        if pictures is not None:
            image = scored.pair.reference.image
            tiles = panel(image if image.shape[1] == 3 else image.expand(-1, 3, -1, -1), stereo, truth)
            atomic_write_bytes(
                Path(pictures) / f"multiview_{name}.png", cv2.imencode(".png", tiles)[1].tobytes()
            )
    refinement = next((p.refinement for p, _ in pairs if isinstance(p, ScoredPair) and p.refinement), None)
    if refinement is not None:
        r = refinement
        echo(
            f"\nADT slam right relative to left, refined from {r['instants']} image pairs: turned "
            f"{r['rotation_deg']:.2f} degrees, median epipolar error {r['error_before_px']:.2f} -> "
            f"{r['error_after_px']:.2f} px ({r['inliers']} of {r['matches']} matches)"
        )
    return record
