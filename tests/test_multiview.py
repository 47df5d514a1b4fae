"""The multi-view command on recordings (``fisheyedepth-multiview``, both matchers): a rig's rotation
refined from its images' feature matches, the command on a rig recording in a textured room with exact
ground truth, and a real rectified pair (Middlebury 2014 Motorcycle)."""

from __future__ import annotations

import functools
import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

from fisheyedepth.cameras import PinholeCamera
from fisheyedepth.cameras.rays import compute_rays
from fisheyedepth.geometry.se3 import axis_angle_to_matrix, invert_pose, make_pose
from fisheyedepth.stereo import SweepMatcher, SweepSettings, View
from fisheyedepth.stereo.features import Matches, match_features
from fisheyedepth.stereo.refine import refine_relative_pose
from stereo_world import pose, render, scores, texture_volume

from conftest import bare_module, kitti02, load_script, realdata_dir


# ------------------------------------------------------------------ the rig refined from its images
def rotation_between_deg(T_a: torch.Tensor, T_b: torch.Tensor) -> float:
    cos = ((torch.trace(T_a[:3, :3] @ T_b[:3, :3].T) - 1) / 2).clamp(-1, 1)
    return math.degrees(float(torch.acos(cos)))


@functools.cache
def refine_rig() -> tuple:
    """Two KITTI-360 fisheyes at 384 px, 0.2 m apart and turned 15 degrees, their SIFT matches, and the
    true pose between them."""
    camera = kitti02().resize(384, 384)
    T_b = pose(15.0, (0.2, 0.0, 0.0))
    image_a, _ = render(camera, pose(), texture_volume(0))
    image_b, _ = render(camera, T_b, texture_volume(0))
    matches = match_features(image_a, camera, image_b, camera)
    return camera, matches, invert_pose(T_b) @ pose()


@pytest.mark.parametrize("degrees", [1.0, 2.0])
@pytest.mark.parametrize("direction", [True, False])
def test_a_rig_turned_by_one_or_two_degrees_is_recovered(degrees, direction):
    camera, matches, T_true = refine_rig()
    axis = torch.tensor([0.3, -0.8, 0.5], dtype=torch.float64)
    turn = axis_angle_to_matrix(axis / axis.norm() * math.radians(degrees))
    start = make_pose(turn @ T_true[:3, :3], turn @ T_true[:3, 3])  # b turned about its centre
    refined = refine_relative_pose(matches, start, float(camera.paraxial_focal()[0]), direction=direction)
    assert rotation_between_deg(refined.T_a_to_b, T_true) < 0.05
    assert refined.rotation_deg == pytest.approx(degrees, abs=0.05)
    assert refined.error_before_px > 0.8 * degrees and refined.error_after_px < 0.2  # pixels of camera b
    assert float(refined.T_a_to_b[:3, 3].norm()) == pytest.approx(0.2, rel=1e-9)  # the baseline's length kept
    assert refined.inliers > 0.9 * refined.matches > 1000


def test_a_correct_rig_is_left_as_it_is():
    camera, matches, T_true = refine_rig()
    refined = refine_relative_pose(matches, T_true, float(camera.paraxial_focal()[0]))
    assert refined.rotation_deg < 0.02 and rotation_between_deg(refined.T_a_to_b, T_true) < 0.02


def test_too_few_matches_or_no_baseline_are_refused():
    camera, matches, T_true = refine_rig()
    few = Matches(matches.rays_a[:5], matches.rays_b[:5], matches.uv_a[:5], matches.uv_b[:5])
    with pytest.raises(ValueError, match="matches: 5 feature matches; at least 8 are needed"):
        refine_relative_pose(few, T_true, 100.0)
    with pytest.raises(ValueError, match="T_a_to_b: the baseline has no length"):
        refine_relative_pose(matches, make_pose(T_true[:3, :3], torch.zeros(3)), 100.0)


