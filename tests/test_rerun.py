"""Rerun recordings (fisheyedepth.rerun3d), read back with Rerun's own reader (``rerun.chunk.RrdReader``):
what is in them, where the points land, and that a failed run leaves nothing behind."""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
import torch

from stereo_world import ROOM, pose, render, texture_volume

from conftest import ROOT, kitti02, load_cfg, load_script

rr = pytest.importorskip("rerun", reason="the viz extra (rerun-sdk) is not installed")

from fisheyedepth.rerun3d import TRUTH_COLOUR, CameraView, RigRecorder  # noqa: E402

STAMPS = (1_000_000_000, 1_033_000_000, 1_066_000_000)


# ------------------------------------------------------------------------------- reading back
class Recording:
    """A recording as Rerun reads it: per entity, its rows (``frame``, ``time`` in ns, components)."""

    def __init__(self, path: Path):
        self.rows: dict[str, list[dict]] = defaultdict(list)
        self.static: dict[str, dict] = defaultdict(dict)
        self.timelines: set[str] = set()
        for chunk in rr.chunk.RrdReader(path).stream().to_chunks():
            batch = chunk.to_record_batch()
            columns = {f.name: batch.column(i) for i, f in enumerate(batch.schema) if ":" in f.name}
            self.timelines |= set(chunk.timeline_names)
            if chunk.is_static:
                self.static[chunk.entity_path] |= {k: v[0] for k, v in columns.items()}
                continue
            frames = batch.column("frame").to_pylist()
            times = batch.column("time").cast(pa.int64()).to_pylist()
            for r, (frame, time_ns) in enumerate(zip(frames, times, strict=True)):
                row = {"frame": frame, "time": time_ns, **{k: v[r] for k, v in columns.items()}}
                self.rows[chunk.entity_path].append(row)
        for rows in self.rows.values():
            rows.sort(key=lambda row: row["frame"])

    def points(self, entity: str, frame: int) -> np.ndarray:
        (row,) = [r for r in self.rows[entity] if r["frame"] == frame]
        return np.array(row["Points3D:positions"].as_py(), dtype=np.float64).reshape(-1, 3)

    def values(self, entity: str, component: str) -> list:
        return [r[component].as_py() for r in self.rows[entity]]


# ---------------------------------------------------------------------------- a synthetic rig
CAMERA = kitti02().resize(48, 48)  # a Mei fisheye, 48 px
EXTRINSICS = {"left": pose(-20.0, (-0.1, 0.0, 0.0)).numpy(), "right": pose(20.0, (0.1, 0.0, 0.0)).numpy()}


def body_pose(i: int) -> np.ndarray:
    return pose(15.0 * i, (0.3 * i, 0.1 * i, 0.4 * i)).numpy()


def room_views(i: int) -> tuple[dict[str, CameraView], dict[str, int]]:
    """Both cameras inside the room at instant ``i`` with their exact distance (``left`` in float32 with
    NaN, inf and negative values written over a few pixels, ``right`` in float64), and how many pixels
    of each have a value."""
    views, valid = {}, {}
    for name, E in EXTRINSICS.items():
        image, distance = render(CAMERA, torch.from_numpy(body_pose(i) @ E), texture_volume(0))
        d = distance[0].numpy()
        if name == "left":
            d = d.astype(np.float32)
            d[0, :3], d[1, :3], d[2, :3] = np.nan, np.inf, -2.0
        else:
            d = d.astype(np.float64)
        grey = (image[0, 0].numpy() * 255).round().astype(np.uint8)
        views[name] = CameraView(CAMERA, grey, {"distance": d}, ground_truth=d, scores={"abs_rel": 0.1 * i})
        valid[name] = int((np.isfinite(d) & (d > 0)).sum())
    return views, valid


def off_the_walls(points: np.ndarray) -> np.ndarray:
    """Each point's distance (metres) to the room's box of walls."""
    lo, hi = ROOM[0].numpy(), ROOM[1].numpy()
    inside = np.minimum(points - lo, hi - points)  # to each wall from inside, negative outside
    outside = np.linalg.norm(np.maximum(0, np.maximum(lo - points, points - hi)), axis=1)
    return np.where(outside > 0, outside, np.abs(inside.min(axis=1)))


def record_room(path: Path, points_per_image: int) -> dict[str, int]:
    with RigRecorder(path, points_per_image=points_per_image) as recorder:
        recorder.rig({n: np.eye(4) for n in EXTRINSICS}, name="refined")
        recorder.rig(EXTRINSICS)  # the last rig logged: the one the instants place their cameras by
        for i, stamp in enumerate(STAMPS):
            views, valid = room_views(i)
            recorder.instant(stamp, i, views, body_pose(i), cam_to_body=EXTRINSICS if i == 2 else None)
    return valid


