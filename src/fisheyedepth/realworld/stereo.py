"""Stereo scored on real photographs with metric ground truth (``make realscore``): the Aria Digital
Twin's two SLAM fisheyes (frames 0 and 1, each camera as the reference, their rotation refined from
the images' feature matches first) and Middlebury 2014 Motorcycle (a rectified pinhole pair); readers
in :mod:`fisheyedepth.realworld.pairs`.

Each pair is scored on the reference's overlap (:func:`~fisheyedepth.realworld.pairs.overlap`): the
checked output on the overlap pixels it keeps, with its coverage of the overlap; the filled (dense) output
on every overlap pixel it has; the constant map at the overlap's median distance on the same pixels as
each. The matcher is the rectified one (``sgbm``, :mod:`.pipeline`) or the sweep (``sweep``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from torch import Tensor

from ..stereo.features import Matches, match_features
from ..stereo.matchers import MATCHERS, Matcher
from ..stereo.pipeline import SgbmSettings
from ..stereo.refine import refine_relative_pose
from ..stereo.scores import panel, score
from ..stereo.sgbm import SgbmMatcher
from ..stereo.sweep import SweepMatcher, SweepSettings
from .frames import Missing, adt_camera, load_adt
from .pairs import (
    ADT_CAMERAS,
    RealPair,
    adt_instants,
    adt_left_to_right,
    adt_pairs,
    motorcycle,
    overlap,
)

# the range by the scene's kind, never tuned on the ground truth: indoors 0.2-10 m; Middlebury's scene
# 1.5-10 m. The sweep: ZNCC indoors (the command's default), census on Middlebury's two exposures.
ADT_RANGE, MIDDLEBURY_RANGE = (0.2, 10.0), (1.5, 10.0)
SETTINGS = {
    "sgbm": {"adt": SgbmSettings(*ADT_RANGE), "middlebury": SgbmSettings(*MIDDLEBURY_RANGE)},
    "sweep": {"adt": SweepSettings(128, *ADT_RANGE, cost="zncc"),
              "middlebury": SweepSettings(128, *MIDDLEBURY_RANGE, cost="census")},
}  # fmt: skip
HEADER = (
    "| reference frame | its partner | overlap pixels | checked: abs_rel, a1, coverage "
    "| constant map there | filled: abs_rel, a1, coverage | constant map there "
    "| models on the overlap: abs_rel, a1 |"
)


def refine_adt(folder: Path) -> tuple[Tensor, dict[str, Any]]:
    """The right SLAM camera's pose relative to the left one, its rotation refined from the pooled matches
    of every same-instant image pair in the folder; and what the refinement changed."""
    T = adt_left_to_right(folder)
    instants = adt_instants(folder)
    left, right = (adt_camera(folder / "adt_sample.json", name) for name in ADT_CAMERAS)
    matches = Matches.pooled([match_features(a, left, b, right) for a, b in instants])
    refined = refine_relative_pose(matches, T, float(np.mean(right.paraxial_focal())), direction=False)
    tensors = ("T_a_to_b", "correction", "covariance")
    record = {"instants": len(instants), **{k: round(v, 4) if isinstance(v, float) else v
              for k, v in refined._asdict().items() if k not in tensors}}  # fmt: skip
    return refined.T_a_to_b, record


def matcher_for(name: str, scene: str) -> Matcher:
    """The matcher ``name`` (:data:`~.matchers.MATCHERS`) with the settings of ``scene`` (``adt`` or
    ``middlebury``: :data:`SETTINGS`)."""
    if name not in MATCHERS:
        raise ValueError(f"matcher: {name!r}; choose from {', '.join(MATCHERS)}")
    settings = SETTINGS[name][scene]
    return SgbmMatcher(settings) if name == "sgbm" else SweepMatcher(settings)


def score_pair(pair: RealPair, scored: Tensor, matcher: Matcher) -> tuple[dict[str, Any], tuple]:
    """One pair, scored on ``scored`` (its overlap): the checked and the filled output of ``matcher``,
    each with the constant map on its own scored pixels (:func:`.scores.score`)."""
    checked, dense = matcher.maps(pair.image, pair.partner_image, pair.camera, pair.partner_camera, pair.T)
    record = {
        "overlap_pixels": int(scored.sum()),
        "checked": score(checked, pair.distance.numpy(), scored.numpy()),
        "dense": score(dense, pair.distance.numpy(), scored.numpy()),
    }
    return record, (checked, dense)


def real_pairs(root: Path, matcher: str = "sgbm", middlebury: bool = True, echo=print) -> list[tuple]:
    """``(pair or Missing, refinement, matcher)`` for every real pair under ``root``: the ADT pairs
    (refined) and, when scikit-image is installed, Middlebury's; ``matcher``: one of
    :data:`~.matchers.MATCHERS`, with the scene's settings (:func:`matcher_for`)."""
    adt = matcher_for(matcher, "adt")
    folder = Path(root) / "adt_slam"
    gone = [f for f in load_adt(folder) if isinstance(f, Missing)]
    out: list[tuple] = []
    if gone:
        out += [(m, None, None) for m in gone]
    else:
        T, refinement = refine_adt(folder)
        out += [(p, refinement, adt) for p in adt_pairs(folder, T)]
    if middlebury:
        try:
            out.append((motorcycle(), None, matcher_for(matcher, "middlebury")))
        except ImportError as err:
            echo(f"(Middlebury Motorcycle left out: {err})")
    return out


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
        f"| {_cell(d)} | {d['constant_abs_rel']} | {monocular} |"
    )


