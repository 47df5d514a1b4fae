"""Transforms, values and paths a user can get wrong, refused before any work with one line naming the
option, field or file: one rigid-transform check for every transform the project accepts (calibrations,
the live API's extrinsics and motion, the recorder's poses) with plausibility bounds on a rig's size and
a body's motion; values that are not numbers, not finite or beyond the machine; outputs that would land
on an input, compared as resolved paths (through links too)."""

from __future__ import annotations

import os
import shutil
import threading

import cv2
import numpy as np
import pytest
import torch
import yaml

from fisheyedepth.cameras import PinholeCamera
from fisheyedepth.cli import multiview
from fisheyedepth.data.layouts import RigLayout
from fisheyedepth.files import check_apart
from fisheyedepth.geometry import MAX_MOTION, rigid_transform
from fisheyedepth.geometry.se3 import axis_angle_to_matrix, make_pose
from fisheyedepth.stereo import RigStereo, SgbmSettings, sgbm
from fisheyedepth.utils import cores

from conftest import load_script
from test_multiview import small_rig

CAMERA = PinholeCamera(width=80, height=60, fx=70.0, fy=70.0, cx=39.5, cy=29.5)


def turned(deg: float = 20.0, t=(0.1, 0.0, 0.0)) -> np.ndarray:
    R = axis_angle_to_matrix(torch.tensor([0.0, np.radians(deg), 0.0], dtype=torch.float64))
    return make_pose(R, torch.tensor(t, dtype=torch.float64)).numpy()


# ------------------------------------------------------------------ one rigid-transform check
@pytest.mark.parametrize(
    "T, why",
    [
        (np.diag([2.0, 2.0, 2.0, 1.0]), "its rotation is not orthonormal"),  # a rotation scaled by 2
        (np.array([[1, 0.3, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]), "not orthonormal"),  # shear
        (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0.1, 0, 0, 2.0]]), "last row .* 0 0 0 1"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "det -1 \\(a reflection"),
        (np.zeros((4, 4)), "last row"),
        (np.eye(3), "a 4x4 \\(or 3x4\\) rigid transform expected, got shape \\(3, 3\\)"),
        ("identity", "a 4x4 matrix of numbers expected, got str 'identity'"),
        (np.where(np.eye(4) > 0, np.nan, 0.0), "not finite"),
    ],
)
def test_a_transform_that_is_not_rigid_is_named_with_why(T, why):
    with pytest.raises(ValueError, match=rf"^motion: not a rigid transform: .*{why}|^motion: .*{why}"):
        rigid_transform(T, "motion")


def test_a_rigid_transform_passes_as_4x4_float64_from_any_form():
    T = turned(30.0, (0.2, -0.1, 1.5))
    for given in (T, T[:3], torch.from_numpy(T).float(), T.tolist()):
        out = rigid_transform(given, "T")
        assert out.shape == (4, 4) and out.dtype == np.float64 and np.allclose(out, T, atol=1e-6)


def test_the_live_api_checks_its_extrinsics_and_its_motion():
    cameras = {"a": CAMERA, "b": CAMERA}
    good = {"a": np.eye(4), "b": turned()}
    RigStereo(cameras, good)  # accepted
    scaled = {"a": np.eye(4), "b": np.diag([1.5, 1.5, 1.5, 1.0])}
    with pytest.raises(ValueError, match=r"^cam_to_body\['b'\]: not a rigid transform: its rotation"):
        RigStereo(cameras, scaled)
    nan = {
        "a": np.eye(4),
        "b": np.where(np.eye(4) > 0, 1.0, 0.0) + np.array([[0, 0, 0, np.nan]] + [[0] * 4] * 3),
    }
    with pytest.raises(ValueError, match=r"^cam_to_body\['b'\]: not a rigid transform: .*not finite"):
        RigStereo(cameras, nan)
    with pytest.raises(ValueError, match=r"^cam_to_body\['b'\]: a 4x4 \(or 3x4\)"):
        RigStereo(cameras, {"a": np.eye(4), "b": np.eye(3)})
    millimetres = {"a": np.eye(4), "b": turned(20.0, (200.0, 0.0, 0.0))}  # 0.2 m written as 200
    with pytest.raises(ValueError, match=r"cameras 'a' and 'b' lie 200 m apart.*millimetres\?"):
        RigStereo(cameras, millimetres)
    rig = RigStereo(cameras, good)
    images = {n: np.full((60, 80), 100, np.uint8) for n in cameras}
    wrong = [(np.diag([2.0, 2.0, 2.0, 1.0]), "not orthonormal"), (np.zeros((4, 4)), "last row"),
             (np.diag([1.0, -1.0, 1.0, 1.0]), "det -1"), ("identity", "matrix of numbers")]  # fmt: skip
    for motion, why in wrong:
        with pytest.raises(ValueError, match=rf"^motion: .*{why}"):
            rig(images, previous=images, motion=motion)
    far = turned(0.0, (0.0, 0.0, 2 * MAX_MOTION))  # odometry in decimetres, say: not matched, and named
    out = rig(images, previous=images, motion=far)
    for name in cameras:
        assert f"{name}@previous" not in out[name].partners
        assert "moved 20 m since the previous instant" in out[name].left_out[f"{name}@previous"]


