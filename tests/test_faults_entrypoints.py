"""Faults of the entry points: nothing lost, nothing silent.

Each test feeds one kind of bad input or fault a new user meets (a killed training run, a resumed run in
the same folder, predictions on pixels without a ray, impossible or foreign calibrations, broken
checkpoints, bad images, a long video, an empty folder, a second run into one folder) and checks that it
gets a clear error naming the file, or the promised output, and never a silent wrong answer.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from fisheyedepth.cameras import CalibrationError, load_camera, load_yaml, save_camera
from fisheyedepth.checkpoints import CheckpointError, check_resumable, read_checkpoint
from fisheyedepth.cli import EXIT_USAGE, run_command
from fisheyedepth.cli.export import export
from fisheyedepth.cli.predict import predict
from fisheyedepth.cli.train import train
from fisheyedepth.data.kitti360 import kitti360_camera
from fisheyedepth.files import atomic_write_text
from fisheyedepth.images import ImageError, read_image
from fisheyedepth.inference import DistancePredictor
from fisheyedepth.module import FisheyeDepthModule

from conftest import TINY, TRAIN_SEQ, copy_tiny_world

ROOT = Path(__file__).resolve().parents[1]
TINY_RUN = [
    *(o for o in TINY if not o.startswith("eval.")),
    "eval.pictures=1",
    "eval.protocols=[full]",
    "callbacks.progress=null",
]


def python(*args, **kwargs):
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **kwargs.pop("env", {})}
    return subprocess.run(
        [sys.executable, *map(str, args)], capture_output=True, text=True, cwd=ROOT, env=env, **kwargs
    )


def predict_cfg(**values):
    """The predict.py config as Hydra would compose it, without Hydra's runtime."""
    cfg = OmegaConf.load(ROOT / "conf" / "predict.yaml")
    for hydra_only in ("defaults", "hydra"):
        cfg.pop(hydra_only, None)
    cfg.paths = {"output_dir": "unused"}
    return OmegaConf.merge(cfg, {k: str(v) if isinstance(v, Path) else v for k, v in values.items()})


def one_line_error(command, cfg, capsys) -> str:
    """Run an entry point that must fail on its input: exit 2 with one ``error:`` line."""
    with pytest.raises(SystemExit) as exit_info:
        run_command(command, cfg)
    assert exit_info.value.code == EXIT_USAGE
    err = capsys.readouterr().err.strip().replace("\r", "\n").splitlines()  # after any progress bar
    assert err[-1].startswith("error: ") and "Traceback" not in "\n".join(err), err
    return err[-1]


def images_of(kitti_data, dst: Path, n: int = 2) -> Path:
    dst.mkdir(parents=True)
    src = kitti_data / "data_2d_raw" / TRAIN_SEQ / "image_02" / "data_rgb"
    for path in sorted(src.glob("*.png"))[:n]:
        shutil.copy(path, dst / path.name)
    return dst


# ------------------------------------------------------------------ training: SIGTERM, resuming in place
@pytest.fixture(scope="module")
def data_dir(tiny_world, tmp_path_factory):
    """``paths.data_dir`` with the tiny world already rendered: these runs are about SIGTERM and resuming
    (rendering on first use is test_entrypoints' fast_dev_run's)."""
    return copy_tiny_world(tiny_world, tmp_path_factory.mktemp("faults_data"))


def stopped_training(data_dir, run_dir, signum) -> tuple[int, str, list[str]]:
    """A tiny training run, as train.py, sent ``signum`` in its second epoch: its exit status, output
    and Hydra arguments."""
    args = [f"paths.data_dir={data_dir}", f"hydra.run.dir={run_dir}", "trainer.limit_train_batches=3"]
    args += TINY_RUN
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / "train.py"), "trainer.max_epochs=200", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # as from a terminal
    )
    last = run_dir / "checkpoints" / "last.ckpt"
    deadline = time.monotonic() + 300
    while not last.is_file() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    assert last.is_file(), proc.communicate()[0][-3000:]
    time.sleep(1.0)  # into the next epoch
    proc.send_signal(signum)
    output = proc.communicate(timeout=120)[0]
    return proc.returncode, output, args