def multiview_records_table(paths) -> list[str]:
    """The stereo real-world table kept in records (JSON files with a ``multiview`` entry, as
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
        raise ValueError(f"{', '.join(map(str, paths))}: no run record with stereo scores")
    return lines


def multiview_scores(
    root: Path,
    predictions: dict[str, dict[str, Tensor]] | None = None,
    pictures: Path | None = None,
    echo=print,
    middlebury: bool = True,
    matcher: str = "sgbm",
) -> dict[str, Any]:
    """Stereo (``matcher``) on every real pair (:func:`real_pairs`), a table row each through ``echo``,
    beside each model of ``predictions`` (``{model: {frame: [H, W]}}``, as ``scripts/tools/real_world.py``
    passes them) scored on the same overlap pixels, and panels ``multiview_<frame>.png`` (image | checked
    | filled | ground truth) into ``pictures``. Returns the record: per frame, the scores, the settings and
    the refinement."""

    from ..files import atomic_write_png

    predictions = predictions or {}
    pairs = real_pairs(root, matcher, middlebury, echo)
    echo("")
    echo(HEADER)
    echo("|---|---|---|---|---|---|---|---|")
    record: dict[str, Any] = {}
    for pair, refinement, stereo in pairs:
        if isinstance(pair, Missing):
            record[pair.name] = {"missing": str(pair.path)}
            echo(f"| {pair.name} | missing: {pair.path} | | | | | | |")
            continue
        scored = overlap(pair)
        result, (checked, dense) = score_pair(pair, scored, stereo)
        truth = pair.distance
        result["refinement"] = refinement
        result["models"] = {
            model: score(frames[pair.name].to(truth), truth, scored)
            for model, frames in predictions.items()
            if pair.name in frames
        }
        settings = stereo.record()
        kept = ("matcher", "min_distance", "max_distance", "hypotheses", "cost")
        result["stereo"] = {k: settings[k] for k in kept if k in settings}
        record[pair.name] = result
        echo(multiview_row(pair.name, result))
        if pictures is not None:
            image = pair.image[0].permute(1, 2, 0).numpy()
            tiles = panel(image, checked, dense, truth.numpy())
            atomic_write_png(Path(pictures) / f"multiview_{pair.name}.png", tiles)
    refinement = next((r for _, r, _ in pairs if r), None)
    if refinement is not None:
        r = refinement
        echo(
            f"\nADT slam right relative to left, refined from {r['instants']} image pairs: turned "
            f"{r['rotation_deg']:.2f} degrees, median epipolar error {r['error_before_px']:.2f} -> "
            f"{r['error_after_px']:.2f} px ({r['inliers']} of {r['matches']} matches)"
        )
    return record
