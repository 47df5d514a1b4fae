"""Options that are not what they say: a switch set to ``maybe``, a NaN or infinite weight, a negative
count, an effect with a level, a traffic density no render finishes. Each is refused by its name as
configured, with one ``error:`` line and exit status 2, before anything is rendered or trained (so these
runs are refused in milliseconds, into folders that stay empty); the shipped configs all pass."""

from __future__ import annotations

import dataclasses
import inspect
import math
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from fisheyedepth.cli.train import train
from fisheyedepth.config import check_config
from fisheyedepth.options.kinds import Group, Number, check_options
from fisheyedepth.options.tables import DATAMODULE_OPTIONS, MODEL_OPTIONS
from fisheyedepth.synthetic import GENERATE_OPTIONS

from conftest import ROOT, TINY, bare_module, bare_objective
from test_faults_entrypoints import one_line_error

EFFECTS = "exposure, white_balance, vignetting, noise, motion_blur"


def train_cfg(tmp_path: Path, *overrides: str):
    """train.py's tiny config, its data and run folders under ``tmp_path`` (neither exists yet)."""
    paths = [f"paths.data_dir={tmp_path / 'data'}", f"paths.output_dir={tmp_path / 'run'}"]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose("train", [*TINY, *paths, *overrides])


REFUSED = {
    # what a user met: 'maybe' ran as true and was recorded, nan acted as 0, inf skipped every step
    "data.generate.random_cameras=maybe": (
        "data.generate.random_cameras: 'maybe' is not a boolean (true or false)"
    ),
    "model.objective.automask=maybe": "model.objective.automask: 'maybe' is not a boolean (true or false)",
    "model.objective.truth_weight=nan": "model.objective.truth_weight: nan is not a finite number >= 0",
    "model.objective.photometric_weight=inf": (
        "model.objective.photometric_weight: inf is not a finite number >= 0"
    ),
    # a TypeError traceback, and Hydra's multi-line block with exit 1 (the loss compared 'abc' with 0)
    "data.generate.effects=[{noise: -1}]": (
        f"data.generate.effects[0]: {{'noise': -1}} is not one of {EFFECTS} (each effect a switch, "
        "named alone)"
    ),
    "model.objective.outliers=abc": "model.objective.outliers: 'abc' is not a number",
    # a render that had not finished 9 frames after 400 s
    "data.generate.traffic=1000": (
        "data.generate.traffic: 1000 is not a number in [0, 8] (0: no traffic, 1: a busy street)"
    ),
    # one of each group
    "model.net.n_bins=1": "model.net.n_bins: 1 is not a whole number >= 2",
    "model.net.scales=[0,5]": (
        "model.net.scales[1]: 5 is not a whole number in [0, 4] (the decoder's 5 levels)"
    ),
    "model.net.base_focal=autos": "model.net.base_focal: 'autos' is not a number or auto",
    "model.objective.real_scale=1": "model.objective.real_scale: 1 is not a boolean (true or false)",
    "model.objective.outliers=1.0": (
        "model.objective.outliers: 1.0 is not a number in [0, 1) (the fraction of each image's "
        "pixels left out)"
    ),
    "model.objective.source_offsets=[-1,0.5]": "model.objective.source_offsets[1]: 0.5 is not a whole number",
    "model.optimizer.lr=0": "model.optimizer.lr: 0 is not a finite number > 0",
    "model.optimizer.weight_decay=-1e-5": "model.optimizer.weight_decay: -1e-05 is not a finite number >= 0",
    "model.scheduler.step_size=0": "model.scheduler.step_size: 0 is not a whole number >= 1",
    "model.scheduler.gamma=nan": "model.scheduler.gamma: nan is not a finite number > 0",
    "model.log_images_every=-1": "model.log_images_every: -1 is not a whole number >= 0",
    "model.compile_kernels=yes": "model.compile_kernels: 'yes' is not a boolean (true or false)",
    "model.eval_cap=[80]": "model.eval_cap: [80] is not a list of 2 values",
    "data.datamodule.batch_size=0": "data.datamodule.batch_size: 0 is not a whole number >= 1",
    "data.datamodule.num_workers=1.5": "data.datamodule.num_workers: 1.5 is not a whole number",
    "data.datamodule.skip_bad_frames=maybe": (
        "data.datamodule.skip_bad_frames: 'maybe' is not a boolean (true or false)"
    ),
    "data.datamodule.augment.flip=2": (
        "data.datamodule.augment.flip: 2 is not a number in [0, 1] (a probability)"
    ),
    "data.datamodule.pose_noise.rotation_deg=-1": (
        "data.datamodule.pose_noise.rotation_deg: -1 is not a finite number >= 0"
    ),
    "data.datamodule.source_baseline=-1.0": (
        "data.datamodule.source_baseline: -1.0 is not a finite number > 0"
    ),
    "data.generate.frames=5": "data.generate.frames: 5 is not a whole number >= 9 (3 per split)",
    "data.generate.supersample=0": "data.generate.supersample: 0 is not a whole number >= 1",
    "data.generate.seed=-1": "data.generate.seed: -1 is not a whole number >= 0",
    # the trainer: a traceback (max_steps), a run without end (max_epochs -1), and the scores of a network
    # never trained (max_epochs 0, no training batch)
    "trainer.max_steps=-5": (
        "trainer.max_steps: -5 is not a whole number >= 1 or -1 (-1: no limit but max_epochs)"
    ),
    "trainer.max_steps=0": (
        "trainer.max_steps: 0 is not a whole number >= 1 or -1 (-1: no limit but max_epochs)"
    ),
    "trainer.max_epochs=-1": (
        "trainer.max_epochs: -1 is not a whole number >= 1 (-1 would train without end, 0 not at all)"
    ),
    "trainer.max_epochs=0": (
        "trainer.max_epochs: 0 is not a whole number >= 1 (-1 would train without end, 0 not at all)"
    ),
    "trainer.max_epochs=2.5": "trainer.max_epochs: 2.5 is not a whole number",
    "trainer.limit_train_batches=0": (
        "trainer.limit_train_batches: 0 is not a fraction in (0, 1] or a whole number of batches >= 1"
    ),
    "trainer.limit_val_batches=1.5": (
        "trainer.limit_val_batches: 1.5 is not a fraction in (0, 1] or a whole number of batches >= 0 "
        "(0: no validation)"
    ),
    "+trainer.val_check_interval=0": (
        "trainer.val_check_interval: 0 is not a fraction in (0, 1] or a whole number of batches >= 1"
    ),
    "+trainer.accumulate_grad_batches=0": "trainer.accumulate_grad_batches: 0 is not a whole number >= 1",
    "trainer.gradient_clip_val=-1": (
        "trainer.gradient_clip_val: -1 is not a finite number >= 0 (null or 0: no clipping)"
    ),
    "trainer.gradient_clip_val=nan": (
        "trainer.gradient_clip_val: nan is not a finite number >= 0 (null or 0: no clipping)"
    ),
    "trainer.log_every_n_steps=0": "trainer.log_every_n_steps: 0 is not a whole number >= 1",
    "trainer.check_val_every_n_epoch=0": "trainer.check_val_every_n_epoch: 0 is not a whole number >= 1",
    "trainer.num_sanity_val_steps=-2": (
        "trainer.num_sanity_val_steps: -2 is not a whole number >= -1 (-1: every validation batch)"
    ),
    "trainer.precision=17": (
        "trainer.precision: 17 is not one of auto, 32-true, 32, bf16-mixed, bf16-true, bf16, 16-mixed, "
        "16-true, 16, 64-true, 64, transformer-engine, transformer-engine-float16"
    ),
    "trainer.accelerator=tpu": "trainer.accelerator: 'tpu' is not one of auto, cpu, cuda, gpu, mps",
    "trainer.devices=0": (
        "trainer.devices: 0 is not a whole number >= 1, -1 (every device), auto or a list of device numbers"
    ),
    "trainer.fast_dev_run=-1": "trainer.fast_dev_run: -1 is not a boolean or a whole number of batches >= 1",
    "trainer.deterministic=maybe": "trainer.deterministic: 'maybe' is not true, false or warn",
    # options each of their kind that contradict each other: a traceback in the first validation (no
    # scale), a network that predicted 173 m everywhere (min_distance above max_distance)
    "model.net.scales=[]": (
        "model.net.scales: [] does not hold 0; the distance the network gives is that of scale 0 (full "
        "resolution): [0], or [0, 1, 2, 3] for the loss at four scales"
    ),
    "model.net.scales=[1,2]": (
        "model.net.scales: [1, 2] does not hold 0; the distance the network gives is that of scale 0 (full "
        "resolution): [0], or [0, 1, 2, 3] for the loss at four scales"
    ),
    "model.net.min_distance=200": (
        "model.net.min_distance: 200 is not below model.net.max_distance (150.0); every distance the "
        "network gives lies between them"
    ),
    "model.net.max_distance=0.5": (
        "model.net.min_distance: 0.5 is not below model.net.max_distance (0.5); every distance the "
        "network gives lies between them"
    ),
    "model.objective.source_offsets=[]": (
        "model.objective.source_offsets: [] with no model.objective.rig_offsets names no source frame; the "
        "photometric loss warps at least one: [-1, 1], or rig_offsets [0] on a rig"
    ),
}


