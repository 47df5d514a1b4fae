"""Inference and deployment: predict.py outputs and units, point clouds, exports with parity, refusals."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from torch.nn import functional as F

from fisheyedepth.cameras import load_camera
from fisheyedepth.cli.export import export
from fisheyedepth.cli.predict import predict
from fisheyedepth.data import collate
from fisheyedepth.inference import DistancePredictor, distance_png, point_cloud, read_ply, write_ply
from fisheyedepth.models import upsample_inverse
from fisheyedepth.module import FisheyeDepthModule

from conftest import TRAIN_SEQ, bare_module, load_cfg, printed

ROOT = Path(__file__).resolve().parents[1]


def frames_folder(kitti_data, dst, n=3, corrupt=True):
    dst.mkdir(parents=True)
    src = kitti_data / "data_2d_raw" / TRAIN_SEQ / "image_02" / "data_rgb"
    for p in sorted(src.glob("*.png"))[:n]:
        shutil.copy(p, dst / p.name)
    if corrupt:
        (dst / "broken.png").write_bytes(b"not an image")
    return dst


def run(script, *args):
    return subprocess.run(
        [sys.executable, str(ROOT / script), *args],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def test_predict_writes_every_promised_file(kitti_data, checkpoint, tmp_path):
    images = frames_folder(kitti_data, tmp_path / "in")
    calib = kitti_data / "calibration" / "image_02.yaml"
    out = tmp_path / "out"
    args = [
        f"ckpt_path={checkpoint}",
        f"input={images}",
        f"camera={calib}",
        f"output={out}",
        "z_depth=true",
        "point_cloud=true",
        "batch_size=2",
        f"hydra.run.dir={tmp_path / 'hydra'}",
    ]
    proc = run("predict.py", *args)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert (
        summary["frames"] == 3 and summary["skipped"] == 1 and summary["unreadable"][0].endswith("broken.png")
    )
    assert "broken.png" in proc.stdout + proc.stderr
    camera = load_camera(calib)
    rays, has_ray = camera.unproject(
        torch.from_numpy(np.stack(np.meshgrid(np.arange(256.0), np.arange(256.0)), -1))
    )
    has_ray = has_ray.numpy()
    assert 0.5 < has_ray.mean() < 1.0  # the synthetic kitti360 camera has corners without a ray
    for stem in sorted(p.stem for p in images.glob("0*.png")):
        d = np.load(out / f"{stem}_distance.npy")
        assert d.shape == (256, 256) and d.dtype == np.float32
        assert (d[has_ray] > 0).all() and np.isfinite(d[has_ray]).all() and np.isnan(d[~has_ray]).all()
        png = cv2.imread(str(out / f"{stem}_distance.png"), cv2.IMREAD_UNCHANGED)
        assert png.dtype == np.uint16 and (png[~has_ray] == 0).all() and (png[has_ray] > 0).all()
        assert np.abs(png[has_ray] / 1000.0 - np.clip(d[has_ray], 0, 65.535)).max() <= 0.0005 + 1e-6
        z = np.load(out / f"{stem}_z.npy")
        assert np.isnan(z[~has_ray]).all()
        assert np.allclose(z[has_ray], (d * rays[..., 2].numpy())[has_ray], atol=1e-4)
        colour = cv2.imread(str(out / f"{stem}_colour.png"))
        assert colour.shape[0] == 256 and colour.shape[1] > 256  # with its colour bar
        assert (colour[:, :256][~has_ray] == 0).all()  # no ray: black
        points, rgb = read_ply(out / f"{stem}.ply")
        assert len(points) == has_ray.sum() and np.isfinite(points).all() and rgb.dtype == np.uint8
    cfg = load_cfg(  # the same command in-process: nothing is replaced without overwrite=true
        "predict", ckpt_path=checkpoint, input=images, camera=calib, output=out, z_depth=True,
        point_cloud=True, batch_size=2,
    )  # fmt: skip
    before = (out / "summary.json").read_bytes()
    with pytest.raises(FileExistsError, match="overwrite=true"):
        predict(cfg)
    assert (out / "summary.json").read_bytes() == before
    cfg.overwrite = True
    assert predict(cfg)["frames"] == 3


def test_predict_reads_videos_and_other_sizes(kitti_data, checkpoint, tmp_path):
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (128, 128))
    src = kitti_data / "data_2d_raw" / TRAIN_SEQ / "image_02" / "data_rgb"
    for p in sorted(src.glob("*.png"))[:3]:
        writer.write(cv2.resize(cv2.imread(str(p)), (128, 128), interpolation=cv2.INTER_AREA))
    writer.release()
    out = tmp_path / "vid"
    proc = run(
        "predict.py",
        f"ckpt_path={checkpoint}",
        f"input={video}",
        f"camera={kitti_data / 'calibration' / 'image_02.yaml'}",
        f"output={out}",
        f"hydra.run.dir={tmp_path / 'hydra'}",
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert sorted(p.name for p in out.glob("*_distance.npy")) == [
        f"frame_00000{i}_distance.npy" for i in range(3)
    ]
    assert np.load(out / "frame_000000_distance.npy").shape == (128, 128)  # the camera model was resized


def test_point_cloud_lies_where_the_distance_says(kitti_data, tmp_path):
    """A stub "network" that returns the ground-truth distance: the cloud must reproduce the scene."""
    camera = load_camera(kitti_data / "calibration" / "image_02.yaml")
    gt = torch.from_numpy(np.load(kitti_data / "data_2d_distance" / TRAIN_SEQ / "image_02" / f"{3:010d}.npy"))
    points, colours = point_cloud(gt, camera)
    write_ply(tmp_path / "c.ply", points, colours)
    back, _ = read_ply(tmp_path / "c.ply")
    assert np.allclose(back, points)
    assert np.allclose(np.sort(np.linalg.norm(back, axis=1)), np.sort(gt[gt > 0].numpy()), rtol=1e-5)
    uv, ok = camera.project(torch.from_numpy(back).double())
    assert bool(ok.all())
    assert torch.allclose(uv, uv.round(), atol=1e-3)  # each point sits on its pixel's ray
    # and the ground: points 1.6-2 m below the (level) side camera, as in the synthetic rig
    below = back[:, 1] > 1.0
    assert 1.6 < np.median(back[below, 1]) < 2.0


@pytest.mark.parametrize("fmt", ["torchscript", "onnx"])
def test_export_parity_and_refusal(checkpoint, tmp_path, fmt):
    if fmt == "onnx":
        pytest.importorskip("onnxruntime")
    cfg = OmegaConf.create(
        {
            "ckpt_path": str(checkpoint),
            "format": fmt,
            "size": [64, 64],
            "camera": None,
            "output": str(tmp_path / f"model.{fmt}"),
            "overwrite": False,
            "paths": {"output_dir": str(tmp_path)},
        }
    )
    record = export(cfg)
    assert Path(record["path"]).is_file() and record["max_relative_difference"] < 1e-4
    assert record["depth_scale"] == 1.0  # no camera: one with the base focal, the training cameras' mean
    with pytest.raises(FileExistsError, match="overwrite=true"):
        export(cfg)


def test_predictor_and_png_units(checkpoint, kitti_data):
    module = FisheyeDepthModule.from_checkpoint(checkpoint)
    camera = load_camera(kitti_data / "calibration" / "image_02.yaml")
    predictor = DistancePredictor(module, camera)
    assert predictor.input_size == (64, 64)  # from the checkpoint
    out = predictor(torch.rand(2, 3, 256, 256))
    has_ray = predictor.has_ray.expand_as(out)
    assert out.shape == (2, 1, 256, 256) and (out[has_ray] > 0).all() and out[~has_ray].isnan().all()
    assert 0.5 < has_ray.float().mean() < 1.0
    with pytest.raises(ValueError, match="images are 100x100"):
        predictor(torch.rand(1, 3, 100, 100))
    d = np.array([0.0, 1.2345, 70.0, np.nan, 1e-4, -1.0], np.float32)
    assert distance_png(d, "mm").tolist() in ([0, 1234, 65535, 0, 1, 0], [0, 1235, 65535, 0, 1, 0])
    assert distance_png(d, "256").tolist() == [0, 316, 17920, 0, 1, 0]


def test_visualize_writes_panels_and_the_angle_plot(kitti_data, checkpoint, tmp_path):
    args = ["--ckpt", str(checkpoint), "--ckpt", str(checkpoint), "--data", str(kitti_data)]
    printed("tools/visualize", [*args, "--out", str(tmp_path / "viz"), "--panels", "2"])
    plot = cv2.imread(str(tmp_path / "viz" / "abs_rel_by_angle.png"))
    assert plot is not None and plot.shape[0] > 200
    assert len(list((tmp_path / "viz").glob("panel_*.png"))) == 2


def test_every_caller_gets_its_distance_from_one_path(kitti_data):
    """Training's forward, Lightning's predict, evaluation, the predictor and the export all run
    ``DepthNet.distance``/``for_cameras``: on one image of a camera whose focal differs from
    ``base_focal`` they agree to float precision, and ``depth_scale`` multiplies the distance."""
    from fisheyedepth.evaluation import evaluate

    torch.manual_seed(0)
    camera = load_camera(kitti_data / "calibration" / "image_02.yaml")  # 256x256
    focal = min(camera.resize(64, 64).paraxial_focal())
    module = bare_module(net={"base_focal": focal / 2, "scales": (0,)}, input_size=(64, 64)).eval()
    image = torch.rand(1, 3, 256, 256)
    with torch.no_grad():
        net = module.depth_net(F.interpolate(image, size=(64, 64), mode="area"), 2.0, scales=(0,))
        reference = upsample_inverse(net["distance"][0], (256, 256))
        unit = module.depth_net(F.interpolate(image, size=(64, 64), mode="area"), 1.0, scales=(0,))
        assert torch.allclose(net["distance"][0], 2.0 * unit["distance"][0], rtol=1e-5)

        small = module(F.interpolate(image, size=(64, 64), mode="area"), [camera.resize(64, 64)])
        assert torch.allclose(small["distance"][0], net["distance"][0], rtol=1e-5)
        sample = {
            "image": image[0],
            "sources": image,
            "poses": torch.eye(4).expand(1, 4, 4),
            "camera": camera,
        }
        batch = collate([{**sample, "mask": torch.ones(1, 256, 256), "distance": torch.ones(1, 256, 256)}])
        predicted = module.predict_step(batch, 0)
        assert torch.allclose(predicted, reference, rtol=1e-5)
        by_predictor = DistancePredictor(module, camera)(image)
        has_ray = DistancePredictor(module, camera).has_ray
        assert torch.allclose(by_predictor[0, 0][has_ray], reference[0, 0][has_ray], rtol=1e-5)
        exported = DistancePredictor(module, camera).exportable()
        assert torch.allclose(exported(F.interpolate(image, size=(64, 64), mode="area")), net["distance"][0])

    # evaluation: ground truth equal to the reference distance scores zero error, unscaled
    batch.distance = reference
    result = evaluate(module, [batch], (64, 64), ["full"], scalings=("none",))
    assert result["full"]["none"]["abs_rel"] < 1e-5