def test_a_rig_yaml_whose_cameras_lie_hundreds_of_metres_apart_is_refused(tmp_path):
    rec = tmp_path / "rec"
    shutil.copytree(small_rig(tmp_path.parent / "small_rig"), rec)
    rig = yaml.safe_load((rec / "rig.yaml").read_text())
    rig["cameras"][1]["cam_to_body"][0][3] = 300.0  # millimetres
    (rec / "rig.yaml").write_text(yaml.safe_dump(rig))
    with pytest.raises(
        ValueError, match=r"rig.yaml: key 'cameras\[\].cam_to_body': cameras 'left' and 'right' lie 300.3 m"
    ):
        RigLayout(rec)


def test_the_recorder_refuses_poses_that_are_not_rigid_and_values_that_are_not_numbers(tmp_path):
    pytest.importorskip("rerun")
    from fisheyedepth.rerun3d import CameraView, RigRecorder

    with pytest.raises(ValueError, match="points_per_image: nan; a whole number"):
        RigRecorder(tmp_path / "a.rrd", points_per_image=float("nan"))
    view = CameraView(CAMERA, np.zeros((60, 80, 3), np.uint8), {})
    with RigRecorder(tmp_path / "b.rrd") as recorder:
        with pytest.raises(ValueError, match=r"^body_to_world: not a rigid transform: its rotation"):
            recorder.instant(
                0, 0, {"a": view}, body_to_world=np.diag([3.0, 3.0, 3.0, 1.0])
            )  # a world 3x too big
        with pytest.raises(ValueError, match="timestamp_ns: 18446744073709551616; a whole number within"):
            recorder.instant(2**64, 0, {"a": view})
        with pytest.raises(ValueError, match=r"views\['a'\].scores\['abs_rel'\]: '0.1'; a number or None"):
            recorder.instant(0, 0, {"a": CameraView(CAMERA, view.image, {}, scores={"abs_rel": "0.1"})})
        recorder.instant(0, 0, {"a": view})


# ------------------------------------------------------------------ values
def test_the_live_api_names_values_it_cannot_use():
    cameras = {"a": CAMERA, "b": CAMERA}
    extrinsics = {"a": np.eye(4), "b": turned()}
    for threads in (0, float("nan"), 2.0, cores() + 1, 999):
        with pytest.raises(
            ValueError, match=r"^threads: .*; a whole number from 1 to \d+ \(this machine's cores\)"
        ):
            RigStereo(cameras, extrinsics, threads=threads)
    with pytest.raises(ValueError, match=r"^min_distance: '0.5'; a number expected"):
        SgbmSettings(min_distance="0.5")
    with pytest.raises(ValueError, match=r"^masks\['a'\]: 1 values are not finite"):
        mask = np.ones((60, 80), np.float32)
        mask[3, 4] = np.nan
        RigStereo(cameras, extrinsics, masks={"a": mask})
    with pytest.raises(ValueError, match=r"^masks\['b'\]: no pixel is usable \(all zero\)"):
        RigStereo(cameras, extrinsics, masks={"b": np.zeros((60, 80), bool)})  # kept nothing, unsaid
    rig = RigStereo(cameras, extrinsics)
    images = {n: np.full((60, 80), 100.0, np.float32) for n in cameras}
    with pytest.raises(ValueError, match=r"^images: a mapping of camera name -> image expected, got list"):
        rig(list(images.values()))
    patched = {**images, "b": images["b"].copy()}
    patched["b"][10:40, 10:40] = np.nan  # a 30x30 NaN patch would blank the whole match
    with pytest.raises(ValueError, match=r"^images\['b'\]: 900 values are not finite \(NaN or inf\)"):
        rig(patched)