def test_ctrl_c_exits_130_with_one_line_naming_the_checkpoint_to_resume(data_dir, tmp_path):
    status, output, _ = stopped_training(data_dir, tmp_path / "run", signal.SIGINT)
    assert status == 130, output[-3000:]  # not Lightning's 1, an error's status
    last = tmp_path / "run" / "checkpoints" / "last.ckpt"
    assert "interrupted (SIGINT) at step" in output and f"Resume with ckpt_path={last}" in output
    assert "Traceback" not in output and not (tmp_path / "run" / "results.json").exists()
    check_resumable(last)


@pytest.mark.parametrize("signum, stop", [(signal.SIGINT, KeyboardInterrupt), (signal.SIGTERM, SystemExit)])
def test_a_signal_while_a_checkpoint_is_written_stops_only_once_it_is_whole(
    tmp_path, monkeypatch, signum, stop
):
    """Ctrl-C inside ``torch.save`` cuts its zip writer (a RuntimeError and a traceback, not the stop
    asked for): the signal is held until the checkpoint is in place, then given to the handlers that
    were there (here KeyboardInterrupt, and signals.sigterm_raises' Terminated)."""
    from fisheyedepth.checkpoints import write_checkpoint
    from fisheyedepth.signals import Terminated, sigterm_raises

    save, calls = torch.save, []

    def signalled_halfway(obj, handle):
        calls.append(1)
        signal.raise_signal(signum)  # as the signal arriving while the zip is written
        return save(obj, handle)

    monkeypatch.setattr(torch, "save", signalled_halfway)
    path = tmp_path / "last.ckpt"
    checkpoint = {"state_dict": {"w": torch.arange(1000.0)}, "epoch": 3}
    with pytest.raises(stop) as stopped, sigterm_raises():
        write_checkpoint(checkpoint, path)
    assert calls == [1] and (signum == signal.SIGINT or isinstance(stopped.value, Terminated))
    written = torch.load(path, map_location="cpu", weights_only=True)
    assert written["epoch"] == 3 and torch.equal(written["state_dict"]["w"], torch.arange(1000.0))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.ckpt"]  # whole, no temporary
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_sigterm_exits_143_and_resuming_in_the_same_folder_keeps_history(data_dir, tmp_path):
    run_dir = tmp_path / "run"
    status, output, args = stopped_training(data_dir, run_dir, signal.SIGTERM)
    last = run_dir / "checkpoints" / "last.ckpt"
    assert status == 143, output[-3000:]
    assert "terminated (SIGTERM) at step" in output and not (run_dir / "results.json").exists()
    check_resumable(last)  # the checkpoint is whole
    epoch = torch.load(last, map_location="cpu", weights_only=True)["epoch"]
    first_log = run_dir / "logs" / "version_0" / "metrics.csv"
    rows = list(csv.DictReader(first_log.open()))
    assert rows and any(r["epoch"] == "0" for r in rows)

    # resumed in this process, twice (train.py's function on its composed config, in the same folder)
    overrides = [f"ckpt_path={last}", f"trainer.max_epochs={epoch + 2}", f"paths.output_dir={run_dir}"]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        resumed = compose("train", [*overrides, *(a for a in args if not a.startswith("hydra."))])
    train(resumed)
    assert list(csv.DictReader(first_log.open())) == rows  # the first run's log is untouched
    second = list(csv.DictReader((run_dir / "logs" / "version_1" / "metrics.csv").open()))
    assert second and {r["epoch"] for r in second} <= {str(epoch), str(epoch + 1)}
    record = json.loads((run_dir / "results.json").read_text())
    assert record["resumed_from"] == str(last)
    assert stat.S_IMODE((run_dir / "results.json").stat().st_mode) == 0o666 & ~current_umask()

    train(resumed)
    assert (run_dir / "results.json").read_text() == json.dumps(record, indent=2) + "\n"  # kept
    assert (run_dir / "results_1.json").is_file()


