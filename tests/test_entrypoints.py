"""Hydra configs and entry points: every experiment composes; train.py smoke runs, a sweep, eval.py on the
checkpoint, resuming, wandb offline, the tables; a CPU DDP run with two processes."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import lightning as L
import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from fisheyedepth.cameras import load_camera
from fisheyedepth.checkpoints import read_checkpoint
from fisheyedepth.cli.evaluate import eval_checkpoint, experiment_of
from fisheyedepth.cli.train import selected_checkpoint, train
from fisheyedepth.config import resolve_base_focal, resolve_precision

from conftest import TINY, load_script, printed

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = sorted(p.stem for p in (ROOT / "conf" / "experiment").glob("[!_]*.yaml"))  # _paper: a base
TABLE_EXPERIMENTS = [e for e in EXPERIMENTS if e.startswith(("ablation_", "table1_"))]


def compose_train(overrides):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose(config_name="train", overrides=overrides, return_hydra_config=True)


def command_paths(workdir, out):
    return [f"paths.root_dir={ROOT}", f"paths.data_dir={workdir}/data", f"paths.output_dir={out}"]


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_composes(experiment):
    cfg = compose_train([f"+experiment={experiment}"])
    assert cfg.experiment_name == experiment
    m = cfg.model
    expected = {
        "ablation_baseline": (False, False, False),
        "ablation_fft_only": (True, False, False),
        "ablation_fft_rs": (True, True, False),
        "ablation_fft_mc": (True, False, True),
        "ablation_full": (True, True, True),
        "table1_dnet": (False, False, False),
        "table1_fsnet": (False, False, True),
        "table1_fsnet_rs": (False, True, True),
        "cpu_30min": (True, True, True),  # the full model, at a larger size for longer
        "gpu_10min": (True, True, True),  # cpu_30min on a GPU for longer
        "release_mobile": (True, True, True),  # the released weights: the mobile model, the mixed world
        "traffic_levers": (True, True, True),  # the levers' base row: the full method on traffic
        "truth_probe": (True, True, True),  # release_mobile told the truth (the next test)
    }[experiment]
    assert (m.objective.fisheye_projection, m.objective.real_scale, m.net.multi_channel) == expected
    if experiment.startswith("table1_fsnet"):
        assert m.net.attention is False
    if experiment == "table1_dnet":
        assert "dnet" in cfg.eval.scalings
    if experiment == "cpu_30min":
        default = compose_train([])
        assert list(cfg.data.datamodule.size) == [256, 256] != list(default.data.datamodule.size)
        assert cfg.model.scheduler.step_size < cfg.trainer.max_epochs
        assert cfg.model.objective.loss_resolution == "native"
    if experiment == "traffic_levers":  # the paper's objective; each other row adds one switch
        assert cfg.data.generate.traffic == 1.0 and len(cfg.data.generate.effects) == 5
        assert "/synthetic_traffic_" in OmegaConf.to_container(cfg.data.datamodule)["root"]
        assert (m.objective.automask, m.objective.outliers, m.objective.brightness) == (True, 0.0, "none")
    if experiment == "release_mobile":
        assert cfg.model.net.encoder == "efficientnet_lite0" and cfg.model.net.decoder_width == 0.25
        assert len(cfg.data.datamodule.root) == 4 and cfg.data.generate.random_cameras is True
        assert cfg.model.scheduler.step_size == cfg.trainer.max_epochs - 1  # the decay in the last fifth


def flat(tree, prefix=""):
    """``{"a.b": leaf}`` for a nested dict."""
    if not isinstance(tree, dict):
        return {prefix: tree}
    out = {}
    for key, sub in tree.items():
        out.update(flat(sub, f"{prefix}.{key}" if prefix else key))
    return out


def test_the_truth_probe_is_the_release_recipe_with_the_truth_instead_of_the_photometric_loss():
    """truth_probe (BENCHMARKS.md, "Real photographs") is release_mobile in everything (model, data,
    steps, schedule) but the objective's two weights."""
    release = flat(OmegaConf.to_container(compose_train(["+experiment=release_mobile"])))
    probe = flat(OmegaConf.to_container(compose_train(["+experiment=truth_probe"])))
    keys = {k for k in release.keys() | probe.keys() if not k.startswith("hydra.")}
    assert {k: (release.get(k), probe.get(k)) for k in keys if release.get(k) != probe.get(k)} == {
        "experiment_name": ("release_mobile", "truth_probe"),
        "model.objective.truth_weight": (0.0, 1.0),
        "model.objective.photometric_weight": (1.0, 0.0),
    }
    assert "train" in probe["data.datamodule.ground_truth_splits"]  # the worlds' exact maps