def test_concurrent_calls_leave_the_process_thread_counts_as_they_were():
    cameras = {"a": CAMERA, "b": CAMERA}
    rig = [RigStereo(cameras, {"a": np.eye(4), "b": turned()}, threads=2) for _ in range(3)]
    images = {n: np.random.default_rng(0).integers(0, 255, (60, 80), dtype=np.uint8) for n in cameras}
    before = cv2.getNumThreads(), torch.get_num_threads()
    calls = [threading.Thread(target=r, args=(images,)) for r in rig]
    for call in calls:
        call.start()
    for call in calls:
        call.join()
    assert (cv2.getNumThreads(), torch.get_num_threads()) == before


def test_the_sweep_refuses_zero_hypotheses(tmp_path, capsys):
    rec = small_rig(tmp_path.parent / "small_rig")
    assert (
        multiview.main([str(rec), "--out", str(tmp_path / "out"), "--matcher", "sweep", "--hypotheses", "0"])
        == 2
    )
    assert "hypotheses: 0; at least 3" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------ paths, resolved
def test_an_output_through_a_link_onto_an_input_is_refused(tmp_path):
    data = tmp_path / "in" / "rec"
    data.mkdir(parents=True)
    (tmp_path / "out").mkdir()
    os.symlink(data, tmp_path / "out" / "lnk")
    for out, how in ((tmp_path / "out" / "lnk", "is"), (tmp_path / "out" / "lnk" / "mv", "lies inside"),
                     (tmp_path / "in", "holds")):  # fmt: skip
        with pytest.raises(ValueError, match=rf"^--out: {out} {how} the recording {data}"):
            check_apart(out, "--out", {"the recording": data})
    with pytest.raises(ValueError, match=r"\(through a link\)"):
        check_apart(tmp_path / "out" / "lnk", "--out", {"the recording": data})
    check_apart(tmp_path / "out" / "elsewhere", "--out", {"the recording": data})  # apart: no error


def test_the_commands_never_write_into_what_they_read_through_a_link(tmp_path, capsys):
    rec = tmp_path / "in" / "rec"
    shutil.copytree(small_rig(tmp_path.parent / "small_rig"), rec)
    before = {p: p.read_bytes() for p in rec.rglob("*") if p.is_file()}
    (tmp_path / "out").mkdir()
    os.symlink(rec, tmp_path / "out" / "lnk")
    for out in (tmp_path / "out" / "lnk", tmp_path / "out" / "lnk" / "mv"):
        assert multiview.main([str(rec), "--out", str(out), "--overwrite"]) == 2
        assert "the recording" in capsys.readouterr().err
    assert multiview.main([str(tmp_path / "out" / "lnk"), "--out", str(rec / "mv")]) == 2  # ROOT via a link
    assert "lies inside the recording" in capsys.readouterr().err
    live_rig = load_script("tools/live_rig")
    assert live_rig.main([str(rec), "--out", str(rec / "rig.yaml"), "--overwrite"]) == 2
    assert "--out: " in capsys.readouterr().err
    assert {p: p.read_bytes() for p in rec.rglob("*") if p.is_file()} == before  # nothing written or lost


# ------------------------------------------------------------------ recordings that fail, signals
def test_a_recording_that_cannot_be_written_is_one_error_and_leaves_nothing(tmp_path):
    pytest.importorskip("rerun")
    from fisheyedepth.rerun3d import CameraView, RecordingError, RigRecorder

    (tmp_path / "folder.rrd").mkdir()
    with pytest.raises(ValueError, match=r"folder.rrd: a folder; a recording is a file"):
        RigRecorder(tmp_path / "folder.rrd")
    target = tmp_path / "rec.rrd"
    recorder = RigRecorder(target)
    recorder.instant(0, 0, {"a": CameraView(CAMERA, np.zeros((60, 80, 3), np.uint8), {})})

    def stopped(**kwargs):
        raise RuntimeError("File-writer thread shut down prematurely")

    recorder.stream.flush = stopped  # what the SDK raises when the disk fills under it
    with pytest.raises(RecordingError, match=r"rec.rrd: the recording could not be written .*full disk"):
        recorder.close()
    assert not target.exists() and not list(tmp_path.glob(".rec.rrd.*"))