@pytest.mark.parametrize("override", REFUSED)
def test_an_option_not_of_its_kind_is_named_before_anything_is_rendered_or_trained(
    override, tmp_path, capsys
):
    assert one_line_error(train, train_cfg(tmp_path, override), capsys) == f"error: {REFUSED[override]}"
    assert list(tmp_path.iterdir()) == []  # no data rendered, no run folder


def test_the_multiview_network_without_sources_is_refused(tmp_path, capsys):
    """The cost volume matches the target against its sources: with none, a traceback in the first step."""
    cfg = train_cfg(tmp_path, "model=fisheyedepth_mv", "model.objective.source_offsets=[]")
    assert one_line_error(train, cfg, capsys) == (
        "error: model.objective.source_offsets: [] with no model.objective.rig_offsets names no source "
        "frame; the photometric loss warps at least one: [-1, 1], or rig_offsets [0] on a rig"
    )
    cfg = train_cfg(tmp_path, "model=fisheyedepth_mv", "model.net.cost_volume_min=100")
    assert one_line_error(train, cfg, capsys) == (
        "error: model.net.cost_volume_min: 100 is not below model.net.cost_volume_max (80.0); the cost "
        "volume's hypotheses lie between them"
    )
    assert list(tmp_path.iterdir()) == []
    cfg = train_cfg(tmp_path, "model.objective.source_offsets=[]", "model.objective.rig_offsets=[0]")
    check_training_of(cfg)  # the rig's other cameras are sources enough