def test_gpu_recipe_is_cpu_30min_longer_on_a_gpu():
    """gpu_10min (BENCHMARKS.md, "Time to accuracy") is cpu_30min with more epochs, the decay after
    the same 80 % of them, on a GPU; everything else (model, data, loss, optimiser) is cpu_30min's."""
    cpu = flat(OmegaConf.to_container(compose_train(["+experiment=cpu_30min"])))
    gpu = flat(OmegaConf.to_container(compose_train(["+experiment=gpu_10min"])))
    keys = {k for k in cpu.keys() | gpu.keys() if not k.startswith("hydra.")}
    changed = {k: (cpu.get(k), gpu.get(k)) for k in keys if cpu.get(k) != gpu.get(k)}
    assert changed == {
        "experiment_name": ("cpu_30min", "gpu_10min"),
        "trainer.accelerator": ("cpu", "gpu"),
        "trainer.log_every_n_steps": (10, 50),
        "trainer.deterministic": (False, None),
        "trainer.max_epochs": (10, 17),
        "model.scheduler.step_size": (8, 14),
        "model.compile_kernels": (True, False),
        "data.datamodule.num_workers": (1, 12),
        "data.generate.workers": (2, 16),
    }
    step = "model.scheduler.step_size"
    assert gpu[step] / gpu["trainer.max_epochs"] == pytest.approx(
        cpu[step] / cpu["trainer.max_epochs"], abs=0.03
    )


@pytest.mark.parametrize(
    "group,option",
    [
        ("data", "kitti360"),
        ("data", "rig"),
        ("trainer", "gpu"),
        ("trainer", "ddp"),
        ("logger", "wandb"),
        ("logger", "none"),
        ("model", "monodepth2"),
        ("model", "fisheyedepth_lite"),
    ],
)
def test_config_groups_compose(group, option):
    cfg = compose_train([f"{group}={option}"])
    assert cfg[group] is not None or option == "none"
    assert "experiment" not in cfg  # the experiment group is not in the defaults list


def compose_command(name, overrides=()):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose(config_name=name, overrides=list(overrides), return_hydra_config=True)


def test_every_command_shares_paths_and_run_folders():
    """One paths block and one hydra block for every command: only the task name differs."""
    for name in ("train", "eval", "predict", "export"):
        cfg = compose_command(name)
        assert cfg.task_name == name
        assert set(cfg.paths) == {"root_dir", "data_dir", "output_dir"}
        assert cfg.hydra.run.dir.startswith(f"outputs/{name}/") and cfg.hydra.job.chdir is False
        assert cfg.hydra.sweep.dir.startswith(f"multirun/{name}/")
    for name in ("train.yaml", "eval.yaml", "predict.yaml", "export.yaml"):
        text = (ROOT / "conf" / name).read_text()
        assert "\npaths:" not in text and "\nhydra:" not in text, name  # through defaults only


def test_trainers_share_one_base_and_clipping_has_one_name():
    cpu, gpu, ddp = (compose_train([f"trainer={t}"]).trainer for t in ("cpu", "gpu", "ddp"))
    for trainer in (cpu, gpu, ddp):
        assert trainer.gradient_clip_val == 1.0 and trainer.num_sanity_val_steps == 1
    assert (cpu.accelerator, cpu.max_epochs, cpu.log_every_n_steps) == ("cpu", 7, 10)
    assert (gpu.accelerator, gpu.max_epochs, gpu.log_every_n_steps) == ("gpu", 7, 50)
    assert ddp.max_epochs == 7 and all(t.precision == "auto" for t in (cpu, gpu, ddp))
    assert compose_train([]).model.scheduler.step_size == 5  # the decay for the last two of every trainer's 7
    assert ddp.strategy == "ddp" and ddp.sync_batchnorm is True
    assert "grad_clip" not in compose_train([]).model


