"""Faults of what a training run and the commands after it read: options that ask for more memory than the
machine has, checkpoints whose weights are not finite or whose hyper-parameters cannot describe their
network, a checksum file that names a file twice, a pickled ground-truth map; and the accelerator a run
chooses. Each bad input is refused with one line naming the option or the file (and the field), exit
status 2, before anything is rendered, trained or written."""

from __future__ import annotations

import copy
import pickle
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

import fisheyedepth.options.memory as option_memory
from fisheyedepth.checkpoints import (
    CHECKSUMS,
    RELEASED,
    CheckpointError,
    check_resumable,
    released_checkpoint,
    sha256,
)
from fisheyedepth.cli.export import export
from fisheyedepth.cli.train import train
from fisheyedepth.data.files import read_distance
from fisheyedepth.module import FisheyeDepthModule
from fisheyedepth.options.kinds import Either, Number
from fisheyedepth.options.memory import in_bytes, machine_memory
from fisheyedepth.plan import choose_accelerator, describe_accelerator, train_plan
from fisheyedepth.runtimes import TrainedDepthNet
from fisheyedepth.synthetic import WorldSpec, generate
from fisheyedepth.synthetic.writer import ensure_datasets
from test_faults_options import train_cfg

from conftest import bare_module, load_script, script_folder
from test_faults_entrypoints import one_line_error, python

GiB = 2**30


@pytest.fixture
def sixteen_gib(monkeypatch):
    """A machine of 16 GiB, whatever this one has: the messages below state both numbers."""
    monkeypatch.setattr(option_memory, "machine_memory", lambda: 16 * GiB)


# ------------------------------------------------------------------ memory
MEMORY = {
    # 160 GB of rays asked for: the render was killed (or swapped for hours)
    ("data.generate.size=100000",): (
        "data.generate.size: 100000 needs 6.91 TiB of memory (1 renderer(s) x 2 cameras x (100000^2 "
        "supersampled + 100000^2 centre) rays x 190 bytes); this machine has 16 GiB"
    ),
    ("data.generate.size=256", "data.generate.supersample=100"): (
        "data.generate.supersample: 100 needs 232 GiB of memory (1 renderer(s) x 2 cameras x (25600^2 "
        "supersampled + 256^2 centre) rays x 190 bytes); this machine has 16 GiB"
    ),
    ("data.generate.size=512", "data.generate.supersample=2", "data.generate.workers=64"): (
        "data.generate.workers: 64 needs 30.2 GiB of memory (65 renderer(s) x 2 cameras x (1024^2 "
        "supersampled + 512^2 centre) rays x 190 bytes); this machine has 16 GiB"
    ),
    ("data.generate.frames=1000000000",): (
        "data.generate.frames: 1000000000 needs 2.18 TiB of memory (its trajectory and a render job a frame, "
        "2400 bytes each); this machine has 16 GiB"
    ),
    # 864 GB of weights for the fusing convolution alone
    ("model=fisheyedepth_mv", "model.net.cost_volume=1000000000"): (
        "model.net.cost_volume: 1000000000 needs 450 TiB of memory (distance hypotheses matched on 24 "
        "channels; a training step of 2 images of 64x64, 2 sources each); this machine has 16 GiB"
    ),
    ("model.net.n_bins=100000000",): (
        "model.net.n_bins: 100000000 needs 15.5 TiB of memory (the binned head's logits at 2 scales; a "
        "training step of 2 images of 64x64); this machine has 16 GiB"
    ),
}


def not_refused(plan):
    raise AssertionError(f"planned, not refused: {plan}")


@pytest.mark.parametrize("overrides", MEMORY, ids=lambda o: o[-1])
def test_an_option_that_needs_more_memory_than_the_machine_has_is_named(
    overrides, tmp_path, capsys, sixteen_gib, monkeypatch
):
    monkeypatch.setattr("fisheyedepth.cli.train.fit_and_test", not_refused)
    assert one_line_error(train, train_cfg(tmp_path, *overrides), capsys) == f"error: {MEMORY[overrides]}"
    assert list(tmp_path.iterdir()) == []  # nothing rendered, no run folder


def test_what_fits_is_not_refused(tmp_path, sixteen_gib):
    """The bounds are the allocation itself: a large render that fits in 16 GiB passes."""
    from test_faults_options import check_training_of

    cfg = train_cfg(
        tmp_path, "data.generate.size=1024", "data.generate.supersample=2", "data.generate.workers=2"
    )
    check_training_of(cfg)  # 3 renderers x 2 cameras x (2048^2 + 1024^2) rays x 190 bytes: 5.6 GiB


def test_the_renderer_and_the_network_bound_their_own_options(tmp_path, sixteen_gib):
    """Without a config (the synthetic command, a script, a checkpoint) the same bounds hold."""
    with pytest.raises(ValueError, match=r"^size: 100000 needs 17\.3 TiB of memory \(") as info:
        generate(tmp_path / "out", WorldSpec(size=100000), progress=False)
    assert str(info.value).endswith("; this machine has 16 GiB")
    with pytest.raises(ValueError, match=r"^data\.generate\.worlds\[1\]\.supersample: 100 needs 232 GiB "):
        worlds = [{"seed": 0}, {"seed": 1, "supersample": 100}]
        ensure_datasets([tmp_path / "a", tmp_path / "b"], {"size": 256, "worlds": worlds})
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match=r"^net\.n_bins: 1000000000 needs 7\.87 TiB of memory \(the binned"):
        bare_module(net={"n_bins": 10**9})  # run-time weights alone, 4 bytes each