# ------------------------------------------------------------------ the command on a recording
def write_room_rig(
    root: Path,
    size: int = 96,
    stamps=(1_000_000_000, 1_100_000_000, 1_200_000_000),
    calibrated: dict | None = None,
    half_baseline: float = 0.1,
) -> dict:
    """A rig layout in the textured room: cameras ``left`` and ``right`` ``2 half_baseline`` apart, turned
    20 degrees apart, moving 0.15 m forward per frame, with exact distance maps; and ``lonely``, whose one
    image is taken between the others' instants. ``calibrated``: cam_to_body written to rig.yaml in place
    of the true one, by camera."""
    camera = kitti02().resize(size, size)
    extrinsics = {
        "left": pose(-10.0, (-half_baseline, 0.0, 0.0)),
        "right": pose(10.0, (half_baseline, 0.0, 0.0)),
    }
    written = {**extrinsics, **(calibrated or {})}
    entries = [{"name": n, "model": camera.to_dict(), "cam_to_body": E.tolist()} for n, E in written.items()]
    entries.append({"name": "lonely", "model": camera.to_dict(), "cam_to_body": np.eye(4).tolist()})
    (root / "seq").mkdir(parents=True)
    (root / "rig.yaml").write_text(yaml.safe_dump({"cameras": entries}))
    poses = {t: pose(0.0, (0.0, 0.0, 0.15 * i)) for i, t in enumerate(stamps)}
    (root / "seq" / "poses.txt").write_text(
        "".join(f"{t} 0 0 {0.15 * i} 0 0 0 1\n" for i, t in enumerate(stamps))
    )
    for name, E in extrinsics.items():
        for t, P in poses.items():
            image, distance = render(camera, P @ E, texture_volume(0))
            (root / "seq" / "images" / name).mkdir(parents=True, exist_ok=True)
            (root / "seq" / "distance" / name).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(
                str(root / "seq" / "images" / name / f"{t}.png"),
                (image[0, 0].numpy() * 255).round().astype(np.uint8),
            )
            np.save(root / "seq" / "distance" / name / f"{t}.npy", distance[0].numpy())
    lonely = root / "seq" / "images" / "lonely"
    lonely.mkdir(parents=True)
    cv2.imwrite(str(lonely / f"{stamps[0] + 50_000_000}.png"), np.zeros((size, size), np.uint8))
    return {"stamps": stamps, "camera": camera, "extrinsics": extrinsics}


def test_the_multiview_command_on_a_rig_recording(tmp_path, capsys):
    """The rectified pipeline by default: every image with the rig's other camera and its own camera's
    previous and next images, each pair matched once, the partners fused; the seconds of each image and
    of each stage in the summary."""
    from fisheyedepth.cli.multiview import main
    from fisheyedepth.stereo.pairing import NO_PARTNER

    rig = write_room_rig(tmp_path / "rec", size=192)
    out = tmp_path / "out"
    args = [str(tmp_path / "rec"), "--out", str(out), "--min-distance", "0.5", "--max-distance", "20",
            "--threads", "1", "--quiet"]  # fmt: skip
    assert main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    t0, t1, t2 = rig["stamps"]
    assert summary["images_left_out"] == {f"seq/lonely/{t0 + 50_000_000}": NO_PARTNER}
    records = {r["image"]: r for r in summary["images"]}
    assert records[f"seq/left/{t0}"]["partners"] == [f"right/{t0}", f"left/{t1}"]  # the rig, then later
    assert records[f"seq/left/{t1}"]["partners"] == [f"right/{t1}", f"left/{t0}", f"left/{t2}"]  # both sides
    for record in summary["images"]:  # the pixels it can resolve at 192 px (an estimate no other partner
        # corroborates needs 8 pixels of parallax), at 3 % of their distance
        assert record["checked"]["abs_rel"] < 0.05 and record["checked"]["coverage"] > 0.45, record
        assert record["checked"]["abs_rel"] < 0.2 * record["checked"]["constant_abs_rel"], record
        assert record["dense"]["abs_rel"] < 0.15 and 0 < record["seconds"] < 30, record
    seconds = summary["seconds"]
    stages = {"motion", "rectify", "match", "fill", "map_back", "fuse"}
    assert set(seconds) == {"total", "refine", "per_image", *stages}
    assert seconds["match"] > 0 and seconds["per_image"] > 0 and summary["settings"]["matcher"] == "sgbm"
    distance = np.load(out / "seq" / "distance" / "left" / f"{t0}.npy")
    dense = np.load(out / "seq" / "dense" / "left" / f"{t0}.npy")
    confidence = np.load(out / "seq" / "confidence" / "left" / f"{t0}.npy")
    assert distance.dtype == np.float32 and distance.shape == (192, 192)
    assert ((distance == 0) | (distance == dense)).all() and (dense > 0).sum() >= (distance > 0).sum() > 0
    assert ((confidence > 0) == (distance > 0)).all() and confidence.max() <= 1
    assert cv2.imread(str(out / "seq" / "panels" / "left" / f"{t0}.png")).shape == (192, 4 * 192, 3)

    assert main(args) == 2  # the outputs exist: replaced only with --overwrite
    first = out / "seq" / "distance" / "left" / f"{t0}.npy"  # the first file the run would write
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"error: {first} exists; pass --overwrite to replace the outputs"
    )
    assert main([*args[:3], "--sources", "rig,gps", "--quiet"]) == 2
    assert "--sources: 'rig,gps'; choose from rig,time" in capsys.readouterr().err
    assert main([*args[:3], "--threads", "0", "--quiet"]) == 2
    assert "--threads: 0; a whole number from 1 to" in capsys.readouterr().err
    assert main([*args[:3], "--max-images", "-1", "--quiet"]) == 2  # not Python's [:-1]
    assert "--max-images: -1; at least 1" in capsys.readouterr().err
    assert main([*args[:3], "--hypotheses", "64", "--quiet"]) == 2  # the sweep's option, not ignored
    assert "--hypotheses: an option of --matcher sweep, not sgbm" in capsys.readouterr().err
    assert main([*args[:3], "--matcher", "sweep", "--resolution", "0.5", "--quiet"]) == 2
    assert "--resolution: an option of --matcher sgbm, not sweep" in capsys.readouterr().err
    assert main([*args[:3], "--min-confidence", "1.5", "--quiet"]) == 2
    assert "--min-confidence: 1.5; need 0 <= it < 1" in capsys.readouterr().err
    sure = tmp_path / "sure"  # only the pixels at 0.2 confidence or more: fewer, none of them less sure
    assert main([str(tmp_path / "rec"), "--out", str(sure), "--min-distance", "0.5", "--max-distance", "20",
                 "--min-confidence", "0.2", "--quiet"]) == 0  # fmt: skip
    kept = np.load(sure / "seq" / "confidence" / "left" / f"{t0}.npy")
    assert 0 < (kept > 0).sum() < (confidence > 0).sum() and kept[kept > 0].min() >= 0.2
    assert json.loads((sure / "summary.json").read_text())["settings"]["min_confidence"] == 0.2


