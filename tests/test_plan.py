"""A command's plan (:mod:`fisheyedepth.plan`): its composed config worked out and checked once, with the
values the command will use resolved, before anything is built, rendered or written; and frozen."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from fisheyedepth.checkpoints import CheckpointError
from fisheyedepth.cli.train import train
from fisheyedepth.plan import RuntimePlan, eval_plan, export_plan, predict_plan, train_plan

from conftest import ROOT, TINY, load_cfg
from test_faults_entrypoints import one_line_error


def compose_cfg(name: str, tmp_path: Path, *overrides: str):
    """``conf/<name>.yaml`` as Hydra composes it, its data and output folders under ``tmp_path`` (neither
    exists yet)."""
    paths = [f"paths.data_dir={tmp_path / 'data'}", f"paths.output_dir={tmp_path / 'run'}"]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose(name, [*paths, *overrides])


def test_a_train_config_becomes_a_plan_of_resolved_values(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False)
    overrides = ["model.objective.source_offsets=[-2,1]", "model.objective.rig_offsets=[0]", "select=best"]
    plan = train_plan(compose_cfg("train", tmp_path, *TINY, *overrides, "seed=3"))
    assert plan.output_dir == tmp_path / "run" and plan.resume is None and plan.resumed is None
    assert plan.precision == "32-true" and plan.accelerator == "cpu"  # auto: bf16 is not native here
    assert (plan.data.offsets, plan.data.rig_offsets) == ((-2, 1), (0,))  # the data loads what is warped
    assert plan.data.arguments() == {"offsets": [-2, 1], "rig_offsets": [0]}
    assert (plan.select, plan.seed, plan.test) == ("best", 3, True)
    world = str(tmp_path / "data" / "synthetic_kitti360_64_seed0_f12")
    assert plan.data.root == world == plan.scoring.data and plan.data.generate["frames"] == 12
    assert plan.scoring.experiment == "fisheyedepth" and plan.scoring.protocols == ("full", "kitti360")
    # base_focal: auto until the training cameras exist; the module is given the number then
    assert plan.model.options["net"]["base_focal"] == "auto" and plan.model.options["input_size"] == (64, 64)
    arguments = plan.model.arguments(net={"base_focal": 21.5})
    assert arguments["net"]["base_focal"] == 21.5 and arguments["net"]["scales"] == [0, 1]
    assert arguments["objective"]["source_offsets"] == [-2, 1]
    assert [c["_target_"].rsplit(".", 1)[1] for c in plan.callbacks] == [
        "ModelCheckpoint",
        "ModelCheckpoint",
        "RichProgressBar",
    ]
    assert (
        train_plan(compose_cfg("train", tmp_path, *TINY, "trainer.precision=16-mixed")).precision
        == "16-mixed"
    )
    assert list(tmp_path.iterdir()) == []  # planning made no folder and rendered nothing


REFUSED = {
    "model.net.n_bins=1": "model.net.n_bins: 1 is not a whole number >= 2",
    "select=lowest": "select='lowest': expected one of ('last', 'best')",
    "+data.datamodule.offsets=[-2,2]": (
        "data.datamodule.offsets=[-2, 2] differs from model.objective.source_offsets=[-1, 1]"
    ),
}


@pytest.mark.parametrize("override", REFUSED)
def test_a_bad_option_is_refused_while_planning(override, tmp_path, capsys):
    cfg = compose_cfg("train", tmp_path, *TINY, override)
    with pytest.raises(ValueError, match=re.escape(REFUSED[override])):
        train_plan(cfg)
    assert one_line_error(train, cfg, capsys).startswith(f"error: {REFUSED[override]}")
    assert not (tmp_path / "run").exists() and not (tmp_path / "data").exists()


def test_a_checkpoint_that_cannot_be_resumed_is_refused_while_planning(checkpoint, tmp_path):
    cfg = compose_cfg("train", tmp_path, *TINY, f"ckpt_path={checkpoint}")
    with pytest.raises(CheckpointError, match="cannot resume from it"):
        train_plan(cfg)
    assert list(tmp_path.iterdir()) == []


def test_the_plan_is_immutable(tmp_path):
    plan = train_plan(compose_cfg("train", tmp_path, *TINY))
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.select = "best"
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.data.offsets = (-2, 2)
    with pytest.raises(TypeError):
        plan.model.options["net"]["n_bins"] = 32
    with pytest.raises(TypeError):
        plan.data.generate["frames"] = 9
    assert isinstance(plan.model.options["net"]["scales"], tuple)
    arguments = plan.model.arguments()  # a fresh plain copy for the module
    arguments["net"]["n_bins"] = 32
    assert plan.model.options["net"]["n_bins"] == 64


def test_predict_eval_and_export_plans(tmp_path):
    common = {"input": tmp_path / "in", "camera": tmp_path / "cam.yaml", "output": tmp_path / "out"}
    plan = predict_plan(
        load_cfg("predict", ckpt_path="run/last.ckpt", size=[96, 64], precision="bf16", **common)
    )
    assert plan.output == tmp_path / "out" and not plan.output.exists()
    assert plan.runtime == RuntimePlan(
        kind="torch", checkpoint="run/last.ckpt", model_file=None, size=(96, 64), precision="bf16",
        device="cpu", upsample=None, post_process="none", threads=None,
    )  # fmt: skip
    refused = {
        "model: runtime=onnx needs the exported file": {"runtime": "onnx"},
        "runtime: 'tflite' is not one of torch, onnx": {"runtime": "tflite"},
        "model: a file is for runtime=onnx": {"model_file": "m.onnx"},
        "precision: 'fp16' is not one of fp32, bf16": {"precision": "fp16"},
        "size: [100, 64] cannot be the network's input": {"size": [100, 64]},
    }
    for message, values in refused.items():
        with pytest.raises(ValueError, match=re.escape(message)):
            predict_plan(load_cfg("predict", ckpt_path="run/last.ckpt", **common, **values))
    evaluated = eval_plan(compose_cfg("eval", tmp_path, "runtime=onnx", "model_file=m.onnx", "split=val"))
    assert (evaluated.runtime.kind, evaluated.runtime.model_file, evaluated.runtime.checkpoint) == (
        "onnx",
        "m.onnx",
        None,
    )
    assert evaluated.split == "val" and evaluated.output_dir == tmp_path / "run"
    assert evaluated.data.offsets is None and evaluated.data.arguments() == {}  # the data module's own
    values = {"ckpt_path": "run/last.ckpt", "format": "torchscript", "paths": {"output_dir": str(tmp_path)}}
    exporting = export_plan(load_cfg("export", **values))
    assert exporting.size is None and exporting.path((64, 96)) == tmp_path / "fisheyedepth_64x96.pt"
    with pytest.raises(ValueError, match=re.escape("format: 'tflite' is not one of onnx, torchscript")):
        export_plan(load_cfg("export", **values | {"format": "tflite"}))
    assert list(tmp_path.iterdir()) == []
