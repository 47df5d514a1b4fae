"""Scoring faults that used to pass silently: ground truth out of every range (a perfect score of zero
images), maps of the wrong shape stretched to fit, and distance files that are not float maps in metres."""

from __future__ import annotations

import json
import logging
import pickle
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from fisheyedepth.cameras import RayCache
from fisheyedepth.cli.evaluate import eval_checkpoint
from fisheyedepth.data import FisheyeDataset, RigLayout, collate
from fisheyedepth.evaluation import PROTOCOLS, Evaluator
from fisheyedepth.metrics import DepthMetrics

from conftest import bare_module, kitti02
from test_faults_data import write_tiny_rig
from test_faults_entrypoints import one_line_error

ROOT = Path(__file__).resolve().parents[1]
T0 = 1_700_000_000_000_000_000
STAMPS = [T0 + k * 10**8 for k in (1, 2, 3)]  # three images of one camera, 64 x 64


@pytest.fixture
def rig(tmp_path) -> Path:
    """A one-camera rig recording whose three images each have a 5 m ground-truth distance map."""
    root = tmp_path / "rig"
    write_tiny_rig(root, [T0, T0 + 10**9], [0.0, 1.0], STAMPS)
    (root / "drive" / "distance" / "cam").mkdir(parents=True)
    for t in STAMPS:
        np.save(gt_path(root, t), np.full((64, 64), 5.0, np.float32))
    return root


def gt_path(root: Path, t: int) -> Path:
    return root / "drive" / "distance" / "cam" / f"{t}.npy"


def read_all(root: Path, **kwargs) -> list[dict]:
    ds = FisheyeDataset(RigLayout(root), "all", offsets=(), cache_dir=root.parent / "cache", **kwargs)
    return [ds[i] for i in range(len(ds))]