def test_the_outputs_are_refused_before_any_work_and_put_in_place_whole(tmp_path, capsys, monkeypatch):
    """--out may not be the recording, lie inside it or hold it; a file of the run's outputs that exists
    already is named and kept; a second run into one --out is refused while the first holds it; a run
    that fails halfway leaves nothing in --out."""
    from fisheyedepth.cli import multiview
    from fisheyedepth.stereo import recording, sgbm

    rec = tmp_path / "rec"
    rig = write_room_rig(rec, size=128, stamps=(1_000_000_000, 1_100_000_000), half_baseline=0.3)
    t0 = rig["stamps"][0]
    common = ["--min-distance", "0.3", "--max-distance", "20", "--quiet"]
    for out, what in ((rec, "is the recording"), (rec / "seq" / "out", "lies inside the recording"),
                      (tmp_path, "holds the recording")):  # fmt: skip
        assert multiview.main([str(rec), "--out", str(out), *common]) == 2
        assert f"error: --out: {out} {what} {rec}" in capsys.readouterr().err
    assert sorted(p.name for p in (rec / "seq").iterdir()) == ["distance", "images", "poses.txt"]  # untouched

    out = tmp_path / "out"
    mine = out / "seq" / "distance" / "left" / f"{t0}.npy"
    mine.parent.mkdir(parents=True)
    mine.write_text("mine")
    assert multiview.main([str(rec), "--out", str(out), *common]) == 2
    assert f"error: {mine} exists; pass --overwrite" in capsys.readouterr().err
    assert mine.read_text() == "mine" and sorted(out.rglob("*.*")) == [mine]  # nothing else written
    held = out / "summary.json" / "keep.txt"  # a folder at an output's path: never replaced, even with
    held.parent.mkdir()  # --overwrite (it would go with all it holds)
    held.write_text("kept")
    assert multiview.main([str(rec), "--out", str(out), "--overwrite", *common]) == 2
    said = f"error: --out: {held.parent} is a folder where the run writes a file; move it away\n"
    assert capsys.readouterr().err == said and held.read_text() == "kept"
    shutil.rmtree(held.parent)

    with recording.sole_writer(out):  # another run holds --out
        assert multiview.main([str(rec), "--out", str(out), "--overwrite", *common]) == 2
        assert (
            f"error: --out: {out}: another fisheyedepth-multiview writes into it" in capsys.readouterr().err
        )

    calls, fuse = [], sgbm.fuse

    def fails_on_the_third(maps, min_confidence=0.0):
        calls.append(1)
        if len(calls) == 3:
            raise ValueError("maps: a failure halfway")
        return fuse(maps, min_confidence)

    monkeypatch.setattr(sgbm, "fuse", fails_on_the_third)
    fresh = tmp_path / "fresh"
    assert multiview.main([str(rec), "--out", str(fresh), *common]) == 2
    assert "maps: a failure halfway" in capsys.readouterr().err
    assert not fresh.exists() and not list(tmp_path.glob(".fresh*"))  # no output, no staging, no lock left
    monkeypatch.undo()
    assert multiview.main([str(rec), "--out", str(out), "--overwrite", *common]) == 0
    assert np.load(mine).shape == (128, 128) and (out / "summary.json").is_file()


@functools.cache
def small_rig(root: Path) -> Path:
    """A 128 px room rig of two instants, its cameras 0.6 m apart (a fisheye's pixel is 1.5 degrees at
    this size: a shorter baseline resolves nothing in the room, and its time pairs give too few feature
    matches to check their motion), written once per test session (each case copies it)."""
    write_room_rig(root, size=128, stamps=(1_000_000_000, 1_100_000_000), half_baseline=0.3)
    return root


def spoilt(tmp_path: Path, how) -> Path:
    """A copy of :func:`small_rig` changed by ``how(rec)``."""
    import shutil

    rec = tmp_path / "rec"
    shutil.copytree(small_rig(tmp_path.parent / "small_rig"), rec)
    how(rec)
    return rec


