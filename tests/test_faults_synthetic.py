"""Faults around rendering the synthetic dataset: a user's folder is never replaced, a killed
render leaves no worker processes and no hidden temporary folder behind, a parameter not of its kind or
range (a flag or a ``data.generate`` option) is refused by name before anything is written."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fisheyedepth.cli.synthetic import main as cli_main
from fisheyedepth.synthetic import (
    MARKER,
    DatasetMismatch,
    NotASyntheticDataset,
    Terminated,
    WorldSpec,
    ensure_dataset,
    ensure_datasets,
    generate,
    is_complete,
    made_by_generator,
)
from fisheyedepth.synthetic.folder import OWNER
from fisheyedepth.synthetic.frames import FrameRenderer
from fisheyedepth.synthetic.sensor import check_effects

TINY = {"frames": 9, "size": 16, "supersample": 1}  # a tiny spec
QUIET = {"lidar": False, "progress": False}  # rendered without LiDAR or a progress bar
# long enough to be killed mid-render on two cores: ~15 s of rendering after the first image
SLOW = {"frames": 60, "size": 64, "supersample": 1}
linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")


def snapshot(root: Path) -> dict[str, tuple[bytes, int]]:
    """Every file under ``root`` with its bytes and modification time."""
    return {
        str(p.relative_to(root)): (p.read_bytes(), p.stat().st_mtime_ns)
        for p in root.rglob("*")
        if p.is_file()
    }


def hidden_siblings(out: Path) -> list[Path]:
    return sorted(out.parent.glob(f".{out.name}.*"))


def dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def user_folder(root: Path) -> Path:
    (root / "images" / "cam0").mkdir(parents=True)
    (root / "images" / "cam0" / "000001.png").write_bytes(b"\x89PNG not really")
    (root / "poses.txt").write_text("0 1 0 0 0 0 1 0 0 0 0 1 0\n")
    (root / ".hidden").write_text("mine")
    return root


# ---------------------------------------------------------------- what ensure_dataset may replace


def test_a_folder_it_did_not_make_is_refused_and_left_untouched(tmp_path):
    root = user_folder(tmp_path / "my_robot")
    before = snapshot(root)
    with pytest.raises(NotASyntheticDataset) as err:
        ensure_dataset(root, WorldSpec(**TINY), **QUIET)
    assert isinstance(err.value, FileExistsError)
    message = str(err.value)
    for words in (str(root), "not a synthetic dataset made by fisheyedepth", "left untouched"):
        assert words in message
    assert "data=kitti360" in message and "data=rig" in message
    assert snapshot(root) == before
    assert not hidden_siblings(root) and not is_complete(root)


def test_a_file_and_a_foreign_synthetic_json_are_refused(tmp_path):
    file = tmp_path / "notes"
    file.write_text("mine")
    with pytest.raises(NotASyntheticDataset, match="a file"):
        ensure_dataset(file, WorldSpec(**TINY), **QUIET)
    assert file.read_text() == "mine"
    other = tmp_path / "other"
    other.mkdir()
    (other / "synthetic.json").write_text(json.dumps({"generator": "blender 4.1", "size": 16}))
    before = snapshot(other)
    with pytest.raises(NotASyntheticDataset, match="left untouched"):
        ensure_dataset(other, WorldSpec(**TINY), **QUIET)
    assert snapshot(other) == before


def test_an_absent_or_empty_folder_is_rendered(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    for root in (empty, tmp_path / "absent" / "deeper"):
        assert ensure_dataset(root, WorldSpec(**TINY), **QUIET) == root
        assert is_complete(root) and made_by_generator(root) and (root / MARKER).is_file()
        assert not hidden_siblings(root)


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """A finished TINY dataset (seed 1), rendered once for the tests that start from one: each takes a
    copy (:func:`copy_of`)."""
    return generate(tmp_path_factory.mktemp("finished") / "d", WorldSpec(seed=1, **TINY), **QUIET)


def copy_of(finished: Path, root: Path) -> Path:
    """``root``: a copy of the ``finished`` dataset, as ``generate(root, WorldSpec(seed=1, **TINY))``
    leaves it."""
    shutil.copytree(finished, root)
    assert is_complete(root) and made_by_generator(root)
    return root


def test_a_folder_the_generator_started_is_rendered_again(finished, tmp_path):
    root = copy_of(finished, tmp_path / "d")
    (root / "synthetic.json").unlink()  # damaged: the marker says the generator made it
    (root / "leftover.png").write_bytes(b"old")
    assert made_by_generator(root) and not is_complete(root)
    ensure_dataset(root, WorldSpec(seed=1, **TINY), **QUIET)
    assert is_complete(root) and not (root / "leftover.png").exists()
    only_marker = tmp_path / "m"
    only_marker.mkdir()
    (only_marker / MARKER).write_text("")
    ensure_dataset(only_marker, WorldSpec(seed=1, **TINY), **QUIET)
    assert is_complete(only_marker)


def test_a_finished_dataset_is_reused_only_with_the_same_parameters(finished, tmp_path):
    root = copy_of(finished, tmp_path / "d")
    (root / "notes.txt").write_text("kept")
    before = snapshot(root)
    assert ensure_dataset(root, WorldSpec(seed=1, **TINY), **QUIET) == root
    assert snapshot(root) == before  # not rendered again
    with pytest.raises(DatasetMismatch) as err:
        ensure_dataset(root, WorldSpec(**{**TINY, "seed": 2, "size": 24}), **QUIET)
    message = str(err.value)
    assert str(root) in message and "size 16 (asked 24)" in message and "seed 1 (asked 2)" in message
    assert "frames" not in message and "rig " not in message
    assert snapshot(root) == before


def test_cli_overwrite_says_what_it_replaces(tmp_path, capsys):
    args = ["--frames", "9", "--size", "16", "--supersample", "1", "--no-lidar", "--quiet", "--overwrite"]
    mine = user_folder(tmp_path / "mine")
    assert cli_main(["--out", str(mine), *args]) == 0
    assert f"{mine} (NOT a dataset made by fisheyedepth" in capsys.readouterr().err
    assert is_complete(mine)
    assert cli_main(["--out", str(mine), *args]) == 0
    assert "(a synthetic dataset made by fisheyedepth)" in capsys.readouterr().err


DENSITY = "(0: no traffic, 1: a busy street)"
REFUSED_FLAGS = {
    # had not rendered 9 frames of 64 px after 400 s: the agents' tracks take the square of the density
    ("--traffic", "1000"): f"--traffic: 1000.0 is not a number in [0, 8] {DENSITY}",
    ("--traffic", "nan"): f"--traffic: nan is not a number in [0, 8] {DENSITY}",
    ("--frames", "5"): "--frames: 5 is not a whole number >= 9 (3 per split)",
    ("--supersample", "0"): "--supersample: 0 is not a whole number >= 1",
    ("--seed", "-1"): "--seed: -1 is not a whole number >= 0",
    ("--workers", "-2"): "--workers: -2 is not a whole number >= 0",
}


def test_cli_flags_are_checked_as_data_generate_is_before_anything_is_written(tmp_path, capsys):
    """Each flag of a generation parameter by the kind and range of its ``data.generate`` option, named
    as typed: the dataset folder is not made, a user's folder under ``--overwrite`` not even announced."""
    for (flag, value), message in REFUSED_FLAGS.items():
        assert cli_main(["--out", str(tmp_path / "d"), "--size", "64", flag, value, "--quiet"]) == 2, flag
        assert capsys.readouterr().err == f"error: {message}\n"
    assert list(tmp_path.iterdir()) == []
    mine = user_folder(tmp_path / "mine")
    before = snapshot(mine)
    assert cli_main(["--out", str(mine), "--overwrite", "--traffic", "9", "--quiet"]) == 2
    assert capsys.readouterr().err == f"error: --traffic: 9.0 is not a number in [0, 8] {DENSITY}\n"
    assert snapshot(mine) == before and not hidden_siblings(mine)