@pytest.fixture(scope="module")
def scene():
    """A 64 x 64 KITTI-360 camera and a ground truth of 2-40 m on its rays."""
    camera = kitti02().resize(64, 64)
    _, valid = RayCache().get(camera, dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    return camera, (2.0 + 38.0 * torch.rand(64, 64, generator=gen, dtype=torch.float64)) * valid, valid


# 1. Nothing scored is an error, an unscored image is counted -------------------------------------------


@pytest.mark.parametrize(
    "scale,reason",
    [
        (1000.0, r"\(largest ground truth value 3\d{4}(\.\d+)?: millimetres\?\)"),
        (-1.0, r"\(largest ground truth value -2(\.\d+)?: no positive distance; 0 marks a pixel"),
    ],
    ids=["millimetres", "negative"],
)
def test_ground_truth_out_of_range_everywhere_is_refused(scene, scale, reason):
    camera, gt, valid = scene
    ev = Evaluator(PROTOCOLS["full"], ("none", "median"))
    for _ in range(2):
        ev.update(gt * scale, gt * scale, valid, camera)
    message = r"^data/x \(test split\): no pixel of the 2 images' ground truth lies in the full protocol's "
    message += r"range \(distance 0\.001-80 m\) " + reason
    with pytest.raises(ValueError, match=message):
        ev.compute("data/x (test split)")


def test_an_image_without_ground_truth_in_range_is_counted_and_named(scene, caplog):
    camera, gt, valid = scene
    ev = Evaluator(PROTOCOLS["full"], ("none", "median"))
    ev.update(gt * 0.5, gt, valid, camera, frame="drive/cam/1")  # abs_rel 0.5, ratio 2
    ev.update(gt * 1000, gt * 1000, valid, camera, frame="drive/cam/2")  # millimetres: nothing in range
    with caplog.at_level(logging.WARNING):
        out = ev.compute("data/x (test split)")
    assert out["unscored_images"] == 1
    assert out["none"]["images"] == out["median"]["images"] == 1
    assert out["none"]["abs_rel"] == pytest.approx(0.5)
    assert out["median"]["scale_ratio"] == pytest.approx(2.0)  # the unscored image adds no ratio of 1
    (record,) = [r.getMessage() for r in caplog.records if "not scored" in r.getMessage()]
    assert record.startswith("data/x (test split): 1 of 2 images have no ground truth in the full protocol")
    assert re.search(r"drive/cam/2 \(largest 3\d{4}(\.\d+)? m\)$", record), record


def test_a_group_without_pixels_reports_no_number():
    """The kitti360 protocol scores z > 0.3 m only: nothing beyond 90 degrees. That band held 0.000."""
    camera = kitti02().resize(64, 64)
    _, valid = RayCache().get(camera, dtype=torch.float64)
    gt = torch.full((64, 64), 4.0, dtype=torch.float64) * valid
    ev = Evaluator(PROTOCOLS["kitti360"], ("none",))
    ev.update(gt * 1.5, gt, valid, camera)
    bands = ev.compute()["none_by_angle"]
    assert bands["0-30"]["abs_rel"] == pytest.approx(0.5) and bands["0-30"]["images"] == 1
    assert bands["90-180"] == {k: None for k in bands["0-30"] if k != "images"} | {"images": 0}
    json.dumps(bands, allow_nan=False)  # no NaN in results.json


def test_metrics_over_zero_images_are_an_error_not_zero():
    metric = DepthMetrics()
    metric.update(torch.ones(1, 1, 4, 4), torch.zeros(1, 1, 4, 4))  # no valid pixel
    with pytest.raises(ValueError, match=r"no image had a pixel to score .*1 image\(s\) without one"):
        metric.compute()


# 2-4. Distance files: shape, dtype, format, values -------------------------------------------------------


@pytest.mark.parametrize(
    "array,what",
    [
        (
            np.full((32, 64), 5.0, np.float32),
            r"shape \(32, 64\), but its image is 64x64: expected shape \(64, 64\)",
        ),
        (np.full(64 * 64, 5.0, np.float32), r"shape \(4096,\) and dtype float32; expected an H x W float"),
        (np.full((64, 64, 3), 5.0, np.float32), r"shape \(64, 64, 3\) and dtype float32; expected an H x W"),
        (np.full((64, 64), 5000, np.uint16), r"shape \(64, 64\) and dtype uint16; expected an H x W float"),
    ],
    ids=["half-height", "flat", "HxWx3", "integer"],
)
def test_a_distance_map_of_the_wrong_shape_or_type_is_refused(rig, array, what):
    path = gt_path(rig, STAMPS[1])
    np.save(path, array)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: ground-truth distance of {what}"):
        read_all(rig)


def test_a_native_size_map_is_resized_with_the_camera(rig):
    samples = read_all(rig, size=(32, 32))
    assert [s["distance"].shape for s in samples] == [(1, 32, 32)] * 3
    assert all(float(s["distance"].max()) == 5.0 for s in samples)
    assert collate(samples).frame == [f"drive/cam/{t}" for t in STAMPS]


@pytest.mark.parametrize(
    "write,what",
    [
        (lambda p: p.write_bytes(pickle.dumps(np.ones((64, 64)))), "holds Python objects (a pickled array)"),
        (
            lambda p: p.write_text("5.0 5.0\n5.0 5.0\n"),
            "not a NumPy .npy array (no .npy header; it begins b'5.0 5.')",
        ),
        (lambda p: np.save(p, np.array([None, 1.0], dtype=object)), "holds Python objects (a pickled array)"),
        (lambda p: np.savez(p.with_suffix(""), d=np.ones((64, 64))), "not a NumPy .npy array: a NpzFile"),
        (lambda p: p.write_bytes(b""), "not a NumPy .npy array (empty)"),
    ],
    ids=["pickle", "text", "object-array", "npz", "empty"],
)
def test_a_distance_file_that_is_not_an_npy_array_is_named(rig, write, what):
    path = gt_path(rig, STAMPS[1])
    path.unlink()
    write(path)
    if not path.exists():  # np.savez adds ".npz"
        path.with_suffix(".npz").rename(path)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: {re.escape(what)}"):
        read_all(rig)


@pytest.mark.parametrize(
    "value,what",
    [
        (np.nan, "3 non-finite value(s) (NaN or inf)"),
        (np.inf, "3 non-finite value(s) (NaN or inf)"),
        (-1.0, "3 negative value(s) (smallest -1)"),
        (1e30, "3 value(s) beyond 10000 m (largest 1e+30)"),
    ],
    ids=["nan", "inf", "negative", "1e30"],
)
def test_bad_values_name_the_npy_file_and_count(rig, value, what):
    path = gt_path(rig, STAMPS[1])
    d = np.full((64, 64), 5.0, np.float32)
    d[10, 10:13] = value
    np.save(path, d)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: {re.escape(what)} in the ground-truth"):
        read_all(rig)
    (skipped,) = [s["skipped"] for s in read_all(rig, skip_bad_frames=True) if "skipped" in s]
    assert f"{path}: {what}" in skipped  # asked for: skipped, and counted by whoever collates


def test_zero_is_no_ground_truth_and_is_accepted(rig):
    np.save(gt_path(rig, STAMPS[1]), np.zeros((64, 64), np.float32))
    assert float(read_all(rig)[1]["distance"].abs().sum()) == 0.0


# End to end: eval.py on a rig with ground truth in millimetres -----------------------------------------


def eval_cfg(root: Path, ckpt: Path, out: Path):
    overrides = [
        "data=rig",
        f"data.datamodule.root={root}",
        f"paths.root_dir={out}",
        f"paths.output_dir={out}",
        f"ckpt_path={ckpt}",
        "eval.protocols=[full]",
        "eval.pictures=0",
    ]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose(config_name="eval", overrides=overrides)


def test_eval_counts_an_unscored_image_and_refuses_a_split_in_millimetres(rig, tmp_path, capsys):
    torch.manual_seed(0)
    module = bare_module(net={"scales": (0,), "base_focal": 20.0}, input_size=(64, 64))
    ckpt = tmp_path / "tiny.ckpt"
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams)}, ckpt)
    np.save(gt_path(rig, STAMPS[0]), np.full((64, 64), 5000.0, np.float32))
    record = eval_checkpoint(eval_cfg(rig, ckpt, tmp_path / "a"))
    full = record["results"]["full"]
    assert full["unscored_images"] == 1 and full["none"]["images"] == 2 and full["skipped_frames"] == 0
    assert "full: 1 image(s) with no ground truth in range, not scored" in capsys.readouterr().out
    for t in STAMPS:
        np.save(gt_path(rig, t), np.full((64, 64), 5000.0, np.float32))
    error = one_line_error(eval_checkpoint, eval_cfg(rig, ckpt, tmp_path / "b"), capsys)
    assert error == (
        f"error: {rig} (test split): no pixel of the 3 images' ground truth lies in the full protocol's "
        "range (distance 0.001-80 m) (largest ground truth value 5000: millimetres?)"
    )
    assert not (tmp_path / "b" / "results.json").exists()
