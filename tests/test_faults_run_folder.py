"""Faults of a training run's folder, its checkpoints and its options: nothing replaced, nothing silent.

A second run into a finished run's folder, two runs into one folder at once, a kill while a checkpoint is
written, sizes the network cannot run at, a resume with another network, a non-numeric option and an ONNX
file whose metadata disagrees with its graph: each is refused with one line naming the folder, file or
option, or survived with the previous checkpoint whole.
"""

from __future__ import annotations

import builtins
import json
import logging
import os
import re
import signal
import socket
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from fisheyedepth.checkpoints import CheckpointError
from fisheyedepth.cli import EXIT_USAGE
from fisheyedepth.cli.export import export
from fisheyedepth.cli.predict import predict
from fisheyedepth.cli.train import train
from fisheyedepth.module import FisheyeDepthModule
from fisheyedepth.runtimes import OnnxRuntime, onnx_metadata

from conftest import ROOT, bare_module, copy_tiny_world
from test_faults_entrypoints import TINY_RUN, images_of, one_line_error, predict_cfg, python

# one epoch of two steps, one validation batch: a run takes a few seconds
TINY_FIT = [
    *TINY_RUN,
    "trainer.max_epochs=1",
    "trainer.limit_train_batches=2",
    "trainer.limit_val_batches=1",
    "logger=none",
]
NEAREST = "each side must be a multiple of 32 (the encoder halves it 5 times); the nearest that can:"


def train_cfg(run: Path, data: Path, *overrides: str):
    """train.py's config for ``run`` as Hydra composes it (``paths.output_dir`` set, no Hydra runtime)."""
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose("train", [*TINY_FIT, f"paths.data_dir={data}", f"paths.output_dir={run}", *overrides])


def snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    """Every file under ``folder`` with its size and modification time: what a refused run must not change."""
    return {
        str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def world(tiny_world, tmp_path_factory):
    """``paths.data_dir`` of these runs, the tiny world already rendered in it."""
    return copy_tiny_world(tiny_world, tmp_path_factory.mktemp("world"))


@pytest.fixture(scope="module")
def first_run(world, tmp_path_factory):
    """One finished tiny run, trained with the system temp folder elsewhere and every file opened for
    writing recorded."""
    base = tmp_path_factory.mktemp("runs")
    elsewhere = base / "system_tmp"
    elsewhere.mkdir()
    writes: list[Path] = []
    real_open = builtins.open

    def recording_open(file, mode="r", *args, **kwargs):
        if isinstance(file, (str, os.PathLike)) and set(mode) & set("wax+"):
            writes.append(Path(file))
        return real_open(file, mode, *args, **kwargs)

    logged: list[str] = []
    handler = logging.Handler(logging.INFO)
    handler.emit = lambda record: logged.append(record.getMessage())
    logger = logging.getLogger("fisheyedepth")
    level = logger.level
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(tempfile, "tempdir", str(elsewhere))
        patch.setenv("TMPDIR", str(elsewhere))
        patch.setattr(builtins, "open", recording_open)
        logger.addHandler(handler)
        logger.setLevel(logging.INFO)
        try:
            train(train_cfg(base / "run", world))
        finally:
            logger.removeHandler(handler)
            logger.setLevel(level)
    root = world / "synthetic_kitti360_64_seed0_f12"  # the world the run trained on
    return SimpleNamespace(
        dir=base / "run", elsewhere=elsewhere, writes=writes, root=root, logged=logged,
        last=base / "run" / "checkpoints" / "last.ckpt", calib=root / "calibration" / "image_02.yaml",
    )  # fmt: skip


def test_a_run_states_its_accelerator(first_run):
    """train.py's default trainer takes the machine's accelerator (CUDA where torch sees a GPU) and says
    which; without a GPU, the CPU."""
    from fisheyedepth.plan import choose_accelerator, describe_accelerator

    assert f"accelerator: {describe_accelerator(choose_accelerator('auto'))}" in first_run.logged


# ------------------------------------------------------------------ one run per folder
def test_a_second_run_into_a_finished_runs_folder_is_refused(first_run, world, capsys):
    run = first_run.dir
    before = snapshot(run)
    assert {"checkpoints/last.ckpt", "checkpoints/best-000.ckpt", "results.json"} <= set(before)
    assert one_line_error(train, train_cfg(run, world), capsys) == (
        f"error: {run}: holds another run's checkpoints (checkpoints/best-000.ckpt, checkpoints/last.ckpt); "
        f"train into a new folder (another hydra.run.dir, or none for a fresh one), or continue that run "
        f"with ckpt_path={run}/checkpoints/last.ckpt"
    )
    assert snapshot(run) == before
    assert json.loads((run / "results.json").read_text())["checkpoint"] == str(
        run / "checkpoints" / "last.ckpt"
    )
    from fisheyedepth.cli.run_folder import check_run_folder

    check_run_folder(run, run / "checkpoints" / "last.ckpt")  # a resume continues in its own folder
    with pytest.raises(FileExistsError, match="holds another run's checkpoints"):
        check_run_folder(run, run.parent / "elsewhere" / "last.ckpt")


def test_a_refused_run_leaves_the_earlier_runs_hydra_folder_and_log(world, tmp_path):
    """Through train.py: Hydra writes .hydra/ and train.log into the run folder before train() runs."""
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.ckpt").write_bytes(b"the first run's")
    (run / ".hydra").mkdir()
    (run / ".hydra" / "config.yaml").write_text("experiment_name: first\n")
    before = snapshot(run)
    proc = python("train.py", f"hydra.run.dir={run}", f"paths.data_dir={world}", *TINY_FIT, timeout=300)
    assert proc.returncode == EXIT_USAGE, proc.stdout[-2000:] + proc.stderr[-2000:]
    last_line = proc.stderr.strip().splitlines()[-1]
    assert last_line.startswith(f"error: {run}: holds another run's checkpoints (checkpoints/last.ckpt); ")
    assert "Traceback" not in proc.stderr
    assert snapshot(run) == before  # no train.log, no new .hydra/, no lock left


def test_a_run_into_a_folder_another_run_has_locked_is_refused(world, tmp_path, capsys, caplog):
    from fisheyedepth.cli.run_folder import LOCK, acquire, release

    run, host = tmp_path / "run", socket.gethostname()
    ready_r, ready_w = os.pipe()
    child = os.fork()
    if child == 0:  # another training process: holds the folder until it is killed
        try:
            acquire(run)
            os.write(ready_w, b"1")
            time.sleep(120)
        finally:
            os._exit(0)
    try:
        assert os.read(ready_r, 1) == b"1"
        assert one_line_error(train, train_cfg(run, world), capsys) == (
            f"error: {run / LOCK}: another training run (process {child} on {host}) is writing into this "
            "folder; wait for it to end, or choose another hydra.run.dir"
        )
        assert sorted(p.name for p in run.iterdir()) == [LOCK]  # nothing else written
    finally:
        os.kill(child, signal.SIGKILL)
        os.waitpid(child, 0)
    assert (run / LOCK).read_text() == f"{child} on {host}\n"  # a killed run cannot remove its lock
    assert acquire(run)  # ... and never blocks the next run
    assert (
        f"taking over the lock of process {child} on {host}, which ended without removing it" in caplog.text
    )
    assert (run / LOCK).read_text() == f"{os.getpid()} on {host}\n"
    release(run)
    assert not (run / LOCK).exists()


# ------------------------------------------------------------------ checkpoints survive a kill
def test_checkpoints_are_written_beside_their_target(first_run):
    folder = first_run.dir / "checkpoints"
    written = [p for p in first_run.writes if ".ckpt" in p.name or p.is_relative_to(first_run.elsewhere)]
    names = {re.sub(r"\.\w+\.\d+\.tmp$", ".PID.tmp", p.name) for p in written}  # .NAME.<random>.<pid>.tmp
    assert names == {".last.ckpt.PID.tmp", ".best-000.ckpt.PID.tmp"}, written
    assert all(p.parent == folder and p.name.endswith(f".{os.getpid()}.tmp") for p in written)
    assert list(first_run.elsewhere.iterdir()) == []
    assert sorted(p.name for p in folder.iterdir()) == ["best-000.ckpt", "last.ckpt"]  # no temporary left


def test_a_kill_during_a_save_keeps_the_previous_checkpoint(tmp_path, caplog):
    from fisheyedepth.checkpoints import write_checkpoint
    from fisheyedepth.cli.run_folder import run_folder

    run = tmp_path / "run"
    last = write_checkpoint({"epoch": 0, "w": torch.arange(20_000.0)}, run / "checkpoints" / "last.ckpt")
    before = last.read_bytes()
    child = os.fork()
    if child == 0:  # killed half-way through writing the next one
        try:

            def killed(obj, handle, *args, **kwargs):
                handle.write(b"x" * (len(before) // 2))
                handle.flush()
                os.kill(os.getpid(), signal.SIGKILL)

            torch.save = killed
            write_checkpoint({"epoch": 1, "w": torch.zeros(20_000)}, last)
        finally:
            os._exit(1)
    _, status = os.waitpid(child, 0)
    assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL
    assert last.read_bytes() == before
    (stale,) = last.parent.glob(f".last.ckpt.*.{child}.tmp")  # .NAME.<random>.<pid>.tmp
    assert stale.stat().st_size == len(before) // 2
    live = last.with_name(f".best-001.ckpt.{os.getppid()}.tmp")  # a writer that still runs
    live.write_bytes(b"being written")
    with run_folder(run, last):  # the next start (a resume) removes what the killed writer left
        assert sorted(p.name for p in last.parent.iterdir()) == [live.name, "last.ckpt"]
    assert f"removed {stale}, a checkpoint half-written by a process that no longer runs" in caplog.text
    assert last.read_bytes() == before


# ------------------------------------------------------------------ options and files: one line
@pytest.mark.parametrize("command", ["train", "export", "predict"])
def test_a_size_the_network_cannot_run_at_is_named(command, first_run, world, tmp_path, capsys):
    out = tmp_path / "out"
    if command == "train":
        cfg, option = train_cfg(out, world, "data.datamodule.size=[100,64]"), "data.datamodule.size"
    elif command == "export":
        values = {"ckpt_path": str(first_run.last), "format": "onnx", "size": [100, 64], "output": str(out)}
        cfg, option = OmegaConf.create(values), "size"
    else:
        images = images_of(first_run.root, tmp_path / "in", 1)
        values = {"input": images, "camera": first_run.calib, "output": out, "size": [100, 64]}
        cfg, option = predict_cfg(ckpt_path=first_run.last, **values), "size"
    err = one_line_error({"train": train, "export": export, "predict": predict}[command], cfg, capsys)
    assert err == f"error: {option}: [100, 64] cannot be the network's input: {NEAREST} [96, 64] or [128, 64]"
    assert not out.exists()


def test_resuming_with_another_network_names_the_options(first_run, world, capsys):
    last = first_run.last
    before = snapshot(first_run.dir)
    cfg = train_cfg(first_run.dir, world, f"ckpt_path={last}", "model.net.n_bins=32", "model.net.resnet=34")
    assert one_line_error(train, cfg, capsys) == (
        f"error: {last}: cannot resume it with another network: model.net.resnet is 34 here, 18 in "
        "the checkpoint; model.net.n_bins is 32 here, 64 in the checkpoint"
    )
    assert snapshot(first_run.dir) == before


def test_weights_that_do_not_fit_name_the_file_and_the_keys(first_run, tmp_path):
    full = torch.load(first_run.last, weights_only=True)
    ckpt = {k: full[k] for k in ("state_dict", "hyper_parameters")}
    ckpt["hyper_parameters"]["net"]["n_bins"] = 32
    ckpt["state_dict"]["depth_net.extra"] = torch.zeros(3)
    missing = next(k for k in ckpt["state_dict"] if k.startswith("depth_net.encoder.") and k.endswith("bias"))
    del ckpt["state_dict"][missing]
    torch.save(ckpt, tmp_path / "bins.ckpt")
    with pytest.raises(CheckpointError) as info:
        FisheyeDepthModule.from_checkpoint(tmp_path / "bins.ckpt")
    assert str(info.value) == (
        f"{tmp_path / 'bins.ckpt'}: weights do not fit the model its hyper_parameters describe: 4 of another "
        "shape (depth_net.heads.0.logits.1.weight [64, 16, 3, 3] in the file, [32, 16, 3, 3] in the model, "
        "depth_net.heads.0.logits.1.bias [64] in the file, [32] in the model, and 2 more); "
        f"1 missing ({missing}); 1 unexpected (depth_net.extra)"
    )


def test_a_non_numeric_option_is_named(world, tmp_path, capsys):
    assert one_line_error(train, train_cfg(tmp_path / "run", world, "model.optimizer.lr=abc"), capsys) == (
        "error: model.optimizer.lr: 'abc' is not a number"
    )
    with pytest.raises(ValueError, match=r"^net\.n_bins: 32\.5 is not a whole number$"):
        bare_module(net={"n_bins": 32.5})
    with pytest.raises(ValueError, match=r"^optimizer\.weight_decay: True is not a number$"):
        bare_module(optimizer={"weight_decay": True})


def tiny_onnx(path: Path, graph_size: int, metadata_size: int, out_channels: int = 1) -> Path:
    """A hand-made ONNX file: ``[B, 3, S, S]`` in, the channel mean (or the image itself) out, with the
    metadata export.py writes, claiming ``metadata_size``."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    pytest.importorskip("onnxruntime")
    s = graph_size
    image = helper.make_tensor_value_info("image", TensorProto.FLOAT, ["batch", 3, s, s])
    distance = helper.make_tensor_value_info("distance", TensorProto.FLOAT, ["batch", out_channels, s, s])
    node = (
        helper.make_node("ReduceMean", ["image"], ["distance"], axes=[1], keepdims=1)
        if out_channels == 1
        else helper.make_node("Identity", ["image"], ["distance"])
    )
    model = helper.make_model(
        helper.make_graph([node], "tiny", [image], [distance]), opset_imports=[helper.make_opsetid("", 17)]
    )
    model.ir_version = 8
    for key, value in onnx_metadata((metadata_size, metadata_size), 1.0, 20.0, None).items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save(model, path)
    return path


def test_an_onnx_file_whose_metadata_disagrees_with_its_graph_is_refused(first_run, tmp_path, capsys):
    wrong_size = tiny_onnx(tmp_path / "size.onnx", 64, 128)
    images = images_of(first_run.root, tmp_path / "in", 1)
    values = {"input": images, "camera": first_run.calib, "output": tmp_path / "out"}
    cfg = predict_cfg(runtime="onnx", model_file=wrong_size, **values)
    assert one_line_error(predict, cfg, capsys) == (
        f"error: {wrong_size}: metadata field 'fisheyedepth.input_size' says 128x128, but the graph's input "
        "'image' is 64x64"
    )
    three = tiny_onnx(tmp_path / "rgb.onnx", 64, 64, out_channels=3)  # copied metadata, an image out
    with pytest.raises(ValueError) as info:
        OnnxRuntime(three)
    assert str(info.value) == (
        f"{three}: the graph's output 'distance' has 3 channels, not 1 (one distance per pixel)"
    )
    assert OnnxRuntime(tiny_onnx(tmp_path / "fits.onnx", 64, 64)).input_size == (64, 64)