def rewrite_rig(rec: Path, change) -> None:
    rig = yaml.safe_load((rec / "rig.yaml").read_text())
    change(rig["cameras"])
    (rec / "rig.yaml").write_text(yaml.safe_dump(rig))


T0, T1 = 1_000_000_000, 1_100_000_000
REFUSED = {  # each: what is spoilt, the options, and the one line that names it
    "a corrupt partner image": (
        lambda r: (r / f"seq/images/right/{T1}.png").write_bytes(b"\x89PNG\r\n\x1a\nxx"),
        [],
        f"seq/images/right/{T1}.png: truncated PNG",
    ),
    "an empty ground-truth file": (
        lambda r: (r / f"seq/distance/right/{T1}.npy").write_bytes(b""),
        [],
        f"seq/distance/right/{T1}.npy: not a NumPy .npy array (empty)",
    ),
    "ground truth of 1e30 m": (
        lambda r: np.save(r / f"seq/distance/left/{T1}.npy", np.full((128, 128), 1e30, np.float32)),
        [],
        f"seq/distance/left/{T1}.npy: 16384 value(s) beyond 10000 m",
    ),
    "a camera named twice": (
        lambda r: rewrite_rig(r, lambda cams: cams[2].update(name="left")),
        [],
        "rig.yaml: key 'cameras[2].name': 'left' is also cameras[0]",
    ),
    "a quaternion of norm 2": (
        lambda r: (r / "seq/poses.txt").write_text(f"{T0} 0 0 0 0 0 0 2\n{T1} 0 0 0.15 0 0 0 1\n"),
        [],
        "seq/poses.txt:1: quaternion of norm 2; a rotation is a unit quaternion",
    ),
    "one camera paired with the rig": (
        lambda r: rewrite_rig(r, lambda cams: cams.__delitem__(slice(1, None))),
        ["--sources", "rig"],
        "no image to match: 2 no partner at its instant or among its camera's neighbours (--sources rig "
        "pairs the rig's cameras, and it has one)",
    ),
    "poses that cover no image": (
        lambda r: (r / "seq/poses.txt").write_text("1 0 0 0 0 0 0 1\n2 0 0 1 0 0 0 1\n"),
        [],
        "no image to match: 5 outside the poses' time range",
    ),
}