@pytest.mark.parametrize("experiment", TABLE_EXPERIMENTS)
def test_table_experiments_keep_the_papers_loss_frames_and_float32(experiment):
    """The default model takes the speed levers (native-resolution loss, bf16 where native) and the
    accuracy levers of make train (sources two frames away, 600 rendered frames); the Table 1/2 rows
    keep Monodepth2's full-resolution loss on the +-1 neighbours in float32, as their kept runs did."""
    default = compose_train([])
    assert default.model.objective.loss_resolution == "native" and default.model.compile_kernels is True
    assert list(default.model.objective.source_offsets) == [-2, 2] and default.data.generate.frames == 600
    cfg = compose_train([f"+experiment={experiment}"])
    assert cfg.model.objective.loss_resolution == "full" and cfg.trainer.precision == "32-true"
    assert list(cfg.model.objective.source_offsets) == [-1, 1]


def test_heldout_scores_the_200_frame_worlds_unless_told_otherwise(tmp_path, monkeypatch):
    """The held-out worlds were named as 200-frame renders; a training default of 600 frames must not
    make scripts/research/heldout.py render and score other worlds (the 200-frame world 0 is the first
    third of the 600-frame one, so the same slip on world 0 would score training frames)."""
    heldout = load_script("research/heldout")
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "last.ckpt").touch()
    commands = []
    monkeypatch.setattr(heldout.subprocess, "run", lambda command, **kw: commands.append(command))
    heldout.score_heldout(tmp_path, 2001, "kitti360", None, ["paths.data_dir=x"])
    heldout.score_heldout(tmp_path, 2002, "kitti360", None, ["data.generate.frames=12"])
    frames = [[o for o in c if o.startswith("data.generate.frames=")] for c in commands]
    assert frames == [["data.generate.frames=200"], ["data.generate.frames=12"]]
    assert "data.generate.seed=2001" in commands[0] and "data.generate.seed=2002" in commands[1]
    assert not any(o.startswith("post_process=") for c in commands for o in c)
    # Monodepth2's post-processing: scored into its own folder, beside the plain score
    heldout.score_heldout(tmp_path, 2001, "kitti360", None, [], "flip")
    assert "post_process=flip" in commands[2]
    assert f"hydra.run.dir={tmp_path / 'heldout_kitti360_seed2001_flip'}" in commands[2]
    assert f"hydra.run.dir={tmp_path / 'heldout_kitti360_seed2001'}" in commands[0]
    # the car in the left lane: its own world folder and its own results, even beside the right lane's
    (tmp_path / "heldout_surround4_seed2001").mkdir()
    (tmp_path / "heldout_surround4_seed2001" / "results.json").write_text("{}")
    heldout.score_heldout(tmp_path, 2001, "surround4", None, [], lane="left")
    assert f"hydra.run.dir={tmp_path / 'heldout_surround4_seed2001_laneleft'}" in commands[3]
    assert "++data.generate.lane=left" in commands[3]
    roots = [o for o in commands[3] if o.startswith("data.datamodule.root=")]
    template = yaml.safe_load((ROOT / "conf" / "data" / "synthetic.yaml").read_text())["datamodule"]["root"]
    assert roots == [f"data.datamodule.root={template}_laneleft"]
    assert not any("lane" in o for c in commands[:3] for o in c)
    heldout.score_heldout(tmp_path, 2001, "surround4", None, [])  # the right lane's is reused
    assert len(commands) == 4
    # from the command line
    monkeypatch.setattr(heldout, "scores", lambda path, traffic=False: "-")
    assert heldout.main([str(tmp_path), "--rig", "surround4", "--lane", "left", "--seeds", "2002"]) == 0
    assert "++data.generate.lane=left" in commands[4] and "data.generate.seed=2002" in commands[4]
    # worlds with traffic: their own data config and their own results folder
    assert heldout.main([str(tmp_path), "--traffic", "--seeds", "2003"]) == 0
    assert "data=synthetic_traffic" in commands[5]
    assert f"hydra.run.dir={tmp_path / 'heldout_kitti360_seed2003_traffic'}" in commands[5]
    assert "data=synthetic_traffic" not in commands[4]