def check_training_of(cfg) -> None:
    """What train.py's plan checks beyond config.check_config: the trainer, options that contradict each
    other, memory."""
    from fisheyedepth.config import rig_offsets, source_offsets
    from fisheyedepth.plan import check_training, data_plan, model_plan

    check_training(cfg, model_plan(cfg), data_plan(cfg, source_offsets(cfg), rig_offsets(cfg)))


def test_each_world_of_a_mixed_dataset_is_checked(tmp_path, capsys):
    cfg = train_cfg(tmp_path, "data=synthetic_mixed", "data.generate.worlds.2.seed=0.5")
    assert (
        one_line_error(train, cfg, capsys) == "error: data.generate.worlds[2].seed: 0.5 is not a whole number"
    )
    assert list(tmp_path.iterdir()) == []


EXPERIMENTS = sorted(p.stem for p in (ROOT / "conf" / "experiment").glob("[!_]*.yaml"))
SHIPPED = [
    *([f"+experiment={e}"] for e in EXPERIMENTS),
    *([f"model={m.stem}"] for m in sorted((ROOT / "conf" / "model").glob("*.yaml"))),
    *([f"data={d.stem}"] for d in sorted((ROOT / "conf" / "data").glob("[!_]*.yaml"))),
    *([f"trainer={t.stem}"] for t in sorted((ROOT / "conf" / "trainer").glob("*.yaml"))),
    ["model/scheduler=cosine"],
    ["+debug=tiny"],
]


@pytest.mark.parametrize("overrides", SHIPPED, ids=lambda o: o[0])
def test_every_shipped_config_passes_the_checks(overrides, tmp_path):
    paths = [f"paths.data_dir={tmp_path / 'data'}", f"paths.output_dir={tmp_path / 'run'}"]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("train", [*overrides, *paths])
    check_config(cfg)
    check_training_of(cfg)


