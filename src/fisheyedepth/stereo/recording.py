"""The multi-view run behind ``fisheyedepth-multiview`` (:mod:`fisheyedepth.cli.multiview`, which says what
it writes): every image of a recording matched with its partners (:mod:`.pairing`), its maps fused and
written into a staging folder beside ``--out``, moved into place when the run completes; the inputs,
``--out`` and the memory the run needs checked before any work."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ..data.layouts import RigLayout
from ..files import (
    atomic_write_npy,
    atomic_write_png,
    atomic_write_text,
    check_apart,
    check_writable,
    drop_lock,
    move_into_place,
    staged_folder,
    take_lock,
)
from ..rerun3d import InstantRecorder, RecordingError
from .match import SgbmParameters, off_the_rim, textured
from .matchers import Matcher, RecordingMatches, check_run_memory
from .pairing import NO_PARTNER, SOURCES, Pairing, check_sources, images_left_out, nothing_to_match, pairings
from .pipeline import Timer, grey, nothing
from .rectify import RAYS
from .refine import REFINE, refine_rig, refined_rig_yaml
from .scores import panel, score

log = logging.getLogger("fisheyedepth")


OUTPUTS = ("distance", "dense", "confidence")  # the .npy maps of an image, beside its panel


def outputs(pairing: Pairing) -> list[Path]:
    """The files one image gets, relative to ``--out``."""
    stem = f"{pairing.camera}/{pairing.frame.key}"
    folder = Path(pairing.sequence)
    return [*(folder / what / f"{stem}.npy" for what in OUTPUTS), folder / "panels" / f"{stem}.png"]


def check_out(root: Path, out: Path) -> None:
    """``--out`` is a folder of its own: neither the recording, nor inside it (its ground truth lies at the
    outputs' own paths), nor around it, compared as resolved paths (links followed)."""
    check_apart(out, "--out", {"the recording": root})


def check_inputs(layout: RigLayout, paired: list[Pairing], progress: bool = True) -> None:
    """Every image the run reads (each image it matches and their partners) decoded and checked against
    its camera's size, and every ground-truth file checked
    (:meth:`~..data.layouts.RigLayout.read_distance`), before any output exists: a bad file is named
    before the first map is written, not after."""
    images = {}
    for pairing in paired:
        for camera, frame in (
            (pairing.camera, pairing.frame),
            *((p.camera, p.frame) for p in pairing.partners),
        ):
            images[pairing.sequence, camera, frame.key] = (pairing.sequence, camera, frame)
    for sequence, camera, frame in tqdm(images.values(), desc="checking images", unit="image",
                                        disable=not progress):  # fmt: skip
        layout.read_image(sequence, camera, frame)
    for pairing in paired:
        layout.read_distance(pairing.sequence, pairing.camera, pairing.frame)


def flat_fraction(image: np.ndarray, camera) -> float:
    """The share of the image's pixels whose matching window has no contrast (:func:`.match.textured`):
    nothing there can be matched, and the summary says so."""
    valid = RAYS.get(camera).valid.numpy()  # the rays its rectification took
    judged = off_the_rim(valid)
    if not judged.any():
        return 1.0
    flat = judged & ~textured(grey(image), valid, SgbmParameters.block)
    return round(float(flat.sum() / judged.sum()), 4)


@contextlib.contextmanager
def sole_writer(out: Path):
    """Hold ``.<out>.multiview.lock`` beside ``out`` while the block runs; a second run into the same
    ``out`` is refused by name, not interleaved."""
    lock = out.parent / f".{out.name}.multiview.lock"
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = take_lock(lock)
    except BlockingIOError:
        raise FileExistsError(
            f"--out: {out}: another fisheyedepth-multiview writes into it ({lock})"
        ) from None
    try:
        yield
    finally:
        drop_lock(fd, lock)


def run(
    root: str | Path,
    out: str | Path,
    matcher: Matcher,
    sources: tuple[str, ...] = SOURCES,
    overwrite: bool = False,
    progress: bool = True,
    max_images: int | None = None,
    refine: str | None = None,
    rerun: bool = False,
    bag_out: str | Path | None = None,
    source: str | Path | None = None,
) -> dict[str, Any]:
    """The command's work: every pairing of ``root`` matched (``matcher``: a :class:`~.matchers.Matcher`,
    :class:`.sgbm.SgbmMatcher` or :class:`.sweep.SweepMatcher`), its outputs and
    ``summary.json`` in ``out``; with ``refine`` (:data:`.refine.REFINE`) the rig's extrinsics are refined
    from its images first (:func:`.refine.refine_rig`), matched with, and written to ``out/rig.yaml``. The
    recording is never modified. Before any work: ``out`` is a folder of its own that can be written, no
    file the run would write exists there (unless ``overwrite``), and no other run writes into it; the
    outputs are written into a staging folder beside ``out`` and put in place when the run completes
    (``summary.json`` last), so an interrupted or refused run leaves nothing in ``out``. With ``bag_out``,
    the outputs as ROS 2 messages too (:class:`~..rosout.BagRecorder`), the bag put in place last.
    ``source``: what ``root`` was made from (a ROS bag imported for the run), named in the summary."""
    layout, out = RigLayout(root), Path(out)
    check_sources(sources)
    if refine is not None and refine not in REFINE:
        raise ValueError(f"--refine: {refine!r}; choose from {', '.join(REFINE)}")
    check_out(layout.root, out)
    check_writable(out, "--out")
    if bag_out is not None:
        from ..rosout import check_bag_out

        check_apart(bag_out, "--bag-out", {"the recording": layout.root, "--out": out})
        check_bag_out(bag_out, overwrite)
    planned = pairings(layout, sources, min_baseline=matcher.min_baseline)
    planned.sort(key=lambda p: (p.sequence, p.frame.key, p.camera))  # instant by instant: pairs freed soon
    paired = [p for p in planned if p.partners]
    left_out = images_left_out(layout, planned)
    left_out.update(
        {p.name: f"beyond --max-images {max_images}" for p in paired[max_images or len(paired) :]}
    )
    paired = paired[:max_images]
    if not paired:
        raise ValueError(f"{root}: no image to match: {nothing_to_match(layout, sources, left_out)}")
    check_run_memory(layout, matcher)
    parts = [path for pairing in paired for path in outputs(pairing)]
    parts += [Path("rig.yaml")] if refine else []
    parts += [Path(RECORDING)] if rerun else []
    parts += [Path("summary.json")]
    if rerun:
        from ..rerun3d import import_rerun

        try:
            import_rerun()  # the viz extra, before any work
        except ImportError as err:
            raise ValueError(f"--rerun: {err}") from None
    taken = next((out / part for part in parts if os.path.lexists(out / part)), None)
    folder = next((out / p for p in parts if (out / p).is_dir() and not (out / p).is_symlink()), None)
    if folder is not None:  # --overwrite replaces the run's files, never a folder and what it holds
        raise FileExistsError(f"--out: {folder} is a folder where the run writes a file; move it away")
    if taken is not None and not overwrite:
        raise FileExistsError(f"{taken} exists; pass --overwrite to replace the outputs")
    check_inputs(layout, paired, progress)
    with sole_writer(out):
        remove_stale_staging(out)
        with _bag(layout, bag_out, overwrite) as bag, staged_folder(out, "multiview") as staging:
            try:
                summary = _work(layout, staging, matcher, sources, paired, left_out, refine, progress, rerun,
                                bag)  # fmt: skip
            except RecordingError as err:  # named where it was to be, not in the staging folder
                raise RecordingError(out / RECORDING, err.why) from None
            summary["root"] = str(source or root)
            if bag is not None:
                summary["bag_out"] = {"path": str(bag_out), "messages": bag.writer.count}
            atomic_write_text(staging / "summary.json", json.dumps(summary, indent=2) + "\n")
            move_into_place(staging, out, parts, overwrite)
    return summary


@contextlib.contextmanager
def _bag(layout: RigLayout, bag_out, overwrite: bool):
    """The run's :class:`~..rosout.BagRecorder` (None without ``bag_out``): its bag put in place when the
    block completes, removed when it fails."""
    if bag_out is None:
        yield None
        return
    from ..rosout import BagRecorder, BagWriter

    cameras = {name: spec.camera for name, spec in layout.cameras.items()}
    rig = {name: spec.cam_to_body for name, spec in layout.cameras.items()}
    with BagWriter(bag_out, overwrite) as writer:
        yield BagRecorder(writer, cameras, rig, layout.topics, layout.frame_ids)


def remove_stale_staging(out: Path) -> None:
    """The staging folders a killed run left beside ``out`` (``SIGKILL`` runs no clean-up): while this
    run holds ``out``'s lock no other run is writing them, so they are removed, and said so."""
    import shutil

    prefix = f".{out.name}.multiview-"  # compared as text: a name with [ or * is no pattern here
    for stale in out.parent.iterdir():
        if stale.name.startswith(prefix) and stale.is_dir():
            log.warning("removing %s, left by an interrupted run", stale)
            shutil.rmtree(stale, ignore_errors=True)


RECORDING = "recording.rrd"


def _work(layout, out, matcher, sources, paired, left_out, refine, progress, rerun=False,
          bag=None) -> dict[str, Any]:  # fmt: skip
    """The matching itself: every output of ``paired`` written into ``out`` (with ``rerun``, the 3-D
    recording too: :class:`InstantRecorder`); the summary, returned."""
    begun = time.perf_counter()
    recorded_rig = {name: spec.cam_to_body.copy() for name, spec in layout.cameras.items()}
    refinement = None
    if refine:
        refinement = refine_rig(layout, refine)
        for name, change in refinement["cameras"].items():
            if "rotation_deg" not in change:  # the fit itself failed
                log.info("%s not refined against %s: %s", name, change["relative_to"], change["why"])
                continue
            c = change
            log.info("%s refined against %s: %.3f degrees (%.3f bounded); epipolar error %.2f -> %.2f px "
                     "(%d inliers): %s (%s)", name, c["relative_to"], c["rotation_deg"],
                     c["bounded_rotation_deg"], c["epipolar_px_before"], c["epipolar_px_after"],
                     c["inliers"], "applied" if c["applied"] else "not applied", c["why"])  # fmt: skip
        if refinement["unrefined"]:
            log.warning("not refined (too few matches with the other cameras): %s", refinement["unrefined"])
        atomic_write_text(out / "rig.yaml", refined_rig_yaml(layout))
    refine_seconds = time.perf_counter() - begun
    unpaired = [name for name, why in left_out.items() if why == NO_PARTNER]
    if unpaired:
        log.warning("%d images have no partner and are left out: %s", len(unpaired), ", ".join(unpaired[:5]))
    timer = Timer()
    matches = matcher.recording(layout, paired, timer)
    images = []
    recorder = InstantRecorder(out / RECORDING, layout, recorded_rig, refinement) if rerun else None
    with recorder or contextlib.nullcontext():
        bar = tqdm(paired, desc=f"stereo ({matcher.name})", unit="image", disable=not progress)
        for pairing in bar:
            images.append(_image(layout, pairing, matches, out, recorder, bag))
    seconds = time.perf_counter() - begun
    return {
        "root": None,
        "sources": list(sources),
        "settings": matcher.record(),
        "refinement": refinement,
        "images": images,
        "images_left_out": left_out,
        **matches.record(),  # static, pairs, pairs_left_out
        "kept_nothing": [r["image"] for r in images if not r["kept_pixels"]],
        "seconds": {
            "total": round(seconds, 3),
            "refine": round(refine_seconds, 3),
            **timer.rounded(),
            "per_image": round((seconds - refine_seconds) / max(len(images), 1), 4),
        },  # fmt: skip
    }


def _image(layout, pairing, matches: RecordingMatches, out, recorder, bag=None) -> dict[str, Any]:
    """One image's maps (against its partners) written into ``out``; its summary record, returned."""
    start = time.perf_counter()
    image = layout.read_image(pairing.sequence, pairing.camera, pairing.frame)
    fused, used, disagree = matches.image(pairing, image)
    if fused is None:  # every partner left out: nothing to say about this image
        fused = nothing(layout.cameras[pairing.camera].camera)
    *maps, picture = outputs(pairing)
    for path, array in zip(maps, (fused.distance, fused.dense, fused.confidence), strict=True):
        atomic_write_npy(out / path, array)
    truth = layout.read_distance(pairing.sequence, pairing.camera, pairing.frame)
    tiles = panel(image[..., ::-1], fused.distance, fused.dense, truth)
    atomic_write_png(out / picture, tiles)
    record: dict[str, Any] = {
        "image": pairing.name,
        "partners": [f"{p.camera}/{p.frame.key}" for p in used],
        "partners_disagreeing": disagree,
        "flat": flat_fraction(image, layout.cameras[pairing.camera].camera),
        "kept": round(float((fused.distance > 0).mean()), 4),
        "kept_pixels": int((fused.distance > 0).sum()),
        "seen": round(float((fused.dense > 0).mean()), 4),
    }
    if truth is not None:
        seen = fused.dense > 0
        record["checked"] = score(fused.distance, truth, seen)
        record["dense"] = score(fused.dense, truth, seen)
    record["seconds"] = round(time.perf_counter() - start, 4)
    if recorder is not None:
        recorder.add(pairing, image, fused, truth, record)
    if bag is not None:
        bag.add(
            pairing.camera, pairing.frame.key, image, fused.distance, fused.confidence, pairing.frame.pose
        )
    return record