def test_heldout_refuses_the_world_the_run_trained_on(tmp_path, monkeypatch):
    heldout = load_script("research/heldout")
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "last.ckpt").touch()
    (tmp_path / ".hydra").mkdir()
    config = {"data": {"generate": {"rig": "kitti360", "seed": 2001, "frames": 600}}}
    (tmp_path / ".hydra" / "config.yaml").write_text(yaml.safe_dump(config))
    commands = []
    monkeypatch.setattr(heldout.subprocess, "run", lambda command, **kw: commands.append(command))
    assert heldout.trained_world(tmp_path) == ("kitti360", 2001)
    with pytest.raises(ValueError, match=r"world 2001 \(kitti360\) is the world it trained on"):
        heldout.score_heldout(tmp_path, 2001, "kitti360", None, [])
    with pytest.raises(ValueError, match="is the world it trained on"):  # the same streets
        heldout.score_heldout(tmp_path, 2001, "kitti360", None, [], lane="left")
    heldout.score_heldout(tmp_path, 2001, "surround4", None, [])  # another rig: another world
    heldout.score_heldout(tmp_path, 2002, "kitti360", None, [])
    assert len(commands) == 2 and "data.generate.seed=2002" in commands[1]
    assert heldout.main([str(tmp_path), "--seeds", "2001"]) == 2 and len(commands) == 2


def test_debug_tiny_is_what_the_smoke_tests_use():
    cfg = compose_train(["+debug=tiny"])
    assert cfg.data.generate.frames == 12 and list(cfg.data.datamodule.size) == [64, 64]
    plain = compose_train(TINY)
    for key in ("data", "model", "eval", "trainer"):
        assert cfg[key] == plain[key], key