def test_effects_are_names_and_parameters_are_checked_before_rendering(tmp_path):
    """An effect is a switch: ``effects=[{noise: -1}]`` was a TypeError traceback (a dict in a set)."""
    effects = "exposure, white_balance, vignetting, noise, motion_blur"
    named_alone = (
        rf"^effects\[0\]: \{{'noise': -1\}} is not one of {effects} \(each effect a switch, named alone\)$"
    )
    with pytest.raises(ValueError, match=named_alone):
        generate(tmp_path / "d", WorldSpec(effects=[{"noise": -1}], **TINY), **QUIET)
    with pytest.raises(ValueError, match=r"^data\.generate\.effects\[0\]: \{'noise': -1\} is not one of"):
        ensure_datasets(tmp_path / "d", {"effects": [{"noise": -1}], **TINY, **QUIET})
    with pytest.raises(ValueError, match=r"^random_cameras: 'maybe' is not a boolean \(true or false\)$"):
        ensure_dataset(tmp_path / "d", WorldSpec(random_cameras="maybe", **TINY), **QUIET)
    with pytest.raises(
        ValueError, match=r"^data\.generate\.worlds\[1\]\.traffic: 9 is not a number in \[0, 8\]"
    ):
        ensure_datasets(
            [tmp_path / "a", tmp_path / "b"], {**TINY, **QUIET, "worlds": [{"seed": 0}, {"traffic": 9}]}
        )
    with pytest.raises(ValueError, match=r"^effects: unknown \[\{'noise': -1\}\]"):  # where it is read, too
        check_effects([{"noise": -1}])
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------- interruptions in this process


def test_sigterm_while_rendering_cleans_up_and_restores_the_handler(tmp_path, monkeypatch):
    calls = {"n": 0}
    original = FrameRenderer.__call__

    def terminated_midway(self, job):
        calls["n"] += 1
        if calls["n"] == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return original(self, job)

    monkeypatch.setattr(FrameRenderer, "__call__", terminated_midway)
    previous = signal.getsignal(signal.SIGTERM)
    out = tmp_path / "d"
    with pytest.raises(Terminated) as err:
        generate(out, WorldSpec(**TINY), **QUIET)
    assert err.value.code == 143 and isinstance(err.value, SystemExit)
    assert calls["n"] == 3  # stopped at once, not after the last frame
    assert not out.exists() and not hidden_siblings(out)
    assert signal.getsignal(signal.SIGTERM) is previous