def test_training_never_replaces_a_users_folder(tmp_path):
    """A user who forgot ``data=rig``: train.py must refuse the folder, not render over it."""
    robot = tmp_path / "my_robot"
    (robot / "seq0" / "images").mkdir(parents=True)
    (robot / "seq0" / "poses.txt").write_text("0 0 0 0 0 0 0 1\n")
    (robot / "rig.yaml").write_text("cameras: []\n")
    before = {p: p.read_bytes() for p in robot.rglob("*") if p.is_file()}
    proc = python(
        "train.py", f"data.datamodule.root={robot}", f"hydra.run.dir={tmp_path / 'run'}", timeout=300
    )
    assert proc.returncode == EXIT_USAGE, proc.stderr[-2000:]
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith(f"error: {robot} is not a synthetic dataset made by fisheyedepth")
    assert "data=rig" in last and "data=kitti360" in last
    assert {p: p.read_bytes() for p in robot.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["my_robot", "run"]  # no partial folder


def current_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@pytest.mark.parametrize("kind", ["empty", "truncated", "random", "foreign", "wrong_keys", "not_a_dict"])
def test_broken_checkpoints_are_named(checkpoint, tmp_path, kind, capsys):
    path = tmp_path / f"{kind}.ckpt"
    good = checkpoint.read_bytes()
    if kind == "empty":
        path.write_bytes(b"")
    elif kind == "truncated":
        path.write_bytes(good[: len(good) // 2])
    elif kind == "random":
        path.write_bytes(np.random.default_rng(0).bytes(4096))
    elif kind == "foreign":
        torch.save({"model": {"w": torch.zeros(3)}, "epoch": 3}, path)
    elif kind == "wrong_keys":
        ckpt = torch.load(checkpoint, weights_only=True)
        ckpt["hyper_parameters"]["hidden"] = 128
        torch.save(ckpt, path)
    else:
        torch.save([torch.zeros(2)], path)
    with pytest.raises(CheckpointError) as info:
        FisheyeDepthModule.from_checkpoint(path)
    message = str(info.value)
    assert message.startswith(str(path)) and "\n" not in message
    with pytest.raises(CheckpointError, match="cannot resume|not a|empty|refused|holds"):
        check_resumable(path)
    err = one_line_error(export, OmegaConf.create({"ckpt_path": str(path), "format": "onnx"}), capsys)
    assert str(path) in err


def test_weight_shapes_that_do_not_fit_are_named(checkpoint, tmp_path):
    ckpt = torch.load(checkpoint, weights_only=True)
    ckpt["hyper_parameters"]["net"]["n_bins"] = 32
    torch.save(ckpt, tmp_path / "shapes.ckpt")
    with pytest.raises(CheckpointError, match="weights do not fit"):
        FisheyeDepthModule.from_checkpoint(tmp_path / "shapes.ckpt")


# the hyper-parameters of the ``checkpoint`` fixture's module as they were saved before the options
# came in groups (net, objective, optimizer, scheduler): one flat dictionary
FLAT_HPARAMS = {
    "resnet": 18, "weights": None, "fisheye_projection": True, "real_scale": True, "multi_channel": True,
    "n_bins": 64, "attention": True, "min_distance": 0.5, "max_distance": 150.0, "base_focal": 20.0,
    "scales": (0, 1), "source_offsets": (-1, 1), "rig_offsets": (), "automask": True, "smoothness": 0.001,
    "lr": 0.0001, "weight_decay": 1e-05, "lr_step": 8, "lr_gamma": 0.1, "eval_cap": (0.001, 80.0),
    "log_images_every": 200, "input_size": (64, 64), "pose_translation_scale": None,
    "pinhole_focal": "paraxial", "channels_last": False, "loss_resolution": "full", "compile_kernels": False,
    "lr_schedule": "step", "upsample": "distance", "decoder_width": 1.0, "rim_margin": None,
}  # fmt: skip


def test_a_checkpoint_with_flat_hyper_parameters_loads_and_resumes_into_groups(checkpoint, tmp_path):
    """A checkpoint written before the option groups (flat ``lr``, ``multi_channel``, ...) loads with
    every option in its group, predicts what the grouped one predicts, and is checked for a resume
    against a grouped config (``model.net.n_bins`` named when it differs)."""
    from fisheyedepth.checkpoints import network_differences
    from fisheyedepth.migration import nested_hparams

    ckpt = torch.load(checkpoint, weights_only=True)
    grouped = FisheyeDepthModule.from_checkpoint(checkpoint)
    ckpt["hyper_parameters"] = dict(FLAT_HPARAMS)
    torch.save(ckpt, tmp_path / "flat.ckpt")
    module = FisheyeDepthModule.from_checkpoint(tmp_path / "flat.ckpt")
    assert dict(module.hparams) == dict(grouped.hparams)
    assert module.hparams.optimizer == {"_target_": "torch.optim.Adam", "_partial_": True} | {
        "lr": 1e-4, "weight_decay": 1e-5,
    }  # fmt: skip
    assert module.hparams.scheduler["step_size"] == 8 and module.hparams.net["base_focal"] == 20.0
    image = torch.rand(1, 3, 64, 64)
    camera = [kitti360_camera(2).resize(64, 64)]
    with torch.no_grad():
        assert torch.equal(
            module.eval()(image, camera)["distance"][0], grouped.eval()(image, camera)["distance"][0]
        )
    configured = FisheyeDepthModule.options(net={"scales": [0, 1], "n_bins": 32})
    assert network_differences(FLAT_HPARAMS, configured) == [
        "model.net.n_bins is 32 here, 64 in the checkpoint"
    ]
    assert network_differences(FLAT_HPARAMS, dict(grouped.hparams)) == []
    cosine = nested_hparams(FLAT_HPARAMS | {"lr_schedule": "cosine", "lr": 1e-3})["scheduler"]
    assert cosine["_target_"].endswith("CosineAnnealingLR") and cosine["eta_min"] == pytest.approx(1e-4)


def test_a_checkpoint_with_a_retired_key_still_loads(checkpoint, tmp_path):
    """grad_clip left the model on 2026-11-23 (the trainer's gradient_clip_val is the only one), the
    training-only distance search (bin_search) on 2026-11-24, the hint search and the plane-sweep
    hints (hint_weight) on 2026-11-25."""
    ckpt = torch.load(checkpoint, weights_only=True)
    ckpt["hyper_parameters"].update(grad_clip=1.0, bin_search=0.25, bin_search_scale=2)
    ckpt["hyper_parameters"].update(hints=1.0, hint_candidates=2, hint_spread=4.0, hint_margin=0.02)
    ckpt["hyper_parameters"].update(hint_weight=1.0)
    cap = ckpt["hyper_parameters"].pop("eval_cap")  # before 2026-11-23: eval_min and eval_max
    ckpt["hyper_parameters"].update(eval_min=0.5, eval_max=40.0)
    torch.save(ckpt, tmp_path / "old.ckpt")
    module = FisheyeDepthModule.from_checkpoint(tmp_path / "old.ckpt")
    assert "grad_clip" not in module.hparams and "eval_min" not in module.hparams
    assert "bin_search" not in module.hparams and "bin_search_scale" not in module.hparams
    assert not any(key.startswith("hint") for key in module.hparams)
    assert tuple(module.hparams.eval_cap) == (0.5, 40.0) and module.val_metrics.cap == (0.5, 40.0)
    assert tuple(cap) == (1e-3, 80.0)
    ckpt["hyper_parameters"]["no_such_key"] = 1.0  # an unknown key is still refused, by name
    torch.save(ckpt, tmp_path / "foreign.ckpt")
    with pytest.raises(CheckpointError, match="no_such_key"):
        FisheyeDepthModule.from_checkpoint(tmp_path / "foreign.ckpt")


def test_resume_from_a_foreign_checkpoint_is_one_line(checkpoint, tmp_path):
    proc = python("train.py", f"ckpt_path={checkpoint}", f"hydra.run.dir={tmp_path / 'run'}", timeout=300)
    assert proc.returncode == EXIT_USAGE, proc.stderr[-2000:]
    err = proc.stderr.strip().splitlines()
    assert (
        err[-1].startswith(f"error: {checkpoint}: cannot resume from it") and "Traceback" not in proc.stderr
    )
    assert "pytorch-lightning_version" in err[-1]


def test_export_names_an_unknown_format(checkpoint, capsys):
    cfg = OmegaConf.create({"ckpt_path": str(checkpoint), "format": "tflite"})
    err = one_line_error(export, cfg, capsys)
    assert "format: 'tflite' is not one of onnx, torchscript" in err


def test_export_json_gets_the_users_permissions(checkpoint, tmp_path):
    cfg = OmegaConf.create(
        {"ckpt_path": str(checkpoint), "format": "torchscript", "size": None, "camera": None,
         "output": str(tmp_path / "m.pt"), "overwrite": False, "paths": {"output_dir": str(tmp_path)}}
    )  # fmt: skip
    export(cfg)
    mode = 0o666 & ~current_umask()
    assert stat.S_IMODE((tmp_path / "m.pt.json").stat().st_mode) == mode


# ------------------------------------------------------------------ calibrations
def test_garbage_bytes_calibration_is_named(tmp_path, capsys, checkpoint, kitti_data):
    calib = tmp_path / "garbage.yaml"
    calib.write_bytes(np.random.default_rng(1).bytes(512) + b"\xff\xfe")
    with pytest.raises(CalibrationError, match=f"^{calib}: not a text file"):
        load_camera(calib)
    images = images_of(kitti_data, tmp_path / "in", 1)
    cfg = predict_cfg(ckpt_path=checkpoint, input=images, camera=calib, output=tmp_path / "out")
    assert one_line_error(predict, cfg, capsys).startswith(f"error: {calib}: not a text file")


def test_a_calibration_without_rays_is_refused(tmp_path, kitti_data, checkpoint, capsys):
    camera = dataclasses.replace(kitti360_camera(2).resize(256, 256), k1=-1e12)
    calib = save_camera(camera, tmp_path / "impossible.yaml")
    with pytest.raises(CalibrationError, match=r"only 0\.0% of the 256x256 image has a ray"):
        load_camera(calib)
    text = (kitti_data / "calibration" / "image_02.yaml").read_text().replace("k1: ", "k1: -1.0e+12 #", 1)
    (tmp_path / "opencv.yaml").write_text(text)
    with pytest.raises(CalibrationError, match=str(tmp_path / "opencv.yaml")):
        load_camera(tmp_path / "opencv.yaml")
    cfg = predict_cfg(
        ckpt_path=checkpoint,
        input=images_of(kitti_data, tmp_path / "in", 1),
        camera=calib,
        output=tmp_path / "o",
    )
    assert "has a ray" in one_line_error(predict, cfg, capsys)
    assert not (tmp_path / "o").exists()


def test_yaml_exponents_without_a_dot_are_numbers(kitti_data, tmp_path):
    assert load_yaml("a: 1e-3\nb: -2E+5\nc: 1.5e-3\nd: 1e3x\n", "x") == {
        "a": 1e-3, "b": -2e5, "c": 1.5e-3, "d": "1e3x"
    }  # fmt: skip
    text = (kitti_data / "calibration" / "image_02.yaml").read_text().splitlines()
    lines = ["   k2: 1e-3" if line.strip().startswith("k2:") else line for line in text]
    assert lines != text
    (tmp_path / "exp.yaml").write_text("\n".join(lines) + "\n")
    assert load_camera(tmp_path / "exp.yaml").k2 == 1e-3  # OpenCV reads it so; YAML 1.1 said "1e-3"


# ------------------------------------------------------------------ predictions
@pytest.mark.realdata
def test_pixels_without_a_ray_get_no_distance_on_the_real_kitti360_frame(realdata, checkpoint, tmp_path):
    frame = realdata / "kitti360_frame"
    camera = load_camera(frame / "image_02.yaml")
    predictor = DistancePredictor(FisheyeDepthModule.from_checkpoint(checkpoint), camera)
    no_ray = ~predictor.has_ray
    assert int(no_ray.sum()) == 259_005  # of 1400 x 1400 = 1,960,000 pixels
    out = tmp_path / "out"
    (tmp_path / "in").mkdir()
    shutil.copy(frame / "image_02_rgb.png", tmp_path / "in" / "kitti.png")
    cfg = predict_cfg(
        ckpt_path=checkpoint, input=tmp_path / "in", camera=frame / "image_02.yaml", output=out,
        z_depth=True, point_cloud=True,
    )  # fmt: skip
    predict(cfg)
    d = np.load(out / "kitti_distance.npy")
    z = np.load(out / "kitti_z.npy")
    png = cv2.imread(str(out / "kitti_distance.png"), cv2.IMREAD_UNCHANGED)
    mask = no_ray.numpy()
    assert np.isnan(d[mask]).all() and np.isfinite(d[~mask]).all() and (d[~mask] > 0).all()
    assert np.isnan(z[mask]).all() and (z[~mask] != d[~mask]).mean() > 0.99  # z is not the distance
    assert (png[mask] == 0).all() and (png[~mask] > 0).all()
    from fisheyedepth.inference import read_ply

    points, _ = read_ply(out / "kitti.ply")
    assert len(points) == int((~mask).sum())


def test_an_image_of_another_aspect_ratio_is_refused(kitti_data, checkpoint, tmp_path, capsys):
    (tmp_path / "in").mkdir()
    image = cv2.imread(
        str(next((kitti_data / "data_2d_raw" / TRAIN_SEQ / "image_02" / "data_rgb").glob("*.png")))
    )
    cv2.imwrite(str(tmp_path / "in" / "wide.png"), cv2.resize(image, (320, 180)))
    calib = kitti_data / "calibration" / "image_02.yaml"
    cfg = predict_cfg(ckpt_path=checkpoint, input=tmp_path / "in", camera=calib, output=tmp_path / "out")
    err = one_line_error(predict, cfg, capsys)
    assert "wide.png: image is 320x180" in err and f"{calib} is 256x256" in err


def test_grayscale_and_truncated_images_are_reported_by_name(kitti_data, checkpoint, tmp_path, caplog):
    images = images_of(kitti_data, tmp_path / "in", 1)
    colour = cv2.imread(str(next(images.glob("*.png"))))
    cv2.imwrite(str(images / "grey.png"), cv2.cvtColor(colour, cv2.COLOR_BGR2GRAY))
    cv2.imwrite(str(images / "cut.jpg"), colour, [cv2.IMWRITE_JPEG_QUALITY, 95])
    data = (images / "cut.jpg").read_bytes()
    (images / "cut.jpg").write_bytes(data[: int(len(data) * 0.6)])
    assert cv2.imread(str(images / "cut.jpg")) is not None  # what OpenCV does: a half-grey picture
    with pytest.raises(ImageError, match="cut.jpg: truncated JPEG"):
        read_image(images / "cut.jpg")
    assert read_image(images / "grey.png").grayscale
    out = tmp_path / "out"
    summary = predict(predict_cfg(ckpt_path=checkpoint, input=images, camera=_calib(kitti_data), output=out))
    assert summary["frames"] == 2 and summary["skipped"] == 1
    assert summary["unreadable"] == [str(images / "cut.jpg")]
    assert summary["grayscale"] == [str(images / "grey.png")]
    assert "grey.png: grayscale image" in caplog.text and "cut.jpg: truncated JPEG" in caplog.text
    assert not (out / "cut_distance.npy").exists() and (out / "grey_distance.npy").is_file()


def _calib(kitti_data):
    return kitti_data / "calibration" / "image_02.yaml"


def test_an_empty_folder_is_an_error(checkpoint, kitti_data, tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("no images here")
    cfg = predict_cfg(ckpt_path=checkpoint, input=tmp_path / "empty", camera=_calib(kitti_data))
    assert one_line_error(predict, cfg, capsys) == f"error: {tmp_path / 'empty'}: no images " + (
        "(.png .jpg .jpeg .bmp .tif .tiff) in this folder"
    )
    (tmp_path / "empty" / "a.png").write_bytes(b"broken")
    cfg = predict_cfg(
        ckpt_path=checkpoint, input=tmp_path / "empty", camera=_calib(kitti_data), output=tmp_path / "o"
    )
    assert "no frame could be read (1 unreadable)" in one_line_error(predict, cfg, capsys)


def test_a_second_run_into_one_folder_keeps_the_first_summary(kitti_data, checkpoint, tmp_path):
    first = images_of(kitti_data, tmp_path / "first", 1)
    second = tmp_path / "second"
    second.mkdir()
    src = kitti_data / "data_2d_raw" / TRAIN_SEQ / "image_03" / "data_rgb"
    shutil.copy(sorted(src.glob("*.png"))[-1], second / "other.png")
    out = tmp_path / "out"
    predict(predict_cfg(ckpt_path=checkpoint, input=first, camera=_calib(kitti_data), output=out))
    before = (out / "summary.json").read_text()
    predict(predict_cfg(ckpt_path=checkpoint, input=second, camera=_calib(kitti_data), output=out))
    assert (out / "summary.json").read_text() == before
    assert json.loads((out / "summary_1.json").read_text())["input"] == str(second)
    assert stat.S_IMODE((out / "summary.json").stat().st_mode) == 0o666 & ~current_umask()
    with pytest.raises(FileExistsError, match="overwrite=true"):
        predict(predict_cfg(ckpt_path=checkpoint, input=first, camera=_calib(kitti_data), output=out))


def test_two_images_with_one_name_are_refused(kitti_data, checkpoint, tmp_path, capsys):
    images = images_of(kitti_data, tmp_path / "in", 1)
    src = next(images.glob("*.png"))
    cv2.imwrite(str(src.with_suffix(".jpg")), cv2.imread(str(src)))
    cfg = predict_cfg(ckpt_path=checkpoint, input=images, camera=_calib(kitti_data), output=tmp_path / "o")
    assert "two images with one name" in one_line_error(predict, cfg, capsys)


def _video(path: Path, kitti_data, frames: int, size: int = 384) -> Path:
    src = sorted((kitti_data / "data_2d_raw" / TRAIN_SEQ / "image_02" / "data_rgb").glob("*.png"))
    base = [cv2.resize(cv2.imread(str(p)), (size, size)) for p in src[:4]]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (size, size))
    for i in range(frames):
        writer.write(base[i % len(base)])
    writer.release()
    return path


def start_peak_rss(*args) -> subprocess.Popen:
    """A child ``python ARGS`` process, started under a probe that prints the child's peak resident
    memory (kB, from the kernel's accounting) when it ends: read it with :func:`peak_rss_mb`. Two probes
    may run side by side; each reports its own child only."""
    probe = (
        "import resource, subprocess, sys;"
        "r = subprocess.run([sys.executable, *sys.argv[1:]], capture_output=True, text=True);"
        "sys.stderr.write(r.stderr[-2000:]);"
        "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss); sys.exit(r.returncode)"
    )
    return subprocess.Popen(
        [sys.executable, "-c", probe, *map(str, args)], cwd=ROOT, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )  # fmt: skip


def peak_rss_mb(probe: subprocess.Popen) -> tuple[float, str]:
    """The peak resident memory (MB) of a :func:`start_peak_rss` child, and its standard error; the child
    must have succeeded."""
    out, err = probe.communicate(timeout=600)
    assert probe.returncode == 0, err
    return int(out.strip().splitlines()[-1]) / 1024, err


# a short and a long clip of frames of SIDE x SIDE pixels: the long one's extra frames, decoded up front,
# would take 120 x 384 x 384 x 3 bytes = 51 MB, twice the growth the test allows
SIDE, CLIPS = 384, (10, 130)


def test_predict_streams_a_video_in_flat_memory(kitti_data, checkpoint, tmp_path):
    """600 frames at 512 px took 906 MB against 608 MB for 30 when the whole video was decoded first.
    The two clips are predicted side by side, each in its own process."""
    probes = {}
    for n in CLIPS:
        video = _video(tmp_path / f"clip{n}.avi", kitti_data, n, SIDE)
        probes[n] = start_peak_rss(
            "predict.py", f"ckpt_path={checkpoint}", f"input={video}", f"camera={_calib(kitti_data)}",
            f"output={tmp_path / f'out{n}'}", f"hydra.run.dir={tmp_path / f'h{n}'}", "batch_size=4",
        )  # fmt: skip
    peaks = {n: peak_rss_mb(probe)[0] for n, probe in probes.items()}
    for n in CLIPS:
        assert len(list((tmp_path / f"out{n}").glob("*_distance.npy"))) == n
    short, long = CLIPS
    print(f"predict.py peak RSS: {peaks[short]:.0f} MB for {short} frames, {peaks[long]:.0f} MB for {long}")
    assert (long - short) * SIDE * SIDE * 3 / 2**20 >= 2 * 25  # what decoding up front would add
    assert peaks[long] - peaks[short] < 25, peaks


def test_a_clash_is_found_before_anything_is_decoded(kitti_data, checkpoint, tmp_path):
    video = _video(tmp_path / "clip.avi", kitti_data, 5, 64)
    out = tmp_path / "out"
    out.mkdir()
    (out / "frame_000004_colour.png").write_bytes(b"keep me")
    cfg = predict_cfg(ckpt_path=checkpoint, input=video, camera=_calib(kitti_data), output=out)
    with pytest.raises(FileExistsError, match="frame_000004_colour.png exists"):
        predict(cfg)
    assert sorted(p.name for p in out.iterdir()) == ["frame_000004_colour.png"]  # nothing written
    assert (out / "frame_000004_colour.png").read_bytes() == b"keep me"


def test_atomic_writes_follow_the_umask(tmp_path):
    old = os.umask(0o027)
    try:
        atomic_write_text(tmp_path / "a.json", "{}")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.json").stat().st_mode) == 0o640


def test_a_checkpoint_with_pickled_objects_is_refused_safely(tmp_path):
    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {tmp_path / 'pwned'}",))

    torch.save({"state_dict": {}, "x": Payload()}, tmp_path / "evil.ckpt")
    with pytest.raises(CheckpointError, match="refused by the safe loader"):
        read_checkpoint(tmp_path / "evil.ckpt")
    assert not (tmp_path / "pwned").exists()