def run(script, *args, env=None, cwd=None, timeout=600):
    proc = subprocess.run(
        [sys.executable, str(ROOT / script), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=cwd or ROOT,
        env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("entry")


def test_fast_dev_run_through_train_py(workdir):
    """The full model through train.py, rendering its world on first use (the baseline: the sweep's)."""
    out = workdir / "fdr_ablation_full"
    proc = run(
        "train.py",
        "+experiment=ablation_full",
        "trainer.fast_dev_run=true",
        f"paths.data_dir={workdir}/data",
        f"hydra.run.dir={out}",
        "+debug=tiny",
    )
    assert (
        workdir / "data" / "synthetic_kitti360_64_seed0_f12" / "synthetic.json"
    ).is_file()  # generated once
    assert (out / ".hydra" / "config.yaml").is_file()
    assert "Warning" not in proc.stderr and "deprecated" not in proc.stderr, proc.stderr[-2000:]


def test_train_eval_resume_tables(workdir):
    first = workdir / "run1"
    run(
        "train.py",
        "+experiment=ablation_full",
        "trainer.max_epochs=1",
        "trainer.limit_train_batches=3",
        f"paths.data_dir={workdir}/data",
        f"hydra.run.dir={first}",
        "select=best",
        *TINY,
    )
    record = json.loads((first / "results.json").read_text())
    assert record["experiment"] == "ablation_full" and record["model"]["real_scale"] is True
    assert record["select"] == "best" and re.search(r"best-000\.ckpt$", record["checkpoint"])
    assert record["model"]["device"] == "cpu" and record["model"]["post_process"] == "none"
    for protocol in ("full", "kitti360"):
        assert {"none", "median", "none_by_angle"} <= set(record["results"][protocol])
    assert set(record["results"]["full"]["none_by_angle"]) == {"0-30", "30-60", "60-90", "90-180"}
    assert set(record["results"]["full"]["none_by_camera"]) == {"image_02", "image_03"}
    assert (
        0 < record["results"]["full"]["none"]["abs_rel"] < 50
        and record["results"]["full"]["none"]["images"] > 0
    )
    assert len(list((first / "predictions").glob("*.png"))) == 2
    assert (first / "checkpoints" / "last.ckpt").is_file()
    assert list((first / "logs").rglob("metrics.csv"))
    hparams = yaml.safe_load(next((first / "logs").rglob("hparams.yaml")).read_text())
    calib = workdir / "data" / "synthetic_kitti360_64_seed0_f12" / "calibration"
    focals = [min(load_camera(calib / f"image_0{i}.yaml").paraxial_focal()) for i in (2, 3)]
    assert hparams["net"]["base_focal"] == pytest.approx(sum(focals) / 2)  # auto, at the 64 px of TINY

    # eval.py's function in-process, on Hydra's composition of its config (heldout.py below runs eval.py)
    tiny_data = [o for o in TINY if o.startswith("data.") or o.startswith("eval.")]
    evaluated = workdir / "eval1"
    eval_checkpoint(
        compose_command(
            "eval",
            [
                f"ckpt_path={first / 'checkpoints' / 'last.ckpt'}",
                *command_paths(workdir, evaluated),
                *tiny_data,
            ],
        )
    )
    again = json.loads((evaluated / "results.json").read_text())
    assert again["checkpoint"].endswith("last.ckpt") and again["results"]["full"]["none"]["images"] > 0
    assert again["split"] == "test" and again["train_size"] == [64, 64]
    test_frames = (calib.parent / "splits" / "test.txt").read_text().splitlines()
    assert again["results"]["full"]["none"]["images"] == 2 * len(test_frames)  # every frame: its ends too
    assert again["experiment"] == "ablation_full"  # from the checkpoint's run: make_tables finds its row
    on_val = workdir / "eval_val"
    eval_checkpoint(
        compose_command(
            "eval",
            [
                f"ckpt_path={first / 'checkpoints' / 'last.ckpt'}",
                *command_paths(workdir, on_val),
                "split=val",
                *tiny_data,
                "data.datamodule.size=[32,32]",  # the data config's size: the checkpoint's wins
            ],
        )
    )
    val = json.loads((on_val / "results.json").read_text())
    assert val["split"] == "val" and val["train_size"] == [64, 64]
    assert val["results"]["full"]["none"]["abs_rel"] != again["results"]["full"]["none"]["abs_rel"]

    resumed = workdir / "run2"
    run(
        "train.py",
        "+experiment=ablation_full",
        "trainer.max_epochs=2",
        "trainer.limit_train_batches=3",
        f"ckpt_path={first / 'checkpoints' / 'last.ckpt'}",
        f"paths.data_dir={workdir}/data",
        f"hydra.run.dir={resumed}",
        *TINY,
    )
    after = json.loads((resumed / "results.json").read_text())
    assert after["select"] == "last" and after["checkpoint"].endswith("last.ckpt")  # the default
    assert torch.load(after["checkpoint"], weights_only=True)["epoch"] == 1  # the second, final epoch
    assert after["global_step"] == 2 * record["global_step"]  # one more epoch on top of the first
    assert after["resumed_from"].endswith("last.ckpt")

    curves = workdir / "curves"
    out = ["--out", f"{curves}.png", "--csv", f"{curves}.csv"]
    printed("research/plot_curves", [str(first), str(resumed), *out])
    rows = [line.split(",") for line in Path(f"{curves}.csv").read_text().splitlines()[1:]]
    val_loss = {(r[0], int(r[2])) for r in rows if r[1] == "val/loss"}
    assert {e for _, e in val_loss} == {0, 1} and all(float(r[3]) > 0 for r in rows if r[1] == "val/loss")
    assert Path(f"{curves}.png").stat().st_size > 10_000

    tables = printed("research/make_tables", [str(first), str(resumed), "--latex"])
    assert "FFT + RS + MC" in tables and "| 2 |" in tables and "\\begin{tabular}" in tables

    reproduced = printed(
        "research/reproduce",
        [
            "--runs",
            str(first),
            str(resumed),
            "--tables",
            "2",
            "--out",
            str(workdir / "reproduce"),
            "--no-write",
        ],
    )
    assert "best-NNN.ckpt x1, last.ckpt x1" in reproduced and "FFT + RS + MC | none | 2 |" in reproduced
    budget = next(line for line in reproduced.splitlines() if line.startswith("Budget overrides"))
    assert "trainer.max_epochs: differs" in budget and "trainer.limit_train_batches=3" in budget  # the runs'
    assert "select: differs" in budget and "model.scheduler.step_size" not in budget and "seed=" not in budget
    assert len(list((workdir / "reproduce").glob("*_runs/curves.png"))) == 1

    # last: its results.json files inside run1 would be collected by the table scripts above
    heldout = printed(
        "research/heldout",
        [str(first), "--seeds", "5", "--set", f"paths.data_dir={workdir}/data", *tiny_data],
    )
    assert (workdir / "data" / "synthetic_kitti360_64_seed5_f12" / "synthetic.json").is_file()
    row = next(line for line in heldout.splitlines() if line.startswith("| run1 |")).split(" | ")
    held = json.loads((first / "heldout_kitti360_seed5" / "results.json").read_text())["results"]
    assert row[2].rstrip(" |") == (
        f"{held['full']['none']['abs_rel']:.3f}, {held['full']['none']['a1']:.3f} / "
        f"{held['kitti360']['none']['abs_rel']:.3f}"
    )
    assert held["full"]["none"]["abs_rel"] != record["results"]["full"]["none"]["abs_rel"]  # another world


def test_the_tested_checkpoint_is_selected_without_ground_truth():
    best = SimpleNamespace(monitor="val/photometric", best_model_path="/r/best-004.ckpt")
    latest = SimpleNamespace(monitor=None, best_model_path="/r/last.ckpt")
    assert selected_checkpoint([best, latest], "last") == "/r/last.ckpt"
    assert selected_checkpoint([best, latest], "best") == "/r/best-004.ckpt"
    assert selected_checkpoint([best], "last") is None  # no per-epoch checkpoint: the weights in memory
    with pytest.raises(ValueError, match="select=best needs a ModelCheckpoint with a monitor"):
        selected_checkpoint([latest], "best")
    with pytest.raises(ValueError, match="select='lowest_abs_rel'"):
        selected_checkpoint([best, latest], "lowest_abs_rel")


class _Worsening(L.LightningModule):
    """Its validation loss rises every epoch, so the best checkpoint is epoch 0 and the last is not."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(1))

    def training_step(self, batch, batch_idx):
        return (self.w - 1.0).pow(2).sum()

    def validation_step(self, batch, batch_idx):
        self.log("val/photometric", float(self.current_epoch))

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


def test_last_ckpt_is_the_last_epoch_even_when_validation_stops_improving(tmp_path):
    """Lightning's ``save_last=True`` copies last.ckpt only when a top-k checkpoint is saved, so it
    would stop at the best epoch; the configured callbacks save the end of every epoch."""
    cfg = compose_train([f"paths.output_dir={tmp_path}", "hydra.run.dir=."])
    callbacks = [instantiate(c) for name, c in cfg.callbacks.items() if name != "progress"]
    loader = torch.utils.data.DataLoader(torch.zeros(2, 1), batch_size=1)
    trainer = L.Trainer(
        max_epochs=3, callbacks=callbacks, logger=False, enable_progress_bar=False, default_root_dir=tmp_path
    )
    trainer.fit(_Worsening(), loader, loader)
    saved = sorted(p.name for p in (tmp_path / "checkpoints").iterdir())
    assert saved == ["best-000.ckpt", "last.ckpt"]
    epoch = {n: torch.load(tmp_path / "checkpoints" / n, weights_only=True)["epoch"] for n in saved}
    assert epoch == {"best-000.ckpt": 0, "last.ckpt": 2}
    assert selected_checkpoint(callbacks, "last") == str(tmp_path / "checkpoints" / "last.ckpt")
    assert selected_checkpoint(callbacks, "best") == str(tmp_path / "checkpoints" / "best-000.ckpt")


def test_a_resumed_run_keeps_its_checkpoints_base_focal(tmp_path, caplog):
    data = SimpleNamespace(base_focal=lambda split: 25.0)
    assert resolve_base_focal(data, None) == 25.0
    for stored in (20.0, None):
        ckpt = tmp_path / f"{stored}.ckpt"
        torch.save({"hyper_parameters": {"base_focal": stored}}, ckpt)
        caplog.clear()
        assert resolve_base_focal(data, read_checkpoint(ckpt)) == stored  # not 25: the scale cannot change
        assert f"keeps its base_focal {stored}; the training cameras now give 25.000 px" in caplog.text
    torch.save({"hyper_parameters": {"base_focal": 25.0}}, tmp_path / "same.ckpt")
    caplog.clear()
    assert (
        resolve_base_focal(data, read_checkpoint(tmp_path / "same.ckpt")) == 25.0
        and "keeps" not in caplog.text
    )


def test_eval_names_the_row_by_the_checkpoints_run(tmp_path):
    ckpt = tmp_path / "run" / "checkpoints" / "last.ckpt"
    assert experiment_of(ckpt) is None  # no run folder: the row is unnamed unless experiment_name is given
    (tmp_path / "run" / ".hydra").mkdir(parents=True)
    (tmp_path / "run" / ".hydra" / "config.yaml").write_text("experiment_name: ablation_fft_mc\nseed: 1\n")
    assert experiment_of(ckpt) == "ablation_fft_mc"
    (tmp_path / "run" / ".hydra" / "config.yaml").write_text("experiment_name: [unclosed\n")
    with pytest.raises(ValueError, match=r"run/\.hydra/config\.yaml: not readable YAML"):
        experiment_of(ckpt)


def test_two_job_sweep_gets_two_output_folders(workdir):
    """Two jobs of a sweep, each in its folder, launched through Hydra's submitit launcher with its local
    executor (the SLURM launcher's path, ``hydra/launcher=slurm``, without a cluster); the Monodepth2
    baseline (PoseNet, sigmoid head, no fisheye warp) runs a step through train.py as the first."""
    sweep = workdir / "sweep"
    proc = run(
        "train.py",
        "-m",
        "hydra/launcher=submitit_local",
        "+experiment=ablation_baseline,ablation_fft_only",
        "trainer.fast_dev_run=true",
        f"paths.data_dir={workdir}/data",
        f"hydra.sweep.dir={sweep}",
        *TINY,
    )
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir() and (p / ".hydra").is_dir())
    assert len(jobs) == 2 and all((j / ".hydra" / "config.yaml").is_file() for j in jobs)
    names = {(j / ".hydra" / "overrides.yaml").read_text().count("ablation_baseline") for j in jobs}
    assert names == {0, 1}
    submitted = list((sweep / ".submitit").glob("*/*_result.pkl"))
    assert len(submitted) == 2  # each job ran as a submitit job and returned
    assert "Warning" not in proc.stderr and "deprecated" not in proc.stderr, proc.stderr[-2000:]


def test_wandb_offline_without_an_account(workdir, monkeypatch):
    """``logger=wandb`` (train.py's function on its composed config): an offline run, no account."""
    out = workdir / "wandb_run"
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    overrides = ["logger=wandb", "trainer.max_epochs=1", "trainer.limit_train_batches=1"]
    overrides += ["trainer.limit_val_batches=1", "test=false", "callbacks.progress=null", *TINY]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("train", [*overrides, *command_paths(workdir, out)])
    train(cfg)  # (fast_dev_run would mute the logger)
    runs = list(out.rglob("offline-run-*"))
    assert runs and list(runs[0].rglob("*.wandb"))


def test_cpu_ddp_with_two_gloo_processes(workdir):
    out = workdir / "ddp"
    proc = run(
        "train.py",
        "trainer=ddp",
        "trainer.accelerator=cpu",
        "trainer.devices=2",
        "trainer.sync_batchnorm=false",
        "trainer.max_epochs=1",
        "trainer.limit_train_batches=2",
        "trainer.limit_val_batches=1",
        "test=false",
        "logger=none",
        f"paths.data_dir={workdir}/data",
        f"hydra.run.dir={out}",
        *TINY,
        timeout=900,
    )
    text = proc.stdout + proc.stderr
    assert "distributed_backend=gloo" in text and "All distributed processes registered" in text


def test_slurm_launcher_config_composes():
    cfg = compose_train(["hydra/launcher=slurm", "+experiment=ablation_full"])
    assert cfg.hydra.launcher.gpus_per_node == 1
    assert (ROOT / "conf" / "hydra" / "launcher" / "slurm.yaml").is_file()


def test_precision_auto_is_bf16_only_where_bf16_is_native(monkeypatch):
    """``trainer.precision: auto``: bf16-mixed on a CPU with AVX-512 BF16, float32 on one without (bf16
    is emulated there and several times slower); an explicit precision is passed through."""
    for native, expected in ((True, "bf16-mixed"), (False, "32-true")):
        monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda native=native: native)
        assert resolve_precision("auto", "cpu") == expected
    assert resolve_precision("16-mixed", "cpu") == "16-mixed" and resolve_precision(None, "cpu") is None
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_precision("auto", "gpu") == "32-true"  # no GPU here: nothing claims bf16


def test_the_data_module_loads_the_sources_the_model_warps(tmp_path):
    """``model.objective.source_offsets`` reaches the data module (it once did not: ``[-2,2]`` trained
    on the +-1 neighbours); a contradicting ``data.datamodule.offsets`` is refused, naming both."""
    from fisheyedepth.config import source_offsets

    cfg = compose_train(["model.objective.source_offsets=[-3,1]", f"paths.data_dir={tmp_path}"])
    assert source_offsets(cfg) == [-3, 1]
    datamodule = instantiate(cfg.data.datamodule, offsets=source_offsets(cfg))
    assert datamodule.offsets == (-3, 1)
    assert source_offsets(compose_train([])) == [-2, 2]
    clash = compose_train(["model.objective.source_offsets=[-2,2]", "+data.datamodule.offsets=[-1,1]"])
    differs = r"data.datamodule.offsets=\[-1, 1\] differs from model.objective.source_offsets=\[-2, 2\]"
    with pytest.raises(ValueError, match=differs):
        source_offsets(clash)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_train_eval_predict_on_cuda(tmp_path):
    """The GPU path end to end: train on the GPU, score on the GPU and on the CPU (the same numbers),
    predict on the GPU. ``eval.py device=cuda`` once failed: its metrics stayed on the CPU."""
    data = f"paths.data_dir={tmp_path}/data"
    train = tmp_path / "train"
    run(
        "train.py",
        "trainer=gpu",
        "trainer.max_epochs=1",
        "trainer.limit_train_batches=3",
        data,
        f"hydra.run.dir={train}",
        "eval.pictures=1",
        *TINY,
    )
    # the test after training runs where training ran (the checkpoint loads on the CPU)
    assert json.loads((train / "results.json").read_text())["model"]["device"] == "cuda:0"
    ckpt = train / "checkpoints" / "last.ckpt"
    scores = {}
    for device in ("cpu", "cuda"):
        out = tmp_path / f"eval_{device}"
        run(
            "eval.py",
            f"ckpt_path={ckpt}",
            f"device={device}",
            data,
            f"hydra.run.dir={out}",
            "eval.pictures=1",
        )
        scores[device] = json.loads((out / "results.json").read_text())["results"]["full"]["none"]
    assert scores["cuda"]["images"] == scores["cpu"]["images"] > 0
    assert scores["cuda"]["abs_rel"] == pytest.approx(scores["cpu"]["abs_rel"], rel=1e-3)
    frames = tmp_path / "data" / "synthetic_kitti360_64_seed0_f12" / "data_2d_raw"
    images = next(frames.rglob("image_02")) / "data_rgb"
    calib = tmp_path / "data" / "synthetic_kitti360_64_seed0_f12" / "calibration" / "image_02.yaml"
    predicted = tmp_path / "predicted"
    run(
        "predict.py",
        f"ckpt_path={ckpt}",
        f"input={images}",
        f"camera={calib}",
        "device=cuda",
        f"output={predicted}",
        "max_frames=2",
        f"hydra.run.dir={tmp_path / 'predict'}",
    )
    assert len(list(predicted.glob("*_distance.npy"))) == 2


def test_a_benchmark_loads_after_a_test_restored_sys_path(monkeypatch):
    """The benchmarks find ``_compose`` in ``scripts/``, which their ``_benchmarks`` puts on ``sys.path``
    when first imported; once a test's ``monkeypatch`` has restored ``sys.path``, the cached module puts
    nothing back, and loading a script still finds it."""
    load_script("bench/bench_fit")
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p != str(ROOT / "scripts")])
    monkeypatch.delitem(sys.modules, "_compose", raising=False)
    assert load_script("bench/bench_inference").__name__ == "bench_inference"
    assert str(ROOT / "scripts") not in sys.path  # as it was: the loader restores what it added