def test_a_moving_rig_lands_its_points_on_the_walls_in_the_world_frame(tmp_path):
    path = tmp_path / "room.rrd"
    budget = 500
    valid = record_room(path, budget)
    assert not list(tmp_path.glob(".*"))  # the temporary file was renamed into place
    recording = Recording(path)
    assert {"time", "frame"} <= recording.timelines
    for camera in EXTRINSICS:
        for entity in (f"world/points/{camera}/distance", f"world/points/{camera}/ground_truth"):
            rows = recording.rows[f"/{entity}"]
            assert [r["frame"] for r in rows] == [0, 1, 2] and [r["time"] for r in rows] == list(STAMPS)
            for i in range(3):
                points = recording.points(f"/{entity}", i)
                assert len(points) == budget < valid[camera]  # the budget, of more pixels with a value
                assert np.isfinite(points).all() and off_the_walls(points).max() < 0.01
        for part in ("image", "distance/colour", "distance/metres", "ground_truth/metres"):
            assert len(recording.rows[f"/images/{camera}/{part}"]) == 3
        scores = [v for (v,) in recording.values(f"/scores/{camera}/abs_rel", "Scalars:scalars")]
        assert scores == pytest.approx([0.0, 0.1, 0.2])
        truth_colours = recording.rows[f"/world/points/{camera}/ground_truth"][0]["Points3D:colors"].as_py()
        r, g, b = TRUTH_COLOUR
        assert set(truth_colours) == {(r << 24) | (g << 16) | (b << 8) | 255}  # one colour, RGBA packed
        for rig, expected in (("rig", EXTRINSICS[camera][:3, 3]), ("refined", np.zeros(3))):
            static = recording.static[f"/world/body/{rig}/{camera}"]
            assert np.allclose(static["Transform3D:translation"].as_py(), expected, atol=1e-6)
    body = [v for (v,) in recording.values("/world/body", "Transform3D:translation")]
    assert np.allclose(body, [body_pose(i)[:3, 3] for i in range(3)], atol=1e-6)
    strips = recording.values("/world/trajectory", "LineStrips3D:strips")
    assert [len(s[0]) for s in strips] == [1, 2, 3]  # the path so far, at each instant
    assert np.allclose(strips[-1][0], [body_pose(i)[:3, 3] for i in range(3)], atol=1e-6)

    everything = tmp_path / "all.rrd"  # a budget above the pixels: every pixel with a value, none other
    valid = record_room(everything, 10_000)
    again = Recording(everything)
    for camera, count in valid.items():
        assert [len(again.points(f"/world/points/{camera}/distance", i)) for i in range(1)] == [count]
    depth = again.rows["/images/left/distance/metres"][0]
    assert depth["DepthImage:meter"].as_py() == [1.0]
    stored = np.frombuffer(bytes(depth["DepthImage:buffer"].as_py()[0]), np.float16).reshape(48, 48)
    views, _ = room_views(0)
    truth = views["left"].maps["distance"]
    good = np.isfinite(truth) & (truth > 0)
    assert np.allclose(stored[good], truth[good], rtol=1e-3)  # metres, to 0.05 %


def test_an_exception_in_the_block_leaves_no_file_and_no_temporary(tmp_path):
    path = tmp_path / "out" / "recording.rrd"
    with pytest.raises(RuntimeError, match="stopped"), RigRecorder(path) as recorder:
        recorder.rig(EXTRINSICS)
        recorder.instant(STAMPS[0], 0, room_views(0)[0])
        assert len(list(path.parent.glob(".recording.rrd.*.tmp"))) == 1  # written beside, hidden
        raise RuntimeError("stopped")
    assert list(path.parent.iterdir()) == []


def test_an_existing_recording_is_refused_without_overwrite(tmp_path):
    path = tmp_path / "recording.rrd"
    path.write_bytes(b"an earlier run's")
    with pytest.raises(FileExistsError, match=str(path)):
        RigRecorder(path)
    assert path.read_bytes() == b"an earlier run's" and sorted(tmp_path.iterdir()) == [path]
    with RigRecorder(path, overwrite=True) as recorder:
        recorder.instant(5, 0, {"left": room_views(0)[0]["left"]})
    assert len(Recording(path).rows["/world/points/left/distance"]) == 1


def test_a_wrong_shape_is_named_and_rerun_missing_names_the_extra(tmp_path, monkeypatch):
    view = room_views(0)[0]["left"]
    bad = CameraView(CAMERA, view.image, {"distance": np.ones((10, 10))})
    with (
        pytest.raises(ValueError, match="left: map 'distance': shape"),
        RigRecorder(tmp_path / "a.rrd") as rec,
    ):
        rec.instant(0, 0, {"left": bad})
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setitem(sys.modules, "rerun", None)  # as if the extra were not installed
    with pytest.raises(ImportError, match=r'pip install -e "\.\[viz\]"'):
        RigRecorder(tmp_path / "b.rrd")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------- predict and eval
