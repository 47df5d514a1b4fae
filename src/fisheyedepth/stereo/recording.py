"""The multi-view run behind ``fisheyedepth-multiview`` (:mod:`fisheyedepth.cli.multiview`, which says what
it writes): every image of a recording matched with its partners (:mod:`.pairing`), its maps fused and
written into a staging folder beside ``--out``, moved into place when the run completes; the inputs,
``--out`` and the memory the run needs checked before any work."""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from ..data.dataset import binary_mask, read_distance
from ..data.layouts import Frame, RigLayout
from ..option_checks import check_memory
from ..rerun3d import InstantRecorder, RecordingError
from ..utils import (
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
from .fuse import Fused, fuse
from .mapback import PixelMaps
from .match import MatcherSettings, off_the_rim, textured
from .pairing import NO_PARTNER, SOURCES, Pairing, check_sources, images_left_out, nothing_to_match, pairings
from .pipeline import StereoSettings, Timer, grey, match_pair, nothing, pair_step, partner_pair
from .rectify import RAYS, Rectification, RectificationCache
from .refine import (
    MOTION_FEATURES,
    REFINE,
    Features,
    check_motion,
    features,
    layout_image,
    refine_rig,
    refined_rig_yaml,
)
from .scores import panel, score
from .static import StaticFinder, usable
from .sweep import SweepStereo, View

log = logging.getLogger("fisheyedepth")
MATCHERS = ("sgbm", "sweep")


def _truth(layout: RigLayout, pairing: Pairing) -> np.ndarray | None:
    path = layout.distance(pairing.sequence, pairing.camera, pairing.frame)
    if path is None:
        return None
    camera = layout.cameras[pairing.camera].camera
    return read_distance(path, camera)


def masks(layout: RigLayout) -> dict[str, np.ndarray | None]:
    """Each camera's body mask (``H x W`` bool, True: the scene), None where the rig names none."""
    out = {}
    for name, spec in layout.cameras.items():
        size = (spec.camera.width, spec.camera.height)
        out[name] = (
            None if spec.mask is None else binary_mask(spec.mask, size, size, "body mask")[0].numpy() > 0.5
        )
    return out


def static_masks(layout: RigLayout, max_distance: float, pairs: int = 12) -> dict[str, np.ndarray]:
    """Each camera's pixels that do not move with the scene (:class:`.static.StaticFinder`), from up to
    ``pairs`` pairs of its consecutive images spread over the recording (every sequence)."""
    out = {}
    for name, spec in layout.cameras.items():
        finder = StaticFinder(spec.camera, max_distance)
        found = []
        for sequence in layout.sequences():
            frames = layout.frames(sequence, name)
            found += [(sequence, a, b) for a, b in zip(frames, frames[1:], strict=False)]
        for sequence, a, b in found[:: max(1, len(found) // pairs)][:pairs]:
            images = [layout_image(layout, sequence, name, frame) for frame in (a, b)]
            finder.add(grey(images[0]), grey(images[1]), _T(layout, name, a, name, b))
        out[name] = finder.mask
    return out


def _T(
    layout: RigLayout,
    camera_a: str,
    frame_a: Frame,
    camera_b: str,
    frame_b: Frame,
    same_instant_ns: int = 1_000_000,
) -> np.ndarray:
    """``T_a_to_b`` of two images: each camera's extrinsics and each instant's body pose. Two cameras of
    one instant (within ``same_instant_ns``) are a rig pair: their extrinsics alone, so that its
    rectification is built once (the body moves 0.4 mm in a millisecond at 0.4 m/s)."""
    if camera_a != camera_b and abs(frame_a.key - frame_b.key) <= same_instant_ns:
        return np.linalg.inv(layout.cameras[camera_b].cam_to_body) @ layout.cameras[camera_a].cam_to_body
    world_a = frame_a.pose @ layout.cameras[camera_a].cam_to_body
    world_b = frame_b.pose @ layout.cameras[camera_b].cam_to_body
    return np.linalg.inv(world_b) @ world_a


class PairStore:
    """The recording's pairs through the rectified pipeline: each pair of images matched once, for the
    images of the pair that ask for it (``pairings``: one, or both), and kept until they have taken
    their maps."""

    def __init__(self, layout: RigLayout, settings: StereoSettings, timer: Timer, pairings: list[Pairing]):
        self.layout, self.settings, self.timer = layout, settings, timer
        start = time.perf_counter()
        self.static = static_masks(layout, settings.max_distance)
        self.masks = {name: usable(mask, self.static[name]) for name, mask in masks(layout).items()}
        timer.add("motion", start)
        self.rectifications = RectificationCache(max_entries=64)
        self.wanted: dict[tuple, set[tuple[str, int]]] = defaultdict(set)  # pair -> the images asking
        for pairing in pairings:
            for partner in pairing.partners:
                key, _, _ = self._key(
                    pairing.sequence, (pairing.camera, pairing.frame), (partner.camera, partner.frame)
                )
                self.wanted[key].add((pairing.camera, pairing.frame.key))
        self.maps: dict[tuple, dict[tuple, PixelMaps | None]] = {}
        self.unmatched: dict[str, str] = {}  # pair name -> why no map (no overlap, too short a baseline,
        # a motion its images do not explain, images that contradict the pair's geometry)
        # pair name -> its evidence (round trip, rows, a motion's residuals)
        self.checks: dict[str, dict] = {}
        self.described: dict[tuple, Features] = {}

    @staticmethod
    def _key(sequence: str, one: tuple[str, Frame], other: tuple[str, Frame]) -> tuple:
        a, b = sorted((one, other), key=lambda x: (x[1].key, x[0]))  # the earlier image is camera a
        return (sequence, a[0], a[1].key, b[0], b[1].key), a, b

    def get(self, sequence: str, own: tuple[str, Frame], other: tuple[str, Frame]) -> PixelMaps | None:
        """``own``'s maps against ``other`` (None where the pair is left out)."""
        key, a, b = self._key(sequence, own, other)
        if key not in self.maps:
            self.maps[key] = self._match(sequence, a, b, self.wanted.pop(key, {(own[0], own[1].key)}))
        entry = self.maps[key]
        found = entry.pop((own[0], own[1].key), None)
        if not entry:
            del self.maps[key]
        return found

    def _match(self, sequence: str, a: tuple[str, Frame], b: tuple[str, Frame], wanted: set) -> dict:
        layout, s = self.layout, self.settings
        sides = (a[0], a[1].key), (b[0], b[1].key)
        directions = tuple(side in wanted for side in sides)
        name = f"{sequence}: {a[0]}/{a[1].key} ~ {b[0]}/{b[1].key}"
        nothing_here = {side: None for side, want in zip(sides, directions, strict=True) if want}
        start = time.perf_counter()
        T = _T(layout, a[0], a[1], b[0], b[1])
        cameras = layout.cameras[a[0]].camera, layout.cameras[b[0]].camera
        residual, record, images = 0.0, {}, None
        if a[0] == b[0]:  # one camera at two instants: its motion checked against its images first
            images = [layout_image(layout, sequence, cam, frame) for cam, frame in (a, b)]
            found = [
                self._features(sequence, cam, frame, image)
                for (cam, frame), image in zip((a, b), images, strict=True)
            ]
            verdict = check_motion(found[0], cameras[0], found[1], cameras[1], T)
            record = verdict.record()
            start = self.timer.add("motion", start)
            if verdict.left_out is not None:
                self.checks[name] = record
                self.unmatched[name] = verdict.left_out
                return nothing_here
            T, residual = verdict.T_a_to_b, verdict.residual
        rect = partner_pair(*cameras, T, s, directions, self.rectifications)
        if not isinstance(rect, Rectification):  # left out, and why
            self.unmatched[name] = rect
            return nothing_here
        self.timer.add("rectify", start)
        images = images or [layout_image(layout, sequence, cam, frame) for cam, frame in (a, b)]
        pair_masks = (self.masks[a[0]], self.masks[b[0]])
        maps = match_pair(images[0], images[1], rect, s, directions, self.timer, pair_masks, residual)
        evidence = next(m.evidence for m in maps if m is not None)
        self.checks[name] = {**record, **evidence.record()}
        if evidence.contradicted:
            self.unmatched[name] = evidence.contradicted
            return nothing_here
        return {side: m for side, m, want in zip(sides, maps, directions, strict=True) if want}

    def _features(self, sequence: str, camera: str, frame: Frame, image: np.ndarray) -> Features:
        """An image's SIFT features, kept for the next pair it is in (the time pairs on its two sides)."""
        key = (sequence, camera, frame.key)
        if key not in self.described:
            self.described[key] = features(grey(image), MOTION_FEATURES)
            while len(self.described) > 4 * len(self.layout.cameras):
                self.described.pop(next(iter(self.described)))
        return self.described[key]


def _sweep(layout: RigLayout, pairing: Pairing, sweep: SweepStereo, image: np.ndarray) -> Fused:
    """The sweep for one pairing (its image the reference, its partners the sources)."""
    device = "cuda" if torch.cuda.is_available() else "cpu"

    def tensor(bgr: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(bgr[..., ::-1].copy()).permute(2, 0, 1)[None].float().to(device) / 255

    own = layout.cameras[pairing.camera].camera
    reference = View(tensor(image), own, torch.eye(4, device=device))
    sources = []
    for partner in pairing.partners:
        T = _T(layout, pairing.camera, pairing.frame, partner.camera, partner.frame)
        partner_image = layout_image(layout, pairing.sequence, partner.camera, partner.frame)
        sources.append(View(tensor(partner_image), layout.cameras[partner.camera].camera,
                            torch.from_numpy(T).float().to(device)))  # fmt: skip
    result = sweep(reference, sources)
    distance, dense, confidence = (
        x[0].cpu().numpy() for x in (result.distance, result.dense, result.confidence)
    )
    return Fused(distance, dense, np.where(distance > 0, confidence, 0).astype(np.float32),
                 (distance > 0).astype(np.uint8))  # fmt: skip


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


# Peak memory of matching one pair: a fixed part and a part per pixel of its larger image at the cameras'
# own resolution (the rays, the rectification's tables, both rectified images, SGBM's buffers and the
# maps back). Measured 44 MiB at 256 px, 148-172 MiB at 512, 509-518 at 1024 and about 1.9 GiB at 2048
# (scripts/bench/bench_stereo_memory.py; tests/test_multiview.py checks a 512 px pair against it): each
# 0.9 of this bound or less.
MEMORY_BASE = 64 * 2**20
MEMORY_PER_PIXEL = 512
SWEEP_MEMORY_PER_VOXEL = 20  # the sweep's cost sums, counts and volume (float32) and a chunk's warps


def pair_memory(pixels: float) -> float:
    """Bytes one pair of images of ``pixels`` pixels needs at its peak (:data:`MEMORY_PER_PIXEL`)."""
    return MEMORY_BASE + MEMORY_PER_PIXEL * pixels


def check_run_memory(layout: RigLayout, matcher: StereoSettings | SweepStereo) -> None:
    """Refuse, before any work, a run whose largest image would need more memory than the machine has
    (:func:`~fisheyedepth.option_checks.check_memory`), naming the camera (or the option) and both numbers."""
    name, spec = max(layout.cameras.items(), key=lambda kv: kv[1].camera.width * kv[1].camera.height)
    pixels, size = spec.camera.width * spec.camera.height, f"{spec.camera.width}x{spec.camera.height}"
    if isinstance(matcher, StereoSettings):
        scale = 1.0
        if matcher.resolution is not None:  # a finer grid than the camera's own
            scale = max(1.0, (pair_step(spec.camera, spec.camera, None) / matcher.resolution) ** 2)
        what = f"{MEMORY_BASE // 2**20} MiB + {MEMORY_PER_PIXEL} bytes a pixel of a pair"
        if scale > 1:
            what += f", x {scale:.3g} at --resolution {math.degrees(matcher.resolution):g} degrees"
        where = f"{layout.root / 'rig.yaml'}: camera {name!r}"
        check_memory(where, size, pair_memory(pixels * scale), what)
    else:
        need = SWEEP_MEMORY_PER_VOXEL * matcher.hypotheses * pixels
        what = f"{SWEEP_MEMORY_PER_VOXEL} bytes x hypotheses x camera {name!r}'s {size} pixels"
        check_memory("--hypotheses", matcher.hypotheses, need, what)


def check_inputs(layout: RigLayout, paired: list[Pairing], progress: bool = True) -> None:
    """Every image the run reads (each image it matches and their partners) decoded and checked against
    its camera's size, and every ground-truth file checked (:func:`~..data.dataset.read_distance`), before
    any output exists: a bad file is named before the first map is written, not after."""
    images = {}
    for pairing in paired:
        for camera, frame in (
            (pairing.camera, pairing.frame),
            *((p.camera, p.frame) for p in pairing.partners),
        ):
            images[pairing.sequence, camera, frame.key] = (pairing.sequence, camera, frame)
    for sequence, camera, frame in tqdm(images.values(), desc="checking images", unit="image",
                                        disable=not progress):  # fmt: skip
        layout_image(layout, sequence, camera, frame)
    for pairing in paired:
        _truth(layout, pairing)


def flat_fraction(image: np.ndarray, camera) -> float:
    """The share of the image's pixels whose matching window has no contrast (:func:`.match.textured`):
    nothing there can be matched, and the summary says so."""
    valid = RAYS.get(camera).valid.numpy()  # the rays its rectification took
    judged = off_the_rim(valid)
    if not judged.any():
        return 1.0
    flat = judged & ~textured(grey(image), valid, MatcherSettings.block)
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
    matcher: SweepStereo | StereoSettings,
    sources: tuple[str, ...] = SOURCES,
    overwrite: bool = False,
    progress: bool = True,
    max_images: int | None = None,
    refine: str | None = None,
    rerun: bool = False,
) -> dict[str, Any]:
    """The command's work: every pairing of ``root`` matched (``matcher``: :class:`.pipeline.StereoSettings`
    for the rectified pipeline, a :class:`.sweep.SweepStereo` for the sweep), its outputs and
    ``summary.json`` in ``out``; with ``refine`` (:data:`.refine.REFINE`) the rig's extrinsics are refined
    from its images first (:func:`.refine.refine_rig`), matched with, and written to ``out/rig.yaml``. The
    recording is never modified. Before any work: ``out`` is a folder of its own that can be written, no
    file the run would write exists there (unless ``overwrite``), and no other run writes into it; the
    outputs are written into a staging folder beside ``out`` and put in place when the run completes
    (``summary.json`` last), so an interrupted or refused run leaves nothing in ``out``."""
    layout, out = RigLayout(root), Path(out)
    check_sources(sources)
    if refine is not None and refine not in REFINE:
        raise ValueError(f"--refine: {refine!r}; choose from {', '.join(REFINE)}")
    check_out(layout.root, out)
    check_writable(out, "--out")
    min_baseline = (
        matcher.min_baseline if isinstance(matcher, StereoSettings) else StereoSettings.min_baseline
    )
    planned = pairings(layout, sources, min_baseline=min_baseline)
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
        with staged_folder(out, "multiview") as staging:
            try:
                summary = _work(layout, staging, matcher, sources, paired, left_out, refine, progress, rerun)
            except RecordingError as err:  # named where it was to be, not in the staging folder
                raise RecordingError(out / RECORDING, err.why) from None
            summary["root"] = str(root)
            atomic_write_text(staging / "summary.json", json.dumps(summary, indent=2) + "\n")
            move_into_place(staging, out, parts, overwrite)
    return summary


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


def _work(layout, out, matcher, sources, paired, left_out, refine, progress, rerun=False) -> dict[str, Any]:
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
    store = PairStore(layout, matcher, timer, paired) if isinstance(matcher, StereoSettings) else None
    images = []
    recorder = InstantRecorder(out / RECORDING, layout, recorded_rig, refinement) if rerun else None
    with recorder or contextlib.nullcontext():
        bar = tqdm(
            paired, desc=f"stereo ({'sgbm' if store else 'sweep'})", unit="image", disable=not progress
        )
        for pairing in bar:
            images.append(_image(layout, pairing, matcher, store, timer, out, recorder))
    seconds = time.perf_counter() - begun
    if isinstance(matcher, StereoSettings):
        settings = {"matcher": "sgbm", **{k: getattr(matcher, k) for k in ("min_distance", "max_distance",
                    "resolution", "min_baseline", "smooth", "max_disparities", "min_confidence")},
                    **vars(matcher.matcher)}  # fmt: skip
    else:
        settings = {"matcher": "sweep", **{k: getattr(matcher, k) for k in matcher.__dataclass_fields__}}
    return {
        "root": None,
        "sources": list(sources),
        "settings": settings,
        "refinement": refinement,
        "images": images,
        "images_left_out": left_out,
        "static": {n: round(float(m.mean()), 4) for n, m in store.static.items()}
        if store is not None
        else {},
        "pairs": store.checks if store is not None else {},
        "pairs_left_out": store.unmatched if store is not None else {},
        "kept_nothing": [r["image"] for r in images if not r["kept_pixels"]],
        "seconds": {
            "total": round(seconds, 3),
            "refine": round(refine_seconds, 3),
            **timer.rounded(),
            "per_image": round((seconds - refine_seconds) / max(len(images), 1), 4),
        },  # fmt: skip
    }


def _image(layout, pairing, matcher, store, timer, out, recorder) -> dict[str, Any]:
    """One image's maps (against its partners) written into ``out``; its summary record, returned."""
    start = time.perf_counter()
    image = layout_image(layout, pairing.sequence, pairing.camera, pairing.frame)
    own = (pairing.camera, pairing.frame)
    disagree: dict[str, str] = {}
    if store is not None:
        found = [(p, store.get(pairing.sequence, own, (p.camera, p.frame))) for p in pairing.partners]
        used = [(p, m) for p, m in found if m is not None]
        fuse_start = time.perf_counter()
        fused = fuse([m for _, m in used], matcher.min_confidence) if used else None
        timer.add("fuse", fuse_start)
        if fused is not None:  # partners whose distances disagree with the others': named, not fused
            disagree = {
                f"{used[k][0].camera}/{used[k][0].frame.key}": why for k, why in fused.left_out.items()
            }
            used = [pm for k, pm in enumerate(used) if k not in fused.left_out]
    else:
        used = [(p, None) for p in pairing.partners]
        fused = _sweep(layout, pairing, matcher, image)
    if fused is None:  # every partner left out: nothing to say about this image
        fused = nothing(layout.cameras[pairing.camera].camera)
    *maps, picture = outputs(pairing)
    for path, array in zip(maps, (fused.distance, fused.dense, fused.confidence), strict=True):
        atomic_write_npy(out / path, array)
    truth = _truth(layout, pairing)
    tiles = panel(image[..., ::-1], fused.distance, fused.dense, truth)
    atomic_write_png(out / picture, tiles)
    record: dict[str, Any] = {
        "image": pairing.name,
        "partners": [f"{p.camera}/{p.frame.key}" for p, _ in used],
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
    return record