def test_a_recording_whose_writer_does_not_finish_in_time_is_one_error(tmp_path, monkeypatch):
    """The SDK's flush waits for ever by default: the recorder bounds it (``FLUSH_SECONDS``, asked in
    slices of a second), and a writer that has not finished by then (the SDK's own timeout error) is a
    RecordingError saying so, nothing at the path. A writer whose file stops growing at a file-size limit
    or on a full disk has stopped: named after ``STALLED_SECONDS``, not at the bound."""
    pytest.importorskip("rerun")
    import time

    from fisheyedepth import rerun3d
    from fisheyedepth.rerun3d import CameraView, RecordingError, RigRecorder

    assert rerun3d.FLUSH_SECONDS == 300.0 and rerun3d.STALLED_SECONDS == 2.0
    asked = []

    def slow(timeout_sec=1e38):  # what rerun 0.41 does when the timeout passes
        asked.append(timeout_sec)
        time.sleep(timeout_sec)
        raise RuntimeError("Flush timed out - not all log messages were sent")

    stopped = "the writer stopped at \\d+ bytes; a full disk or a file-size limit"
    for limited, why in ((False, "its writer did not finish within 3 s"), (True, stopped)):
        monkeypatch.setattr(rerun3d, "FLUSH_SECONDS", 10.0 if limited else 3.0)  # the bound, shortened
        monkeypatch.setattr(rerun3d, "at_a_limit", lambda path, limited=limited: limited)
        target = tmp_path / "rec.rrd"
        recorder = RigRecorder(target)
        recorder.instant(0, 0, {"a": CameraView(CAMERA, np.zeros((60, 80, 3), np.uint8), {})})
        recorder.stream.flush, asked[:] = slow, []
        began = time.monotonic()
        with pytest.raises(RecordingError, match=rf"rec.rrd: the recording could not be written \({why}"):
            recorder.close()
        assert all(0 < t <= 1.0 for t in asked) and not list(tmp_path.iterdir())  # nothing at its path
        took = time.monotonic() - began
        assert (2.0 <= took < 7.0) if limited else (2.9 <= took < 4.5), took  # stalled: named, not at 10 s


def test_a_recording_stopped_by_a_file_size_limit_names_it_in_one_line(tmp_path):
    """The SDK's writer stops at ``ulimit -f`` saying only that it stopped: the error names the limit,
    and the SDK's own log lines stay out of the command's output. A writer that hung would print every
    thread's stack after 90 s (and fail), not hold the suite."""
    pytest.importorskip("rerun")
    import subprocess
    import sys

    code = f"""
import faulthandler, resource, sys
faulthandler.dump_traceback_later(90, exit=True)
import numpy as np
from fisheyedepth.cameras import PinholeCamera
from fisheyedepth.rerun3d import CameraView, RecordingError, RigRecorder
camera = PinholeCamera(width=320, height=240, fx=200.0, fy=200.0, cx=159.5, cy=119.5)
rng = np.random.default_rng(0)
try:
    with RigRecorder({str(tmp_path / "rec.rrd")!r}) as recorder:  # rerun imported and started first
        resource.setrlimit(resource.RLIMIT_FSIZE, (300_000, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
        for i in range(40):  # noise: about 100 kB an instant as JPEG
            image = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
            recorder.instant(i, i, {{"a": CameraView(camera, image, {{}})}})
except RecordingError as err:
    print(f"error: {{err}}", file=sys.stderr)
    sys.exit(2)
"""
    env = {k: v for k, v in os.environ.items() if k != "RUST_LOG"}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=150, env=env)
    assert done.returncode == 2, done.stderr[-6000:]
    assert done.stderr.strip().splitlines() == [
        f"error: {tmp_path / 'rec.rrd'}: the recording could not be written (the file-size limit of this "
        "process, 300000 bytes (ulimit -f))"
    ]
    assert not list(tmp_path.iterdir())  # nothing at its path, no temporary


def test_a_killed_writers_temporary_is_removed_by_the_next_run(tmp_path):
    pytest.importorskip("rerun")
    from fisheyedepth.rerun3d import RigRecorder

    dead = tmp_path / ".rec.rrd.abc123.999999999.tmp"  # no process has this pid
    alive = tmp_path / f".rec.rrd.def456.{os.getpid()}.tmp"
    dead.write_bytes(b"x" * 100)
    alive.write_bytes(b"x")
    with RigRecorder(tmp_path / "rec.rrd"):
        pass
    assert not dead.exists() and alive.exists() and (tmp_path / "rec.rrd").is_file()