@pytest.mark.parametrize("when", ["mid-run", "closing"])
def test_predict_whose_recording_cannot_be_written_keeps_its_frames_and_says_so(
    kitti_data, checkpoint, tmp_path, monkeypatch, when
):
    from fisheyedepth.cli.predict import RecordingFailed, predict
    from fisheyedepth.rerun3d import RigRecorder
    from test_inference import frames_folder

    def stopped(*args, **kwargs):  # what the SDK raises once the disk fills under its writer
        raise RuntimeError("File-writer thread shut down prematurely")

    if when == "mid-run":
        monkeypatch.setattr(RigRecorder, "_log_view", stopped)
    else:
        original = RigRecorder.close

        def close(self):
            self.stream.flush = stopped
            return original(self)

        monkeypatch.setattr(RigRecorder, "close", close)
    images = frames_folder(kitti_data, tmp_path / "in", corrupt=False)
    out = tmp_path / "out"
    cfg = load_cfg("predict", ckpt_path=checkpoint, input=images, camera=kitti_data / "calibration" /
                   "image_02.yaml", output=out, rerun=True)  # fmt: skip
    with pytest.raises(
        RecordingFailed, match=r"recording.rrd: the recording could not be written .*frames predicted"
    ):
        predict(cfg)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["recording"] is None and "could not be written" in summary["recording_error"]
    assert summary["frames"] == len(list(out.glob("*_distance.npy"))) >= 1
    assert not (out / "recording.rrd").exists() and not list(out.glob(".recording.rrd*"))


def test_predict_with_rerun_records_every_frame(kitti_data, checkpoint, tmp_path):
    from fisheyedepth.cli.predict import predict
    from test_inference import frames_folder

    images = frames_folder(kitti_data, tmp_path / "in", corrupt=False)
    calib = kitti_data / "calibration" / "image_02.yaml"
    out = tmp_path / "out"
    cfg = load_cfg("predict", ckpt_path=checkpoint, input=images, camera=calib, output=out, rerun=True)
    summary = predict(cfg)
    assert summary["recording"] == str(out / "recording.rrd")
    recording = Recording(out / "recording.rrd")
    rows = recording.rows["/world/points/camera/distance"]
    assert [r["frame"] for r in rows] == [0, 1, 2]
    assert [r["time"] for r in rows] == [0, 100_000_000, 200_000_000]  # 10 frames a second: a folder's
    distance = np.load(out / f"{sorted(images.iterdir())[0].stem}_distance.npy")
    known = int((np.isfinite(distance) & (distance > 0)).sum())
    assert len(recording.points("/world/points/camera/distance", 0)) == min(known, 100_000) > 0
    assert len(recording.rows["/images/camera/image"]) == 3
    again = tmp_path / "again"
    again.mkdir()
    (again / "recording.rrd").write_bytes(b"an earlier run's")
    with pytest.raises(FileExistsError, match="recording.rrd exists"):  # refused before any frame
        predict(
            load_cfg("predict", ckpt_path=checkpoint, input=images, camera=calib, output=again, rerun=True)
        )
    assert sorted(p.name for p in again.iterdir()) == ["recording.rrd"]
    with pytest.raises(ValueError, match="rerun: 'yes' is not a boolean"):
        predict(load_cfg("predict", ckpt_path=checkpoint, input=images, camera=calib, output=tmp_path / "o2",
                         rerun="yes"))  # fmt: skip


def test_eval_with_rerun_records_the_scored_frames_with_their_ground_truth(kitti_data, checkpoint, tmp_path):
    from fisheyedepth.cli.evaluate import eval_checkpoint
    from test_runtimes import _datamodule

    cfg = load_cfg(
        "eval",
        ckpt_path=str(checkpoint),
        paths={"output_dir": str(tmp_path / "eval")},
        data={"generate": None, "datamodule": _datamodule(kitti_data)},
        rerun=True,
    )
    cfg.eval.pictures = 0
    record = eval_checkpoint(cfg)
    recording = Recording(Path(record["recording"]))
    images = record["results"]["full"]["none"]["images"]
    cameras = {e.split("/")[3] for e in recording.rows if e.startswith("/world/points/")}
    assert cameras == {"image_02", "image_03"}
    instants = {r["frame"] for c in cameras for r in recording.rows[f"/world/points/{c}/distance"]}
    assert len(instants) * len(cameras) == images  # both cameras of a frame at one instant
    abs_rel = [v[0] for c in cameras for v in recording.values(f"/scores/{c}/abs_rel", "Scalars:scalars")]
    assert len(abs_rel) == images and 0 < np.mean(abs_rel) < 5
    truth = recording.points("/world/points/image_02/ground_truth", min(instants))
    assert len(truth) > 0 and np.isfinite(truth).all()
    second = eval_checkpoint(cfg)  # an earlier recording is kept, as results.json is
    assert Path(second["recording"]).name == "recording_1.rrd" and Path(record["recording"]).is_file()