def test_the_machines_memory_is_stated_by_train_py(tmp_path):
    """Through the entry point, on this machine: one line, exit 2, nothing rendered."""
    run, data = tmp_path / "run", tmp_path / "data"
    proc = python("train.py", "data.generate.size=100000", f"hydra.run.dir={run}", f"paths.data_dir={data}")
    assert proc.returncode == 2, proc.stderr[-2000:]
    last = proc.stderr.strip().splitlines()[-1]
    assert last == (  # data=synthetic renders with 2 workers besides the main process
        "error: data.generate.size: 100000 needs 51.8 TiB of memory (3 renderer(s) x 2 cameras x (200000^2 "
        f"supersampled + 100000^2 centre) rays x 190 bytes); this machine has {in_bytes(machine_memory())}"
    )
    assert "Traceback" not in proc.stderr
    assert not data.exists() and not (run / "checkpoints").exists()


def test_a_kind_may_take_a_value_outside_its_range_or_one_of_two_kinds():
    steps = Number(low=1, whole=True, also=(-1,))
    steps.check("x", -1)
    with pytest.raises(ValueError, match=r"^x: 0 is not a whole number >= 1 or -1$"):
        steps.check("x", 0)
    batches = Either((Number(0.0, 1.0, above=True), Number(low=1, whole=True)), "a fraction or a count")
    batches.check("x", 0.25)
    batches.check("x", 3)
    with pytest.raises(ValueError, match=r"^x: 1.5 is not a fraction or a count$"):
        batches.check("x", 1.5)


# ------------------------------------------------------------------ checkpoints
LIGHTNING = {"pytorch-lightning_version": "2.6.0", "optimizer_states": [], "loops": {}, "epoch": 0}
LIGHTNING |= {"global_step": 0}  # what a resume needs besides the weights
HEAD = "depth_net.heads.0.logits.1.weight"  # [64, 16, 3, 3]