def test_the_classes_that_read_the_options_check_them_too(tmp_path):
    """Without a config (a script, a notebook) the module, the objective and the data module refuse the
    same values under their own names."""
    from fisheyedepth.data import Augment, FisheyeDataModule

    with pytest.raises(
        ValueError, match=r"^objective\.automask: 'maybe' is not a boolean \(true or false\)$"
    ):
        bare_module(objective={"automask": "maybe"})
    with pytest.raises(ValueError, match=r"^truth_weight: nan is not a finite number >= 0$"):
        bare_objective(truth_weight=math.nan)
    with pytest.raises(ValueError, match=r"^outliers: 'abc' is not a number$"):  # was a TypeError
        bare_objective(outliers="abc")
    with pytest.raises(ValueError, match="truth_weight 0.0, photometric_weight 0.0"):  # the two weights
        bare_objective(truth_weight=0.0, photometric_weight=0.0)
    with pytest.raises(ValueError, match=r"^batch_size: 0 is not a whole number >= 1$"):
        FisheyeDataModule(tmp_path, batch_size=0)
    with pytest.raises(ValueError, match=r"^augment\.hue: 0\.7 is not a number in \[0, 0\.5\]"):
        FisheyeDataModule(tmp_path, augment={"hue": 0.7})
    assert FisheyeDataModule(tmp_path, augment=Augment(flip=1.0)).augment.flip == 1.0  # made already


def test_a_number_is_finite_of_its_kind_and_within_its_range():
    def complaint(kind, value) -> str | None:
        try:
            kind.check("x", value)
        except ValueError as exc:
            return str(exc)
        return None

    fraction = Number(0.0, 1.0, below=True)
    assert [complaint(fraction, v) for v in (0, 0.0, 0.999)] == [None] * 3
    assert complaint(fraction, 1.0) == "x: 1.0 is not a number in [0, 1)"
    assert complaint(fraction, -0.1) == "x: -0.1 is not a number in [0, 1)"
    assert complaint(fraction, math.nan) == "x: nan is not a number in [0, 1)"
    assert complaint(fraction, True) == "x: True is not a number"  # a boolean is not a number
    positive = Number(low=0.0, above=True, optional=True)
    assert complaint(positive, None) is None
    assert complaint(positive, 0.0) == "x: 0.0 is not a finite number > 0"
    assert complaint(positive, math.inf) == "x: inf is not a finite number > 0"
    assert complaint(Number(high=3.0, below=True), 3) == "x: 3 is not a finite number < 3"
    count = Number(low=1, whole=True)
    assert complaint(count, 2) is None
    assert complaint(count, 2.0) == "x: 2.0 is not a whole number"  # 2.0 from a config is not an integer
    assert complaint(count, 0) == "x: 0 is not a whole number >= 1"
    assert complaint(Number(), -1e300) is None


def test_the_tables_name_the_options_of_their_readers():
    """A misspelt key in a table would check nothing: each names an argument its reader takes, and the
    readers' defaults pass."""
    from fisheyedepth.data import Augment, FisheyeDataModule, PoseNoise
    from fisheyedepth.options.defaults import model_options
    from fisheyedepth.synthetic import WorldSpec, ensure_dataset

    def arguments(function) -> set[str]:
        return set(inspect.signature(function).parameters)

    defaults = model_options(scheduler={"T_max": 8, "eta_min": 0.0})  # with the cosine schedule's keys
    for name, kind in MODEL_OPTIONS.items():
        assert name in defaults, name
        if isinstance(kind, Group):
            assert set(kind.table) <= set(defaults[name]), name
    check_options(defaults, MODEL_OPTIONS)
    assert set(DATAMODULE_OPTIONS) <= arguments(FisheyeDataModule.__init__)
    assert set(DATAMODULE_OPTIONS["augment"].table) <= {f.name for f in dataclasses.fields(Augment)}
    assert set(DATAMODULE_OPTIONS["pose_noise"].table) <= {f.name for f in dataclasses.fields(PoseNoise)}
    spec = {f.name for f in dataclasses.fields(WorldSpec)}  # what the dataset is; the others: how rendered
    assert set(GENERATE_OPTIONS) - {"worlds"} <= arguments(ensure_dataset) | spec
    generate = {
        "frames": 9,
        "traffic": 8,
        "effects": "noise",
        "worlds": [{"seed": 1, "random_cameras": True}],
    }
    check_options(generate, GENERATE_OPTIONS)  # the bound itself, one effect alone, a world