# --------------------------------------------------------------------------------- the live rig
def test_a_killed_live_rigs_aria_conversion_is_removed_by_the_next_run(tmp_path, monkeypatch):
    """A live rig run killed outright leaves its converted Aria export in the temporary folder; the next
    run removes it (a live run's, with a running pid in its name, is kept)."""
    import os
    import tempfile

    from test_multiview import write_room_rig

    live_rig = load_script("tools/live_rig")
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    dead = tmp_path / "tmp" / f"{live_rig.CONVERSION}999999999-abc"  # no process has this pid
    alive = tmp_path / "tmp" / f"{live_rig.CONVERSION}{os.getpid()}-def"
    for folder in (dead, alive):
        (folder / "rig" / "seq0").mkdir(parents=True)
    write_room_rig(tmp_path / "rec", size=64, stamps=(1_000_000_000, 1_100_000_000))
    with live_rig.rig_layout(tmp_path / "rec") as layout:
        assert {"left", "right"} <= set(layout.cameras)
    assert not dead.exists() and alive.is_dir()


def test_the_live_rig_replays_a_recording_into_rerun(tmp_path, capsys):
    from test_multiview import write_room_rig

    write_room_rig(tmp_path / "rec", size=128, half_baseline=0.3)
    live_rig = load_script("tools/live_rig")
    out = tmp_path / "live.rrd"
    args = [str(tmp_path / "rec"), "--out", str(out), "--min-distance", "0.5", "--max-distance", "20",
            "--threads", "1", "--points", "2000"]  # fmt: skip
    assert live_rig.main(args) == 0
    printed = capsys.readouterr()
    assert "left out (no image at every instant): lonely" in printed.err
    assert "instant 3/3:" in printed.out and "instants/s" in printed.out
    recording = Recording(out)
    for camera in ("left", "right"):
        for name in ("kept", "filled"):
            rows = recording.rows[f"/world/points/{camera}/{name}"]
            assert [r["time"] for r in rows] == [1_000_000_000, 1_100_000_000, 1_200_000_000]
            assert 0 < len(recording.points(f"/world/points/{camera}/{name}", 1)) <= 2000
        kept = recording.points(f"/world/points/{camera}/kept", 1)
        assert np.median(off_the_walls(kept)) < 0.12  # 128 px stereo, walls 2-5 m away: 7 cm measured
    assert live_rig.main(args) == 2  # the recording exists: refused without --overwrite
    assert "exists" in capsys.readouterr().err


def test_the_multiview_command_records_its_instants_with_the_refined_rig(tmp_path):
    """``fisheyedepth-multiview --rerun``: OUT/recording.rrd beside the maps, one instant per timestamp
    with both cameras' kept and filled points on the room's walls, the ground truth's points and the
    abs_rel scalar, the recorded rig and the refined one."""
    from fisheyedepth.cli import multiview as command

    from test_multiview import write_room_rig

    write_room_rig(tmp_path / "rec", size=128, half_baseline=0.3)  # at 128 px 0.2 m resolves little
    out = tmp_path / "out"
    args = [str(tmp_path / "rec"), "--out", str(out), "--min-distance", "0.5", "--max-distance", "20",
            "--threads", "1", "--refine", "--rerun", "--quiet"]  # fmt: skip
    assert command.main(args) == 0
    recording = Recording(out / "recording.rrd")
    stamps = [1_000_000_000, 1_100_000_000, 1_200_000_000]
    for camera in ("left", "right"):
        for name in ("kept", "filled", "ground_truth"):
            entity = f"/world/points/{camera}/{name}"
            assert [r["time"] for r in recording.rows[entity]] == stamps, entity
            assert 0 < len(recording.points(entity, 1)) <= 100_000
        assert np.median(off_the_walls(recording.points(f"/world/points/{camera}/kept", 1))) < 0.12
        assert (
            np.percentile(off_the_walls(recording.points(f"/world/points/{camera}/ground_truth", 1)), 99)
            < 0.01
        )
        assert len(recording.values(f"/scores/{camera}/abs_rel", "Scalars:scalars")) == 3
        assert {f"/world/body/rig/{camera}", f"/world/body/refined/{camera}"} <= set(recording.static)
    assert [r["frame"] for r in recording.rows["/world/body"]] == [0, 1, 2]
    assert command.main(args) == 2  # its outputs exist: refused without --overwrite, the recording kept
    assert (out / "recording.rrd").stat().st_size > 0


def test_the_readme_names_the_recording():
    readme = (ROOT / "README.md").read_text()
    assert "rerun OUT/recording.rrd" in readme