@pytest.fixture(scope="module")
def trained():
    """A checkpoint's dictionary as Lightning saves it: a 64x64 two-scale network and its options."""
    torch.manual_seed(0)
    module = bare_module(net={"scales": (0, 1), "base_focal": 20.0}, input_size=(64, 64))
    return {"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams), **LIGHTNING}


def saved(trained, path: Path, change) -> Path:
    ckpt = copy.deepcopy(trained)
    change(ckpt)
    torch.save(ckpt, path)
    return path


def refused_everywhere(path: Path, tmp_path: Path, capsys) -> str:
    """The message a checkpoint gets from every reader: predict and eval's network, the module, a resume
    and export.py; export writes nothing."""
    with pytest.raises(CheckpointError) as info:
        TrainedDepthNet.from_checkpoint(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and "\n" not in message
    for read in (FisheyeDepthModule.from_checkpoint, check_resumable):
        with pytest.raises(CheckpointError) as again:
            read(path)
        assert str(again.value) == message
    out = tmp_path / "exported.onnx"
    cfg = OmegaConf.create({"ckpt_path": str(path), "format": "onnx", "output": str(out)})
    assert one_line_error(export, cfg, capsys) == f"error: {message}"
    assert not out.exists()
    return message


@pytest.mark.parametrize("value", [float("nan"), float("inf")], ids=["nan", "inf"])
def test_a_checkpoint_with_weights_that_are_not_finite_is_refused(trained, value, tmp_path, capsys):
    """It predicted 0 finite pixels with exit 0, and eval wrote abs_rel: NaN."""

    def poison(ckpt):
        ckpt["state_dict"][HEAD] = ckpt["state_dict"][HEAD].clone()
        ckpt["state_dict"][HEAD][0, 0, 0, :2] = value
        ckpt["state_dict"]["depth_net.heads.1.logits.1.bias"] = torch.full((64,), value)  # not the first

    path = saved(trained, tmp_path / "diverged.ckpt", poison)
    assert refused_everywhere(path, tmp_path, capsys) == (
        f"{path}: weight {HEAD} holds 2 NaN or infinite value(s) of 9216; a network with them predicts no "
        "distance (a diverged run: take an earlier checkpoint)"
    )
    run = tmp_path / "run"
    cfg = train_cfg(tmp_path, f"ckpt_path={path}", f"paths.output_dir={run}")
    assert one_line_error(train, cfg, capsys).startswith(f"error: {path}: weight {HEAD} holds 2 NaN")
    assert not run.exists()


def test_a_checkpoint_whose_distances_are_reversed_is_refused(trained, tmp_path, capsys):
    """min_distance 200 over max_distance 150 trained, and predicted 173 m at every pixel."""

    def reverse(ckpt):
        ckpt["hyper_parameters"]["net"] = {**ckpt["hyper_parameters"]["net"], "min_distance": 200.0}

    path = saved(trained, tmp_path / "reversed.ckpt", reverse)
    assert refused_everywhere(path, tmp_path, capsys) == (
        f"{path}: hyper_parameters net.min_distance: 200.0 is not below net.max_distance (150.0); every "
        "distance the network gives lies between them"
    )


def test_a_checkpoint_without_its_network_group_names_the_file_and_the_group(trained, tmp_path, capsys):
    """It was refused as ``base_focal='auto': ...``, naming neither (the module's defaults filled the gap)."""
    path = saved(trained, tmp_path / "no_net.ckpt", lambda ckpt: ckpt["hyper_parameters"].pop("net"))
    assert refused_everywhere(path, tmp_path, capsys) == (
        f"{path}: hyper_parameters has no net group (the network's options: encoder, n_bins, min_distance, "
        "max_distance, scales, ...); its network cannot be built as it was trained"
    )
    path = saved(trained, tmp_path / "net_text.ckpt", lambda ckpt: ckpt["hyper_parameters"].update(net="x"))
    assert refused_everywhere(path, tmp_path, capsys) == (
        f"{path}: hyper_parameters.net is a str, not a mapping"
    )


def test_a_checkpoint_whose_network_does_not_fit_in_memory_is_not_built(
    trained, tmp_path, capsys, sixteen_gib
):
    def huge(ckpt):
        ckpt["hyper_parameters"]["net"] = {**ckpt["hyper_parameters"]["net"], "n_bins": 10**9}

    path = saved(trained, tmp_path / "huge.ckpt", huge)
    with pytest.raises(
        CheckpointError, match=r"hyper_parameters net\.n_bins: 1000000000 needs 1\.58 TiB of memory"
    ):
        TrainedDepthNet.from_checkpoint(path)


# ------------------------------------------------------------------ checksums
def test_a_checksum_file_that_names_a_file_twice_is_refused(trained, tmp_path):
    """Listed wrong then right, the weights were accepted: which line holds cannot be told."""
    weights = tmp_path / RELEASED
    torch.save(trained, weights)
    right, wrong = sha256(weights), "0" * 64
    (tmp_path / CHECKSUMS).write_text(f"{wrong}  {RELEASED}\n{right}  {RELEASED}\n")
    with pytest.raises(CheckpointError) as info:
        released_checkpoint(tmp_path)
    assert str(info.value) == (
        f"{tmp_path / CHECKSUMS}: line 2: {RELEASED} is listed again (first on line 1); one checksum per file"
    )
    (tmp_path / CHECKSUMS).write_text(f"{right}  {RELEASED}\n")
    assert released_checkpoint(tmp_path) == weights

    out = tmp_path / "release"  # the release script reads the file before it writes anything
    out.mkdir()
    (out / CHECKSUMS).write_text(f"{wrong}  other.ckpt\n{right}  *other.ckpt\n")
    with script_folder("tools/release_weights"):
        assert load_script("tools/release_weights").main([str(weights), "--out", str(out)]) == 2
    assert sorted(p.name for p in out.iterdir()) == [CHECKSUMS]


# ------------------------------------------------------------------ ground truth
@pytest.mark.parametrize("kind", ["pickle", "object-array"])
def test_a_pickled_distance_map_names_the_file_and_is_never_unpickled(kind, tmp_path):
    path = tmp_path / "0000000002.npy"
    if kind == "pickle":
        path.write_bytes(pickle.dumps(np.ones((4, 4))))
    else:
        np.save(path, np.array([None, 1.0], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError) as info:
        read_distance(path, SimpleNamespace(width=4, height=4))
    message = str(info.value)
    assert message.startswith(f"{path}: ") and "Python objects" in message and "never loaded" in message
    assert "allow_pickle" not in message and "unsafe" not in message  # no advice to load it anyway


# ------------------------------------------------------------------ the accelerator
def test_the_accelerator_is_the_machines_unless_named(tmp_path, monkeypatch):
    """train.py's default trainer (auto) runs on CUDA where torch sees a GPU, else on the CPU; a named
    accelerator or trainer wins."""
    fp32 = "trainer.precision=32-true"  # bf16 support is a question for the GPU that is not here
    assert train_plan(train_cfg(tmp_path, fp32)).accelerator == "cpu"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert choose_accelerator("auto") == "cuda"
    assert train_plan(train_cfg(tmp_path, fp32)).accelerator == "cuda"
    assert train_plan(train_cfg(tmp_path, fp32, "trainer.accelerator=cpu")).accelerator == "cpu"
    assert train_plan(train_cfg(tmp_path, fp32, "trainer=cpu")).accelerator == "cpu"
    assert train_plan(train_cfg(tmp_path, fp32, "trainer=gpu")).accelerator == "gpu"
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda index=0: "NVIDIA H200")
    assert describe_accelerator("cuda") == "cuda (NVIDIA H200)"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert choose_accelerator("auto") == "cpu" and describe_accelerator("cpu") == "cpu"
    assert list(tmp_path.iterdir()) == []