def _started(args, until: str, cwd):
    """A command started as a new process, read until a line holds ``until``."""
    import subprocess
    import sys

    pipes = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE}
    process = subprocess.Popen([sys.executable, *args], cwd=cwd, text=True, **pipes,
                               env={**os.environ, "PYTHONUNBUFFERED": "1"})  # fmt: skip
    for line in process.stdout:
        if until in line:
            return process
    process.wait()
    raise AssertionError(f"{args}: ended before {until!r}: {process.stderr.read()}")


@pytest.mark.parametrize("signum, status", [(2, 130), (15, 143)])
def test_the_live_rig_stopped_by_a_signal_keeps_the_instants_it_finished(tmp_path, signum, status):
    pytest.importorskip("rerun")
    from test_rerun import Recording

    from conftest import ROOT
    from test_multiview import write_room_rig

    write_room_rig(tmp_path / "rec", size=128, half_baseline=0.3)
    out = tmp_path / "live.rrd"
    args = [str(ROOT / "scripts/tools/live_rig.py"), str(tmp_path / "rec"), "--out", str(out),
            "--threads", "1", "--min-distance", "0.5", "--max-distance", "20", "--points", "500"]  # fmt: skip
    process = _started(args, "instant 1/3", tmp_path)
    process.send_signal(signum)
    _, err = process.communicate(timeout=120)
    if process.returncode == 0:  # the replay finished before the signal arrived: a whole recording
        assert out.is_file() and not list(tmp_path.glob(".live.rrd*"))
        return
    assert process.returncode == status, err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("error: ")
    assert "keeps them" in err  # stopped after one or two instants: a closed, valid recording of them
    frames = {r["frame"] for r in Recording(out).rows["/world/points/left/kept"]}
    assert 1 <= len(frames) <= 2
    assert not list(tmp_path.glob(".live.rrd*"))


@pytest.mark.parametrize(
    "signum, status, said", [(2, 130, "interrupted (SIGINT)"), (15, 143, "terminated (SIGTERM)")]
)
def test_the_multiview_command_stopped_by_a_signal_leaves_nothing(
    tmp_path, monkeypatch, capsys, signum, status, said
):
    import signal

    rec = small_rig(tmp_path.parent / "small_rig")
    out = tmp_path / "out"
    calls = []
    fuse = sgbm.fuse

    def signalled_on_the_second(*args, **kwargs):  # the signal arrives halfway through the run
        calls.append(1)
        if len(calls) == 2:
            signal.raise_signal(signum)
        return fuse(*args, **kwargs)

    monkeypatch.setattr(sgbm, "fuse", signalled_on_the_second)
    assert multiview.main([str(rec), "--out", str(out)]) == status
    err = capsys.readouterr().err
    assert f"error: {said}; nothing was written to {out}" in err and "Traceback" not in err
    assert not out.exists() and not list(tmp_path.glob(".out*"))  # no output, no staging, no lock


def test_predict_refuses_an_image_too_small_to_hold_one_feature_of_the_network(tmp_path):
    from fisheyedepth.inference import MIN_IMAGE_SIDE, check_aspect

    square = PinholeCamera(width=64, height=64, fx=50.0, fy=50.0, cx=31.5, cy=31.5)
    with pytest.raises(ValueError, match=rf"frame.png: image is 1x1; at least {MIN_IMAGE_SIDE} pixels"):
        check_aspect(tmp_path / "frame.png", (1, 1), square, "cam.yaml")
    check_aspect(tmp_path / "frame.png", (32, 32), square, "cam.yaml")  # the smallest it takes


def test_an_option_of_the_wrong_kind_is_one_line_in_every_console_script(tmp_path, capsys):
    """argparse's refusals (a value of the wrong type, a missing option) as one ``error:`` line and exit
    2, like every other refused input, not its usage block (``cli.CommandParser``)."""
    from fisheyedepth.cli import estimate_mask, import_aria, import_ddad, import_rosbag, synthetic

    cases = [
        (multiview.main, [str(tmp_path), "--out", str(tmp_path / "o"), "--threads", "2.5"],
         "error: argument --threads: invalid int value: '2.5' (see fisheyedepth-multiview --help)"),
        (import_aria.main, ["--src", str(tmp_path)], "error: the following arguments are required: --out"),
        (import_ddad.main, ["--out", str(tmp_path)], "error: the following arguments are required: --src"),
        (import_rosbag.main, [str(tmp_path), "--out", "o", "--camera", "a=/a"], "one of the arguments"),
        (estimate_mask.main, ["--root", str(tmp_path), "--sequence", "s", "--camera", "c", "--frames", "x"],
         "error: argument --frames: invalid int value: 'x'"),
        (synthetic.main, ["--out", str(tmp_path / "w"), "--frames", "many"], "invalid int value: 'many'"),
    ]  # fmt: skip
    for main, args, said in cases:
        with pytest.raises(SystemExit) as stopped:
            main(args)
        err = capsys.readouterr().err
        assert stopped.value.code == 2 and said in err and err.startswith("error: "), err
        assert len(err.strip().splitlines()) == 1 and "usage:" not in err