def test_a_stale_temporary_folder_of_a_dead_run_is_removed(tmp_path):
    out = tmp_path / "d"
    dead, alive = dead_pid(), os.getppid()
    for name, owner in (
        (f".d.partial-{dead}", None),
        (f".d.old-{dead}", None),
        (f".d.partial-{alive}", None),  # still rendering: kept
        (f".d.partial-{dead + 1_000_000}", "another-host 1"),  # can't tell from here: kept
    ):
        (tmp_path / name / "calibration").mkdir(parents=True)
        if owner:
            (tmp_path / name / OWNER).write_text(owner)
    (tmp_path / ".other.partial-1").mkdir()  # another dataset's
    generate(out, WorldSpec(**TINY), **QUIET)
    assert is_complete(out) and not (out / OWNER).exists()
    left = sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("."))
    assert left == sorted([".other.partial-1", f".d.partial-{alive}", f".d.partial-{dead + 1_000_000}"])
    assert socket.gethostname() != "another-host"


# ---------------------------------------------------------------- killing a rendering process


def proc_stat(pid: int) -> list[str] | None:
    """Fields 3.. of /proc/<pid>/stat (state, ppid, ..., starttime at index 19); None when gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def multiprocessing_children(pid: int) -> dict[int, str]:
    """{pid: start time} of the live children of ``pid`` started by multiprocessing (workers, tracker)."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        stat = proc_stat(int(entry.name))
        if stat is None or stat[0] == "Z" or int(stat[1]) != pid:
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        if b"multiprocessing" in cmdline:
            found[int(entry.name)] = stat[19]
    return found


def still_running(processes: dict[int, str]) -> list[int]:
    """The processes (pid, start time) that are alive: not gone, not a zombie, not a reused pid."""
    alive = []
    for pid, start in processes.items():
        stat = proc_stat(pid)
        if stat is not None and stat[0] != "Z" and stat[19] == start:
            alive.append(pid)
    return alive


def wait_mid_render(proc: subprocess.Popen, out: Path, timeout: float = 90) -> dict[int, str]:
    """Wait until ``proc`` has written a frame into its temporary folder; returns its worker processes."""
    workers: dict[int, str] = {}
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"the render ended (status {proc.returncode}) before it was killed"
        workers.update(multiprocessing_children(proc.pid))
        frames = list(out.parent.glob(f".{out.name}.partial-*/data_2d_raw/*/*/data_rgb/*.png"))
        if frames and len(workers) >= 2:
            return workers
        time.sleep(0.1)
    proc.kill()
    raise AssertionError(f"no frame rendered into {out} within {timeout} s")


def assert_gone(processes: dict[int, str], within: float = 5.0) -> None:
    deadline = time.monotonic() + within
    while still_running(processes) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not still_running(processes), f"still running: {still_running(processes)}"


def render_in_python(out: Path) -> subprocess.Popen:
    """What train.py does on first use: ``ensure_dataset`` with two workers, in the calling process."""
    args = ", ".join(f"{k}={v}" for k, v in SLOW.items())
    code = (
        "import sys\n"
        "from fisheyedepth.synthetic import WorldSpec, ensure_dataset\n"
        f"ensure_dataset(sys.argv[1], WorldSpec({args}), workers=2, lidar=False, progress=False)\n"
    )
    return subprocess.Popen([sys.executable, "-c", code, str(out)], stderr=subprocess.PIPE)


@linux_only
def test_sigterm_of_make_synthetic_stops_the_workers_and_removes_the_partial_folder(tmp_path):
    out = tmp_path / "d"
    cmd = [sys.executable, "-m", "fisheyedepth.cli.synthetic", "--out", str(out)]
    cmd += [f"--{k}={v}" for k, v in SLOW.items()] + ["--workers=2", "--no-lidar", "--quiet"]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE)
    workers = wait_mid_render(proc, out)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 143, err.decode()
    assert "terminated (SIGTERM)" in err.decode()
    assert not out.exists() and not hidden_siblings(out)
    assert_gone(workers)


@linux_only
def test_sigterm_of_the_first_use_render_stops_the_workers(tmp_path):
    out = tmp_path / "d"
    proc = render_in_python(out)
    workers = wait_mid_render(proc, out)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 143, err.decode()
    assert not out.exists() and not hidden_siblings(out)
    assert_gone(workers)


@linux_only
def test_workers_die_with_a_killed_render_and_the_next_run_cleans_up(tmp_path):
    out = tmp_path / "d"
    proc = render_in_python(out)
    workers = wait_mid_render(proc, out)
    proc.kill()  # SIGKILL: no cleanup in the process itself
    proc.communicate(timeout=30)
    assert_gone(workers)  # PR_SET_PDEATHSIG
    assert len(hidden_siblings(out)) == 1  # the dead run's .d.partial-<pid>
    ensure_dataset(out, WorldSpec(**TINY), **QUIET)
    assert is_complete(out) and not hidden_siblings(out)