@pytest.mark.parametrize("case", REFUSED)
def test_bad_inputs_are_named_before_any_work(tmp_path, capsys, case):
    """Every image the run reads and every ground-truth file is checked before the first output (a bad
    one of the second instant is named with nothing written), and so are the rig's names, the poses and
    a recording that leaves nothing to match: one line, exit 2, no --out."""
    from fisheyedepth.cli.multiview import main

    how, options, message = REFUSED[case]
    rec, out = spoilt(tmp_path, how), tmp_path / "out"
    assert main([str(rec), "--out", str(out), "--quiet", *options]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and err.startswith("error: "), err
    assert not out.exists() and not list(tmp_path.glob(".out*"))


def test_a_disk_that_fills_during_the_run_is_one_line_and_leaves_nothing_a_killed_run_is_cleared(
    tmp_path, capsys, monkeypatch
):
    import errno

    from fisheyedepth.cli import multiview
    from fisheyedepth.data.layouts import RigLayout
    from fisheyedepth.stereo import recording

    def full(path, array):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(recording, "atomic_write_npy", full)
    rec, out = spoilt(tmp_path, lambda r: None), tmp_path / "out"
    assert multiview.main([str(rec), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --out: ") and "cannot be written (No space left on device)" in err
    assert err.count("\n") == 1 and not out.exists() and not list(tmp_path.glob(".out*"))
    image = rec / "seq" / "images" / "left" / "1000000000.png"

    def unreadable(layout, sequence, camera, frame):
        raise PermissionError(errno.EACCES, "Permission denied", str(image))

    monkeypatch.setattr(RigLayout, "read_image", unreadable)  # an input, not --out: named as read
    assert multiview.main([str(rec), "--out", str(out), "--quiet"]) == 2
    assert capsys.readouterr().err == f"error: {image}: cannot be read (Permission denied)\n"
    stale = tmp_path / ".out.multiview-killed"  # what a SIGKILLed run leaves (no clean-up runs)
    other = tmp_path / ".outs.multiview-running"  # another --out's, with a name this one begins
    (stale / "seq").mkdir(parents=True)
    other.mkdir()
    monkeypatch.undo()
    assert multiview.main([str(rec), "--out", str(out), "--quiet"]) == 0
    assert not stale.exists() and other.is_dir() and (out / "summary.json").is_file()


def test_no_number_without_evidence(tmp_path, capsys, monkeypatch):
    """Uniform grey images and a rig pair at one centre keep no pixel (the summary says why, exit 1); file
    names that are no timestamp are named as left out, never read as another image; 12-bit data in 16-bit
    PNGs is read by its range; a run that would need more memory than the machine has is refused naming
    the camera and both numbers, and so is a sweep of too many hypotheses."""
    from fisheyedepth.cli import multiview
    from fisheyedepth.images import read_image
    from fisheyedepth.stereo import pairing

    def grey(r):
        for path in (r / "seq" / "images").rglob("*.png"):
            cv2.imwrite(str(path), np.full((128, 128), 128, np.uint8))

    rec = spoilt(tmp_path / "grey", grey)
    assert multiview.main([str(rec), "--out", str(tmp_path / "o1"), "--quiet"]) == 1
    assert "error: " in capsys.readouterr().err
    summary = json.loads((tmp_path / "o1" / "summary.json").read_text())
    assert {r["flat"] for r in summary["images"]} == {1.0} and all(r["kept"] == 0 for r in summary["images"])
    assert len(summary["kept_nothing"]) == 4

    same_centre = spoilt(
        tmp_path / "zero", lambda r: rewrite_rig(r, lambda c: c[1].update(cam_to_body=c[0]["cam_to_body"]))
    )
    assert (
        multiview.main([str(same_centre), "--out", str(tmp_path / "o2"), "--sources", "rig", "--quiet"]) == 1
    )
    assert "the two camera centres coincide" in capsys.readouterr().err
    summary = json.loads((tmp_path / "o2" / "summary.json").read_text())
    left_out = list(summary["pairs_left_out"].values())  # the pair of each instant
    assert len(left_out) == 2 and all("coincide" in why for why in left_out)
    assert all(r["kept"] == 0 for r in summary["images"])

    def renamed(r):
        images = r / "seq" / "images" / "left"
        (images / f"{T1}.png").rename(images / f"000{T1}.png")  # the timestamp would name another file
        (images / "frame_x.png").write_bytes((images / f"{T0}.png").read_bytes())
        (images / "notes.txt").write_text("not an image")  # neither an image nor left out
        (images / "thumbs").mkdir()
        for path in (r / "seq" / "images").rglob("*.png"):  # 12-bit data: 0-4095 in a 16-bit PNG
            cv2.imwrite(str(path), cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).astype(np.uint16) * 16)

    rec = spoilt(tmp_path / "names", renamed)
    assert multiview.main([str(rec), "--out", str(tmp_path / "o3"), "--quiet"]) == 0
    summary = json.loads((tmp_path / "o3" / "summary.json").read_text())
    not_understood = "name not understood (<timestamp_ns>.png)"
    assert summary["images_left_out"] == {
        f"seq/left/000{T1}.png": not_understood, "seq/left/frame_x.png": not_understood,
        f"seq/lonely/{T0 + 50_000_000}": pairing.NO_PARTNER}  # fmt: skip
    right = next(r for r in summary["images"] if r["image"] == f"seq/right/{T0}")
    assert right["kept"] > 0.2 and right["checked"]["abs_rel"] < 0.1 and right["flat"] < 0.01, right
    twelve_bit = cv2.imread(str(rec / f"seq/images/right/{T0}.png"), cv2.IMREAD_UNCHANGED)
    eight_bit = read_image(rec / f"seq/images/right/{T0}.png").bgr[..., 0]
    assert twelve_bit.dtype == np.uint16 and twelve_bit.max() <= 4095 and eight_bit.max() >= 200  # not 0-15
    assert np.abs(eight_bit.astype(int) - twelve_bit // 16).max() <= 1  # the 8 bits it was made from

    monkeypatch.setattr("fisheyedepth.options.memory.machine_memory", lambda: 2**20)
    assert multiview.main([str(rec), "--out", str(tmp_path / "o4"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err == (
        f"error: {rec / 'rig.yaml'}: camera 'left': '128x128' needs 72 MiB of memory (64 MiB + 512 bytes a "
        "pixel of a pair); this machine has 1 MiB\n"
    )
    monkeypatch.setattr("fisheyedepth.options.memory.machine_memory", lambda: 2**30)
    args = [
        str(rec),
        "--out",
        str(tmp_path / "o5"),
        "--matcher",
        "sweep",
        "--hypotheses",
        "100000",
        "--quiet",
    ]
    assert multiview.main(args) == 2
    assert capsys.readouterr().err == (
        "error: --hypotheses: 100000 needs 30.5 GiB of memory (20 bytes x hypotheses x camera 'left''s "
        "128x128 pixels); this machine has 1 GiB\n"
    )


def test_the_memory_bound_holds_for_a_pair(tmp_path):
    """The bound the command refuses by (:data:`sgbm.MEMORY_PER_PIXEL`) covers a pair's measured
    peak: two 512 px fisheyes matched in a fresh process, against the same process without the match."""
    import subprocess
    import sys

    from fisheyedepth.stereo.sgbm import pair_memory

    tests = str(Path(__file__).parent)
    code = f"""
import sys
import numpy as np
sys.path.insert(0, {tests!r})
from conftest import kitti02
from fisheyedepth.stereo import RigStereo

camera = kitti02().resize(512, 512)
moved = np.eye(4); moved[0, 3] = 0.3
noise = np.random.default_rng(0).integers(0, 255, (2, 512, 512), dtype=np.uint8)
if sys.argv[1] == "match":
    rig = RigStereo({{"a": camera, "b": camera}}, {{"a": np.eye(4), "b": moved}}, threads=1)
    rig({{"a": noise[0], "b": noise[1]}})
# the peak of this process's own memory (ru_maxrss would carry the forking parent's size over exec)
print(next(int(x.split()[1]) * 1024 for x in open("/proc/self/status") if x.startswith("VmHWM:")))
"""

    def peak(what: str) -> int:
        run = subprocess.run([sys.executable, "-c", code, what], capture_output=True, text=True, check=True)
        return int(run.stdout)

    grown = peak("match") - peak("setup")
    assert 0.5 * pair_memory(512 * 512) < grown < pair_memory(512 * 512), grown / 512**2


def test_each_pair_is_matched_once_for_the_images_that_ask_and_then_freed(tmp_path):
    """Time partners need not be mutual (frames 0, 6 and 7 cm on: the third takes the first, the first
    the second): a pair is matched in the directions its images ask for, and nothing is left held when
    every image has taken its maps."""
    from fisheyedepth.data.layouts import RigLayout
    from fisheyedepth.stereo.pairing import pairings
    from fisheyedepth.stereo.pipeline import SgbmSettings, Timer
    from fisheyedepth.stereo.sgbm import SgbmRecording

    stamps = (1_000_000_000, 1_100_000_000, 1_200_000_000)
    write_room_rig(tmp_path / "rec", size=256, stamps=stamps)
    (tmp_path / "rec" / "seq" / "poses.txt").write_text(
        "".join(f"{t} 0 0 {z} 0 0 0 1\n" for t, z in zip(stamps, (0.0, 0.06, 0.07), strict=True))
    )
    layout = RigLayout(tmp_path / "rec")
    planned = [p for p in pairings(layout, ("time",)) if p.partners and p.camera == "left"]
    partners = {p.frame.key: [q.frame.key for q in p.partners] for p in planned}
    assert partners == {stamps[0]: [stamps[1]], stamps[1]: [stamps[0]], stamps[2]: [stamps[0]]}
    store = SgbmRecording(layout, SgbmSettings(min_distance=0.2, max_distance=20.0), Timer(), planned)
    for pairing in planned:
        for partner in pairing.partners:
            maps = store.get(
                pairing.sequence, (pairing.camera, pairing.frame), (partner.camera, partner.frame)
            )
            assert maps is not None and maps.distance.shape == (256, 256)
    assert store.maps == {} and store.wanted == {}


def test_the_sweep_stays_as_a_matcher(tmp_path):
    """``--matcher sweep``: the sweep over every partner of an image at once, the same outputs."""
    from fisheyedepth.cli.multiview import main

    write_room_rig(tmp_path / "rec", size=64, stamps=(1_000_000_000, 1_100_000_000))
    out = tmp_path / "out"
    args = [str(tmp_path / "rec"), "--out", str(out), "--matcher", "sweep", "--hypotheses", "24",
            "--min-distance", "0.5", "--max-distance", "20", "--sources", "rig", "--quiet"]  # fmt: skip
    assert main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["settings"]["matcher"] == "sweep" and summary["settings"]["hypotheses"] == 24
    assert len(summary["images"]) == 4
    for record in summary["images"]:
        assert record["checked"]["abs_rel"] < 0.2 and record["checked"]["coverage"] > 0.3, record


def turned(T: torch.Tensor, degrees: float, axis=(0.3, 1.0, -0.2)) -> torch.Tensor:
    """``T`` turned by ``degrees`` about ``axis`` (in its own frame), its centre kept."""
    axis = torch.tensor(axis, dtype=torch.float64)
    R = axis_angle_to_matrix(axis / axis.norm() * math.radians(degrees))
    return make_pose(T[:3, :3] @ R, T[:3, 3])


@pytest.mark.parametrize("degrees", [0.0, 1.5])
def test_refine_writes_the_rig_its_images_say(tmp_path, degrees):
    """``--refine`` on a rig whose rig.yaml has the right camera turned by 1.5 degrees: the rotation the
    images say is recovered to 0.05 degrees, written to OUT/rig.yaml (the recording untouched) and swept
    with; a correct rig is left as it is (the refinement's drop of the epipolar error is within the
    matches' noise). The camera with no same-instant partner is named."""
    from fisheyedepth.cli.multiview import main
    from fisheyedepth.data.layouts import RigLayout

    true_right = pose(10.0, (0.1, 0.0, 0.0))
    rec, out = tmp_path / "rec", tmp_path / "out"
    rig = write_room_rig(rec, size=384, calibrated={"right": turned(true_right, degrees)})
    before = (rec / "rig.yaml").read_text()
    args = [str(rec), "--out", str(out), "--refine", "--sources", "rig", "--min-distance", "0.5",
            "--max-distance", "20", "--max-images", "1", "--quiet"]  # fmt: skip
    assert main(args) == 0
    assert (rec / "rig.yaml").read_text() == before
    refined = RigLayout(out)  # OUT/rig.yaml reads as a rig description (its models are inline)
    right = torch.from_numpy(refined.cameras["right"].cam_to_body)
    assert rotation_between_deg(right, true_right) < (0.02 if degrees == 0 else 0.05)
    assert np.allclose(refined.cameras["left"].cam_to_body, rig["extrinsics"]["left"].numpy())  # the kept one
    assert np.allclose(right[:3, 3].numpy(), [0.1, 0.0, 0.0])  # rotation only: the lever arm kept
    summary = json.loads((out / "summary.json").read_text())
    change = summary["refinement"]["cameras"]["right"]
    assert change["relative_to"] == "left" and change["instants"] == 3 and change["inliers"] > 100
    assert change["applied"] == (degrees > 0)  # a correct rig's drop lies within the matches' noise
    if degrees == 0:
        assert np.array_equal(right.numpy(), true_right.numpy())  # written back exactly as recorded
    assert change["rotation_deg"] == pytest.approx(degrees, abs=0.05)
    assert change["epipolar_px_after"] < 0.2 and change["epipolar_px_before"] > (0.8 if degrees else 0.0)
    assert summary["refinement"]["unrefined"] == ["lonely"]
    beyond = [name for name, why in summary["images_left_out"].items() if why == "beyond --max-images 1"]
    assert len(beyond) == 5  # the rig's other five images, named
    (record,) = summary["images"]
    assert record["checked"]["abs_rel"] < 0.1, record


# ------------------------------------------------------------------ a real rectified pair
def crop(image: torch.Tensor, camera: PinholeCamera, x0: int, y0: int, width: int, height: int):
    c = camera
    cropped = PinholeCamera(width=width, height=height, fx=c.fx, fy=c.fy, cx=c.cx - x0, cy=c.cy - y0)
    return image[..., y0 : y0 + height, x0 : x0 + width], cropped


def test_middlebury_motorcycle_a_real_pair_swept():
    """Middlebury 2014 Motorcycle (real photographs, scikit-image): census sweep stereo on a 320x240 window
    of the left image's centre against the right image's full rows, scored against the exact disparity.
    The whole image (128 hypotheses) scores 0.0116 on 85.9 % of its pixels (BENCHMARKS.md); the window
    loses some of its border to the round trip."""
    pytest.importorskip("skimage")
    from fisheyedepth.realworld.pairs import motorcycle

    pair = motorcycle()
    x0, y0, width, height = 250, 130, 320, 240
    reference = View(*crop(pair.image, pair.camera, x0, y0, width, height), torch.eye(4))
    source = View(*crop(pair.partner_image, pair.partner_camera, 0, y0, pair.partner_camera.width, height),
                  pair.T.float())  # fmt: skip
    truth = pair.distance[y0 : y0 + height, x0 : x0 + width][None]
    result = SweepMatcher(SweepSettings(hypotheses=96, min_distance=1.5, max_distance=10.0, cost="census"))(
        reference, [source]
    )
    checked = scores(result.distance, truth)
    assert checked["abs_rel"] < 0.02 and checked["a1"] > 0.96 and checked["coverage"] > 0.8, checked
    assert scores(result.dense, truth)["abs_rel"] < 0.1


@pytest.mark.realdata
def test_real_pairs_through_the_rectified_pipeline():
    """``make realscore``'s pairs through the rectified pipeline (the ranges by the scene's kind): the ADT
    SLAM pair, rotation refined, each camera of frames 0 and 1 the reference, checked within 0.075 on 48 %
    or more of the overlap (the round trip's price: 0.068-0.084 on 56 % without it) and filled within
    0.15; Middlebury Motorcycle checked within
    0.02 on 85 % or more of its overlap and filled within 0.05; every one far better than the constant
    map."""
    pytest.importorskip("skimage")
    from fisheyedepth.realworld.pairs import overlap
    from fisheyedepth.realworld.stereo import real_pairs, score_pair

    root = realdata_dir()
    if not (root / "adt_slam").is_dir():
        pytest.skip(f"real data not found at {root} (set FISHEYEDEPTH_REALDATA)")
    pairs = real_pairs(root)
    assert [p.name for p, _, _ in pairs] == ["adt_left_0", "adt_right_0", "adt_left_1", "adt_right_1",
                                            "middlebury_motorcycle"]  # fmt: skip
    refinement = pairs[0][1]
    assert refinement["instants"] == 3 and 0.5 < refinement["rotation_deg"] < 1.2
    assert refinement["error_before_px"] > 1.2 and refinement["error_after_px"] < 0.4
    for pair, _, matcher in pairs:
        scored = overlap(pair)
        record, (checked, dense) = score_pair(pair, scored, matcher)
        c, d = record["checked"], record["dense"]
        bound = (0.02, 0.85, 0.05) if pair.name.startswith("middlebury") else (0.075, 0.48, 0.15)
        assert c["abs_rel"] <= bound[0] and c["coverage"] >= bound[1] and d["abs_rel"] <= bound[2], (
            pair.name,
            record,
        )
        assert c["abs_rel"] < 0.2 * c["constant_abs_rel"] and checked.shape == pair.distance.shape


@pytest.mark.realdata
def test_realscore_scores_stereo_beside_each_model(tmp_path, monkeypatch, capsys):
    """``scripts/tools/real_world.py`` (``make realscore``) adds a table: each ADT reference frame and the
    Middlebury pair, checked and filled, the constant map and each model on the same overlap pixels,
    pictures ``multiview_<frame>.png``; every number in the JSON too, and the record rebuilds the table."""
    pytest.importorskip("skimage")
    from fisheyedepth.realworld import stereo as stereo_scores

    root = realdata_dir()
    if not (root / "adt_slam").is_dir():
        pytest.skip(f"real data not found at {root} (set FISHEYEDEPTH_REALDATA)")
    full = stereo_scores.real_pairs
    # for time: frame 0's two references and Middlebury
    monkeypatch.setattr(
        stereo_scores, "real_pairs", lambda *a, **k: [p for p in full(*a, **k) if "_1" not in p[0].name]
    )
    torch.manual_seed(0)
    module = bare_module(net={"scales": (0, 1), "base_focal": 20.0}, input_size=(64, 64))
    tiny = tmp_path / "tiny.ckpt"
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams)}, tiny)
    pictures, out = tmp_path / "pictures", tmp_path / "scores.json"
    args = [str(tiny), "--root", str(root), "--frames", "adt", "--pictures", str(pictures),
            "--json", str(out)]  # fmt: skip
    assert load_script("tools/real_world").main(args) == 0
    lines = capsys.readouterr().out.splitlines()
    table = lines[lines.index(stereo_scores.HEADER) + 2 :]
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in table if line.startswith("| ")]
    names = ["adt_left_0", "adt_right_0", "middlebury_motorcycle"]
    assert [r[0] for r in rows] == names
    record = json.loads(out.read_text())["multiview"]
    for row in rows:
        kept = record[row[0]]
        assert row[2] == f"{kept['overlap_pixels']:,}"
        assert row[3] == ", ".join(f"{kept['checked'][k]:.3f}" for k in ("abs_rel", "a1", "coverage"))
        assert row[4] == str(kept["checked"]["constant_abs_rel"])
        assert kept["stereo"]["matcher"] == "sgbm"
        if row[0].startswith("adt"):
            model = kept["models"]["tiny"]
            assert row[7] == f"tiny: {model['abs_rel']:.3f}, {model['a1']:.3f}"
            assert model["pixels"] == kept["overlap_pixels"]  # every overlap pixel has a prediction
        else:
            assert row[7] == "-" and kept["refinement"] is None
        picture = cv2.imread(str(pictures / f"multiview_{row[0]}.png"))
        assert picture.shape[1] == 4 * (640 if row[0].startswith("adt") else 741)
    assert any(
        line.startswith("ADT slam right relative to left, refined from 3 image pairs") for line in lines
    )
    # the record rebuilds the table, nothing re-scored
    assert load_script("tools/real_world").main(["--from-records", "--multiview", str(out)]) == 0
    start = lines.index(stereo_scores.HEADER)
    assert capsys.readouterr().out.splitlines() == lines[start : start + 2 + len(names)]


# ------------------------------------------------------------------ held-out worlds: what parallax resolves
def test_a_camera_moving_forward_resolves_nothing_at_its_focus_of_expansion():
    """scripts/research/sweep_heldout.py's resolvable pixels: a 10 % change of the distance moves the point
    by a pixel in a source 1 m ahead wherever it lies 45-78 degrees off the motion at 3 m, but not along the
    motion itself (the image centre of a camera moving along its optical axis); nowhere without motion."""
    resolvable = load_script("research/sweep_heldout").resolvable
    camera = kitti02().resize(192, 192)
    truth = torch.full((192, 192), 3.0)
    ahead = View(torch.zeros(1, 1, 192, 192), camera, make_pose(torch.eye(3), torch.tensor([0.0, 0.0, -1.0])))
    can = resolvable(camera, truth, [ahead])
    centre = camera.project(torch.tensor([[0.0, 0.0, 1.0]]))[0][0].round().long().tolist()
    assert not can[centre[1] - 2 : centre[1] + 3, centre[0] - 2 : centre[0] + 3].any()  # expansion focus
    rays, has_ray = compute_rays(camera)
    off_axis = has_ray & (rays[..., 2] < math.cos(math.radians(45))) & (rays[..., 2] > 0.2)  # 45-78 degrees
    assert can[off_axis].float().mean() > 0.95
    still = View(ahead.image, camera, torch.eye(4))
    assert not resolvable(camera, truth, [still]).any()