SIGNALS = [(2, 130, "interrupted (SIGINT)"), (15, 143, "terminated (SIGTERM)")]


@pytest.mark.parametrize("signum, status, said", SIGNALS)
def test_train_eval_export_and_predict_stopped_by_a_signal_end_with_one_line_and_its_status(
    capsys, signum, status, said
):
    """``run_command`` (train.py, eval.py, export.py, predict.py): the signal's status, one line, no
    traceback, SIGTERM's handler as it was before."""
    import signal

    from fisheyedepth.cli import run_command

    before = signal.getsignal(signal.SIGTERM)
    done = []

    def command(cfg):
        signal.raise_signal(signum)
        done.append(cfg)  # never reached: the signal ends it where it arrives

    with pytest.raises(SystemExit) as stopped:
        run_command(command, {"any": "config"})
    assert stopped.value.code == status and not done
    assert capsys.readouterr().err == f"error: {said}\n"
    assert signal.getsignal(signal.SIGTERM) is before


@pytest.mark.parametrize("signum, status, said", SIGNALS)
def test_the_other_commands_stopped_by_a_signal_end_with_one_line_and_write_nothing(
    tmp_path, monkeypatch, capsys, signum, status, said
):
    """``fisheyedepth-estimate-mask`` and ``scripts/tools`` (``signals.ends_on_signals``): stopped while it
    reads the recording, the command returns the signal's status with one line and writes nothing."""
    import signal

    from fisheyedepth.cli import estimate_mask
    from fisheyedepth.data import body_mask
    from test_faults_inputs import still_rig

    still_rig(tmp_path / "rec")
    opened = body_mask.open_layout

    def signalled(*args):
        signal.raise_signal(signum)
        return opened(*args)

    monkeypatch.setattr(body_mask, "open_layout", signalled)
    before = signal.getsignal(signal.SIGTERM)
    args = ["--root", str(tmp_path / "rec"), "--layout", "rig", "--sequence", "seq0", "--camera", "cam"]
    assert estimate_mask.main(args) == status
    assert capsys.readouterr().err == f"error: {said}\n"
    assert not (tmp_path / "rec" / "masks").exists() and signal.getsignal(signal.SIGTERM) is before


@pytest.mark.parametrize("signum, status", [(2, 130), (15, 143)])
def test_an_importer_stopped_by_a_signal_writes_nothing(tmp_path, monkeypatch, capsys, signum, status):
    import signal

    from fisheyedepth.cli import import_aria
    from fisheyedepth.data import aria
    from test_faults_inputs import aria_export

    src = aria_export(tmp_path / "src")
    calls = []
    read = aria.read_aria_poses

    def signalled(*args):  # the signal arrives while it converts
        calls.append(1)
        signal.raise_signal(signum)
        return read(*args)

    monkeypatch.setattr(aria, "read_aria_poses", signalled)
    assert import_aria.main(["--src", str(src), "--out", str(tmp_path / "rig")]) == status
    err = capsys.readouterr().err
    assert calls and "nothing was written to" in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]  # no output, no staging


def test_predict_never_writes_into_its_input(tmp_path):
    from fisheyedepth.plan import predict_plan

    from conftest import load_cfg

    images = tmp_path / "images"
    images.mkdir()
    (tmp_path / "elsewhere").mkdir()
    os.symlink(images, tmp_path / "elsewhere" / "lnk")
    for output, how in (
        (images, "is"),
        (tmp_path / "elsewhere" / "lnk", "is"),
        (images / "out", "lies inside"),
    ):
        cfg = load_cfg(
            "predict", ckpt_path="run/last.ckpt", input=str(images), camera="c.yaml", output=str(output)
        )
        with pytest.raises(ValueError, match=rf"^output: {output} {how} the input {images}"):
            predict_plan(cfg)
