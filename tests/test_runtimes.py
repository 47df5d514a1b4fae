"""Deployment runtimes: ONNX (float32 and int8) and bf16 against PyTorch float32, their files' metadata,
eval.py and predict.py on an exported file, and live cameras (written as they come, Ctrl-C kept)."""

from __future__ import annotations

import dataclasses
import json
import platform
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from fisheyedepth.cameras import load_camera
from fisheyedepth.checkpoints import CheckpointError
from fisheyedepth.cli.evaluate import eval_checkpoint
from fisheyedepth.cli.export import export
from fisheyedepth.cli.predict import predict
from fisheyedepth.images import FrameSource, ImageError, is_live
from fisheyedepth.module import FisheyeDepthModule
from fisheyedepth.options.defaults import keywords
from fisheyedepth.runtimes import OnnxRuntime, TorchRuntime, TrainedDepthNet, flip_averaged

from conftest import (
    TRAIN_SEQ,
    bare_module,
    kitti02,
    kitti03,
    load_cfg,
    load_script,
    printed,
    tiny_batch,
    train_few_steps,
)

ROOT = Path(__file__).resolve().parents[1]


def export_file(checkpoint, tmp_path, name="m.onnx", **values):
    cfg = load_cfg(
        "export",
        ckpt_path=checkpoint,
        size=[64, 64],
        output=tmp_path / name,
        paths={"output_dir": str(tmp_path)},
    )
    return export(OmegaConf.merge(cfg, values))


def images_of(kitti_data, camera="image_02", n=3):
    files = sorted((kitti_data / "data_2d_raw" / TRAIN_SEQ / camera / "data_rgb").glob("*.png"))[:n]
    rgb = np.stack([cv2.imread(str(p))[..., ::-1] for p in files])
    return torch.from_numpy(rgb.copy()).permute(0, 3, 1, 2).float() / 255.0


def float_and_int8(checkpoint, kitti_data, tmp: Path) -> tuple[Path, Path]:
    """``checkpoint`` exported as float32 and as int8 (calibrated on 8 KITTI-360 frames) into ``tmp``."""
    fp32 = export_file(checkpoint, tmp, "fp32.onnx")
    calibration = str(kitti_data / "data_2d_raw")
    int8 = export_file(checkpoint, tmp, "int8.onnx", quantize="int8", calibration=calibration,
                       calibration_frames=8)  # fmt: skip
    return fp32, int8


@pytest.fixture(scope="module")
def onnx_files(checkpoint, kitti_data, tmp_path_factory):
    pytest.importorskip("onnxruntime")
    return float_and_int8(checkpoint, kitti_data, tmp_path_factory.mktemp("onnx"))


@pytest.fixture(scope="module")
def effnet_checkpoint(kitti_data, tmp_path_factory):
    """The ``checkpoint`` fixture's recipe on the default encoder (``model=fisheyedepth_effnet``: the
    ImageNet EfficientNet-Lite0), saved like Lightning saves it."""
    path = tmp_path_factory.mktemp("effnet") / "effnet.ckpt"
    train_few_steps(kitti_data, path, encoder="efficientnet_lite0")
    return path


@pytest.fixture(scope="module", params=["resnet", "efficientnet_lite0"])
def int8_files(request, onnx_files, kitti_data, tmp_path_factory):
    """float32 and int8 files of each encoder: the ResNet-18's (``onnx_files``) and the default
    EfficientNet-Lite0's, whose first layers int8 is most sensitive in."""
    if request.param == "resnet":
        return onnx_files
    checkpoint = request.getfixturevalue("effnet_checkpoint")
    return float_and_int8(checkpoint, kitti_data, tmp_path_factory.mktemp("onnx_effnet"))


def test_onnx_file_serves_every_camera_of_the_rig_as_pytorch_does(onnx_files, checkpoint, kitti_data):
    """The file freezes one depth_scale; the runtime gives each camera its own from the base focal the
    file carries: both cameras at their native 256 px, and one with 1.5x the focal length, match
    PyTorch float32 to 1e-4."""
    record, _ = onnx_files
    assert record["parity"] == {"statistic": "max", "tolerance": 1e-4}
    assert record["max_relative_difference"] < 1e-4
    onnx = OnnxRuntime(record["path"], threads=1)
    assert onnx.input_size == (64, 64) and onnx.base_focal == 20.0 and onnx.quantize == "none"
    torch_rt = TorchRuntime(FisheyeDepthModule.from_checkpoint(checkpoint))
    outputs = {}
    for name in ("image_02", "image_03", "longer"):
        camera = load_camera(kitti_data / "calibration" / f"{'image_02' if name == 'longer' else name}.yaml")
        if name == "longer":
            camera = dataclasses.replace(camera, gamma1=camera.gamma1 * 1.5, gamma2=camera.gamma2 * 1.5)
        images = images_of(kitti_data, "image_02", 2)
        ref = torch_rt.distance(images, [camera] * 2)
        outputs[name] = got = onnx.distance(images, [camera] * 2)
        assert got.shape == ref.shape == (2, 1, 256, 256)
        assert float(((got - ref).abs() / ref).max()) < 1e-4
    assert torch.allclose(outputs["longer"], 1.5 * outputs["image_02"], rtol=1e-4)


def test_int8_file_is_close_to_float32_and_scores_within_0_01(int8_files, kitti_data, tmp_path):
    """int8 (encoder, decoder, attention) against the float32 file on the test split: the export's median
    relative difference under its written tolerance (3 %), and abs_rel within 0.01 of float32; for
    both encoders."""
    fp32, int8 = int8_files
    assert int8["quantize"] == "int8" and int8["parity"] == {"statistic": "median", "tolerance": 0.03}
    assert int8["calibration"] == {"folder": str(kitti_data / "data_2d_raw"), "frames": 8}
    assert 0 < int8["median_relative_difference"] < 0.03
    assert OnnxRuntime(int8["path"]).quantize == "int8"
    scores = {}
    for name, record in (("fp32", fp32), ("int8", int8)):
        cfg = load_cfg(
            "eval",
            runtime="onnx",
            model_file=record["path"],
            paths={"output_dir": str(tmp_path / name)},
            data={"generate": None, "datamodule": _datamodule(kitti_data)},
        )
        cfg.eval.pictures = 1
        result = eval_checkpoint(cfg)
        assert result["model"]["runtime"] == "onnx" and result["model"]["quantize"] == (
            "int8" if name == "int8" else "none"
        )
        scores[name] = result["results"]["full"]["none"]["abs_rel"]
    assert all(0 < s < 2 for s in scores.values())
    assert abs(scores["int8"] - scores["fp32"]) < 0.01, scores


def test_int8_keeps_the_encoders_first_feature_map_and_the_bin_expectation_float32(int8_files, request):
    """What the int8 file runs in float32: the encoder up to the first feature map the decoder reads
    (EfficientNet-Lite0: its stem and first block, which alone moved the released weights' median by
    1.9 % and 3.6 % in int8; ResNet-18: its 7x7 convolution) and the bin expectation after the logits;
    everything else, the logits' convolution included, in ONNX Runtime's int8 operators."""
    import onnx

    _, int8 = int8_files
    graph = onnx.load(int8["path"]).graph
    float_convs = sorted(node.name for node in graph.node if node.op_type == "Conv")
    first = {
        "resnet": ["/depth_net/encoder/conv1/Conv"],
        "efficientnet_lite0": ["/depth_net/encoder/_blocks.0/_depthwise_conv/Conv",
                               "/depth_net/encoder/_blocks.0/_project_conv/Conv",
                               "/depth_net/encoder/_conv_stem/Conv"],
    }[request.node.callspec.params["int8_files"]]  # fmt: skip
    assert float_convs == sorted([*first, "/depth_net/Conv"])  # /depth_net/Conv: the bins' sums
    ops = {node.name: node.op_type for node in graph.node}
    assert (
        ops["/depth_net/heads.0/logits/logits.1/Conv_quant"] == "QLinearConv"
        and ops["/depth_net/Exp"] == "Exp"
    )
    assert sum(op == "QLinearConv" for op in ops.values()) > 20


def _datamodule(kitti_data):
    data = ROOT / "conf" / "data"  # synthetic.yaml on top of the base its defaults list names
    base = OmegaConf.merge(*(OmegaConf.load(data / f).datamodule for f in ("_common.yaml", "synthetic.yaml")))
    values = {
        "root": str(kitti_data),
        "size": [64, 64],
        "num_workers": 0,
        "cache_dir": str(kitti_data / "cache"),
    }
    return OmegaConf.merge(base, values)


def test_eval_of_the_checkpoint_agrees_with_eval_of_its_float32_file(
    onnx_files, checkpoint, kitti_data, tmp_path
):
    fp32, _ = onnx_files
    data = {"generate": None, "datamodule": _datamodule(kitti_data)}
    by_file = eval_checkpoint(
        load_cfg(
            "eval",
            runtime="onnx",
            model_file=fp32["path"],
            paths={"output_dir": str(tmp_path / "f")},
            data=data,
        )
    )
    by_ckpt = eval_checkpoint(
        load_cfg("eval", ckpt_path=checkpoint, paths={"output_dir": str(tmp_path / "c")}, data=data)
    )
    a, b = by_file["results"]["full"]["none"], by_ckpt["results"]["full"]["none"]
    assert a["abs_rel"] == pytest.approx(b["abs_rel"], rel=1e-4) and a["a1"] == pytest.approx(
        b["a1"], abs=1e-3
    )
    assert by_ckpt["model"]["runtime"] == "torch" and by_ckpt["model"]["precision"] == "fp32"
    assert by_file["checkpoint"] is None and by_file["model"]["file"] == fp32["path"]


def test_bf16_runtime_stays_close_to_float32(checkpoint, kitti_data):
    module = FisheyeDepthModule.from_checkpoint(checkpoint)
    camera = load_camera(kitti_data / "calibration" / "image_02.yaml")
    images = images_of(kitti_data)
    ref = TorchRuntime(module).distance(images, [camera] * 3)
    got = TorchRuntime(FisheyeDepthModule.from_checkpoint(checkpoint), precision="bf16").distance(
        images, [camera] * 3
    )
    assert got.dtype == torch.float32  # the expectation and the upsampling stay float32
    rel = ((got - ref).abs() / ref).flatten()
    assert 0 < float(rel.median()) < 0.02 and float(rel.max()) < 0.2
    with pytest.raises(ValueError, match="precision: 'fp16'"):
        TorchRuntime(module, precision="fp16")


def test_flip_averaging_mirrors_the_second_prediction_back_and_means_inverse_distances():
    """A network whose distance grows along the image's columns: the mirror image's prediction, mirrored
    back, is the column ramp reversed, and the result their harmonic mean. Each mirror image gets its
    camera flipped (cu -> W - 1 - cu), in one call of twice the batch."""
    cameras = [kitti02().resize(8, 6), kitti03().resize(8, 6)]
    images = torch.rand(2, 3, 6, 8, generator=torch.Generator().manual_seed(0))
    calls = []

    def ramp(batch, batch_cameras):
        calls.append((batch.clone(), list(batch_cameras)))
        columns = torch.arange(8, dtype=batch.dtype).expand(batch.shape[0], 1, 6, 8)
        return 2.0 + columns

    got = flip_averaged(ramp, images, cameras)
    forward, reverse = 2.0 + torch.arange(8.0), 2.0 + torch.arange(7.0, -1.0, -1.0)
    expected = (2.0 / (1.0 / forward + 1.0 / reverse)).expand(2, 1, 6, 8)
    torch.testing.assert_close(got, expected)
    assert float(got[0, 0, 0, 0]) == pytest.approx(2 / (1 / 2 + 1 / 9))  # not symmetric: 3.6, not 5.5
    ((batch, batch_cameras),) = calls
    torch.testing.assert_close(batch, torch.cat((images, images.flip(-1))))
    assert batch_cameras == [*cameras, *(c.flip() for c in cameras)]
    assert batch_cameras[2].u0 == pytest.approx(7 - cameras[0].u0) != cameras[0].u0

    def by_content(batch, batch_cameras):  # a prediction that follows the image content
        return 1.0 + batch.mean(1, keepdim=True)

    torch.testing.assert_close(flip_averaged(by_content, images, cameras), by_content(images, cameras))


def test_flip_post_processing_in_both_runtimes_and_eval(onnx_files, checkpoint, kitti_data, tmp_path):
    """post_process=flip: the torch runtime's distance is the harmonic mean of its distance of the
    images and, mirrored back, of their mirror images; the ONNX file's agrees with it; eval.py records
    it in results.json and scores another number than without it; a bad value names the field."""
    module = FisheyeDepthModule.from_checkpoint(checkpoint)
    camera = load_camera(kitti_data / "calibration" / "image_03.yaml")
    images = images_of(kitti_data, "image_03")
    plain = TorchRuntime(module).distance(images, [camera] * 3)
    mirrored = TorchRuntime(module).distance(images.flip(-1), [camera.flip()] * 3).flip(-1)
    got = TorchRuntime(module, post_process="flip").distance(images, [camera] * 3)
    torch.testing.assert_close(got, 2.0 / (1.0 / plain + 1.0 / mirrored), rtol=1e-5, atol=1e-6)
    assert float(((got - plain).abs() / plain).median()) > 1e-4  # the mirror image changes the answer
    by_file = OnnxRuntime(onnx_files[0]["path"], post_process="flip").distance(images, [camera] * 3)
    torch.testing.assert_close(by_file, got, rtol=1e-3, atol=1e-3)
    data = {"generate": None, "datamodule": _datamodule(kitti_data)}
    records = [
        eval_checkpoint(
            load_cfg(
                "eval",
                ckpt_path=checkpoint,
                post_process=pp,
                paths={"output_dir": str(tmp_path / pp)},
                data=data,
            )
        )
        for pp in ("none", "flip")
    ]
    assert [r["model"]["post_process"] for r in records] == ["none", "flip"]
    a, b = (r["results"]["full"]["none"]["abs_rel"] for r in records)
    assert a != b and abs(a - b) < 0.5 * a
    with pytest.raises(ValueError, match="post_process: 'mean' is not one of none, flip"):
        TorchRuntime(module, post_process="mean")
    with pytest.raises(ValueError, match="post_process: 'mean'"):
        OnnxRuntime(onnx_files[0]["path"], post_process="mean")


@pytest.mark.parametrize("real_scale", [True, False])
def test_the_network_read_without_its_training_parts_predicts_what_the_module_predicts(
    checkpoint, kitti_data, tmp_path, real_scale
):
    """``TrainedDepthNet`` (what predict.py, eval.py and export.py load) holds the checkpoint's distance
    network and options alone: the same distances as the whole module, also for a PoseNet row (whose
    PoseNet weights it leaves); hyper-parameters or weights that do not fit are named as the module
    names them."""
    path = checkpoint
    if not real_scale:
        torch.manual_seed(1)
        module = bare_module(net={"scales": (0,)}, objective={"real_scale": False}, input_size=(64, 64))
        path = tmp_path / "posenet.ckpt"
        torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams)}, path)
    batch = tiny_batch(kitti_data)
    full, light = FisheyeDepthModule.from_checkpoint(path), TrainedDepthNet.from_checkpoint(path)
    assert not hasattr(light, "pose_net") and dict(light.hparams) == dict(full.hparams)
    assert sorted(keywords()) == sorted(full.hparams)  # what a checkpoint may hold
    assert torch.equal(
        TorchRuntime(full).distance(batch.image, batch.camera),
        TorchRuntime(light).distance(batch.image, batch.camera),
    )
    assert TorchRuntime(light).describe()["real_scale"] is real_scale
    ckpt = torch.load(path, weights_only=True)
    for group, key, value, match in (
        ("objective", "hidden", 1, "objective.hidden"),
        (None, "hidden", 1, "unexpected hidden"),
        ("net", "n_bins", 32, "weights do not fit"),
    ):
        hparams = dict(ckpt["hyper_parameters"])
        if group:
            hparams[group] = {**hparams[group], key: value}
        else:
            hparams[key] = value
        broken = {**ckpt, "hyper_parameters": hparams}
        torch.save(broken, tmp_path / "broken.ckpt")
        with pytest.raises(CheckpointError, match=match) as info:
            TrainedDepthNet.from_checkpoint(tmp_path / "broken.ckpt")
        assert str(info.value).startswith(str(tmp_path / "broken.ckpt"))
        with pytest.raises(CheckpointError):
            FisheyeDepthModule.from_checkpoint(tmp_path / "broken.ckpt")


def test_onnx_files_without_metadata_or_unreadable_are_named(tmp_path, checkpoint):
    pytest.importorskip("onnxruntime")
    bare = tmp_path / "bare.onnx"
    net = torch.nn.Conv2d(3, 1, 1)
    torch.onnx.export(net, (torch.rand(1, 3, 8, 8),), str(bare), input_names=["image"], dynamo=False)
    with pytest.raises(ValueError, match=r"bare.onnx: metadata field 'fisheyedepth.input_size' is missing"):
        OnnxRuntime(bare)
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(ValueError, match=r"junk.onnx: not a readable ONNX model"):
        OnnxRuntime(junk)
    with pytest.raises(FileNotFoundError, match="nothing.onnx"):
        OnnxRuntime(tmp_path / "nothing.onnx")


def test_export_refuses_bad_quantize_options(checkpoint, tmp_path):
    with pytest.raises(ValueError, match="calibration: quantize=int8 needs a folder"):
        export_file(checkpoint, tmp_path, quantize="int8")
    with pytest.raises(ValueError, match="quantize: 'int4'"):
        export_file(checkpoint, tmp_path, quantize="int4", calibration=str(tmp_path))
    with pytest.raises(ValueError, match="quantize: 'int8'; only quantize=int8 with format=onnx"):
        export_file(
            checkpoint, tmp_path, "m.pt", format="torchscript", quantize="int8", calibration=str(tmp_path)
        )
    pytest.importorskip("onnxruntime")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="calibration: no images"):
        export_file(checkpoint, tmp_path, quantize="int8", calibration=str(tmp_path / "empty"))
    assert not (tmp_path / "m.onnx").exists()


def test_predict_runs_an_exported_file_like_its_checkpoint(onnx_files, checkpoint, kitti_data, tmp_path):
    fp32, _ = onnx_files
    src = kitti_data / "data_2d_raw" / TRAIN_SEQ / "image_02" / "data_rgb"
    calib = kitti_data / "calibration" / "image_02.yaml"
    common = {"input": str(src), "camera": str(calib), "max_frames": 2, "paths": {"output_dir": "unused"}}
    by_file = predict(
        load_cfg("predict", runtime="onnx", model_file=fp32["path"], output=tmp_path / "f", **common)
    )
    by_ckpt = predict(load_cfg("predict", ckpt_path=checkpoint, output=tmp_path / "c", **common))
    assert by_file["frames"] == by_ckpt["frames"] == 2  # max_frames
    assert by_file["runtime"].startswith("onnx (float32)") and by_ckpt["runtime"] == "torch (fp32)"
    assert by_file["input_size"] == [64, 64] and by_file["fps"] > 0
    assert json.loads((tmp_path / "f" / "summary.json").read_text())["fps"] == by_file["fps"]
    for npy in sorted((tmp_path / "c").glob("*_distance.npy")):
        a, b = np.load(npy), np.load(tmp_path / "f" / npy.name)
        ok = np.isfinite(a)
        assert np.array_equal(ok, np.isfinite(b)) and np.allclose(a[ok], b[ok], rtol=1e-4)
    flipped = predict(
        load_cfg("predict", ckpt_path=checkpoint, output=tmp_path / "p", post_process="flip", **common)
    )
    assert by_ckpt["post_process"] == "none" and flipped["post_process"] == "flip"
    for npy in sorted((tmp_path / "c").glob("*_distance.npy")):
        a, b = np.load(npy), np.load(tmp_path / "p" / npy.name)
        ok = np.isfinite(a)
        rel = np.abs(a[ok] - b[ok]) / a[ok]
        assert np.array_equal(ok, np.isfinite(b)) and 1e-4 < np.median(rel) < 0.5
    with pytest.raises(ValueError, match="size: \\[32, 32\\], but .*fp32.onnx was exported at \\[64, 64\\]"):
        predict(
            load_cfg(
                "predict",
                runtime="onnx",
                model_file=fp32["path"],
                size=[32, 32],
                output=tmp_path / "s",
                **common,
            )
        )
    # from the command line, as a user types it: model=FILE.onnx (Hydra alone would read a model group)
    proc = subprocess.run(
        [sys.executable, str(ROOT / "predict.py"), "runtime=onnx", f"model={fp32['path']}", f"input={src}",
         f"camera={calib}", "max_frames=1", f"output={tmp_path / 'cli'}", f"hydra.run.dir={tmp_path / 'h'}"],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads((tmp_path / "cli" / "summary.json").read_text())
    assert summary["frames"] == 1 and summary["runtime"] == f"onnx (float32): {fp32['path']}"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "eval.py"), "runtime=onnx", f"model={fp32['path']}", "data.generate=null",
         f"data.datamodule.root={kitti_data}", f"paths.data_dir={tmp_path}",
         f"hydra.run.dir={tmp_path / 'e'}", "eval.pictures=0"],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads((tmp_path / "e" / "results.json").read_text())["model"]["file"] == fp32["path"]
    with pytest.raises(ValueError, match="model: runtime=onnx needs the exported file"):
        predict(load_cfg("predict", runtime="onnx", output=tmp_path / "m", **common))
    # without ckpt_path, runtime=torch runs the released weights: tests/test_released_weights.py


class FakeCamera:
    """``cv2.VideoCapture`` of a live camera: ``frames`` frames, then (optionally) Ctrl-C."""

    def __init__(self, frames, interrupt=False):
        self.frames, self.interrupt, self.read_count = frames, interrupt, 0
        self.opened_with = None

    def __call__(self, arg):
        self.opened_with = arg
        return self

    def isOpened(self):  # noqa: N802 (OpenCV's name)
        return True

    def read(self):
        if self.read_count >= len(self.frames):
            if self.interrupt:
                raise KeyboardInterrupt
            return False, None
        self.read_count += 1
        return True, self.frames[self.read_count - 1].copy()

    def release(self):
        pass


def test_a_live_camera_is_written_frame_by_frame_and_ctrl_c_keeps_them(
    checkpoint, kitti_data, tmp_path, monkeypatch
):
    assert is_live("0") and is_live("/dev/null") and not is_live(tmp_path) and not is_live("clip.avi")
    with pytest.raises(ImageError, match="/dev/null: the camera could not be opened"):
        list(FrameSource("/dev/null"))
    src = sorted((kitti_data / "data_2d_raw" / TRAIN_SEQ / "image_02" / "data_rgb").glob("*.png"))
    frames = [cv2.imread(str(p)) for p in src[:3]]
    camera = FakeCamera(frames, interrupt=True)
    monkeypatch.setattr(cv2, "VideoCapture", camera)
    written_before_next_read = []
    original_read = camera.read

    def read():  # when a frame is read, every earlier frame is already on disk (no batching)
        written_before_next_read.append(len(list((tmp_path / "live").glob("*_distance.npy"))))
        return original_read()

    camera.read = read
    calib = kitti_data / "calibration" / "image_02.yaml"
    with pytest.raises(SystemExit) as stopped:  # Ctrl-C: the status a shell gives it, the frames kept
        predict(
            load_cfg("predict", ckpt_path=checkpoint, input="0", camera=str(calib),
                     output=tmp_path / "live", paths={"output_dir": "unused"})
        )  # fmt: skip
    assert stopped.value.code == 130
    assert camera.opened_with == 0  # the index, as OpenCV takes it
    assert written_before_next_read == [0, 1, 2, 3]
    summary = json.loads((tmp_path / "live" / "summary.json").read_text())
    assert summary["frames"] == 3 and summary["interrupted"] == "SIGINT"
    # max_frames ends a live run without Ctrl-C
    monkeypatch.setattr(cv2, "VideoCapture", FakeCamera(frames))
    summary = predict(
        load_cfg("predict", ckpt_path=checkpoint, input="0", camera=str(calib), output=tmp_path / "two",
                 max_frames=2, paths={"output_dir": "unused"})
    )  # fmt: skip
    assert summary["frames"] == 2 and summary["interrupted"] is None
    with pytest.raises(ValueError, match="max_frames: 0"):
        FrameSource("0", max_frames=0)


@pytest.mark.filterwarnings("ignore")  # torch.onnx's and the tracer's, printed by the script run alone too
def test_bench_inference_measures_every_runtime_and_scores_each_path(checkpoint, kitti_data, tmp_path):
    """The benchmark behind BENCHMARKS.md "Inference", tiny: every row is measured, and the accuracy
    table scores the four paths of the checkpoint on the split (float32 ONNX equal to PyTorch)."""
    pytest.importorskip("onnxruntime")
    threads = torch.get_num_threads()
    try:  # in-process: the benchmark sets torch's threads
        stdout = printed(
            "bench/bench_inference",
            ["--size", "64", "--rounds", "1", "--threads", "1", "--ckpt", str(checkpoint), "--data",
             str(kitti_data), "--calibration", str(kitti_data / "data_2d_raw"), "--no-write"],
        )  # fmt: skip
    finally:
        torch.set_num_threads(threads)
    rows = {line.split(" | ")[0].strip("| "): line for line in stdout.splitlines() if line.startswith("| ")}
    pairs = {
        "full (ResNet-18)": ("ONNX Runtime float32, fused graph",
                             "ONNX Runtime int8 (bin expectation float32)"),
        "effnet (`make train`)": ("effnet (`make train`): ONNX Runtime float32",
                                  "effnet (`make train`): ONNX Runtime int8"),
        "mobile (released weights)": ("mobile (released weights): ONNX Runtime float32",
                                      "mobile (released weights): ONNX Runtime int8"),
    }  # fmt: skip
    for name in (
        "PyTorch eager, before (NCHW, softmax expectation)",
        "PyTorch eager, + bf16 autocast",
        "lite: ONNX Runtime int8",
        *(row for pair in pairs.values() for row in pair),
    ):
        fps = float(rows[name].split(" | ")[3])
        assert fps > 0, rows[name]
    ms = {
        name: float(row.split(" | ")[2]) for name, row in rows.items() if name in {*sum(pairs.values(), ())}
    }
    for model, (fp32, int8) in pairs.items():  # each int8 file against its own float32 file
        _, checkpoint_, median, parity, gain, goal = rows[model].strip("| ").split(" | ")
        assert checkpoint_ == {"full (ResNet-18)": str(checkpoint), "effnet (`make train`)": "untrained",
                               "mobile (released weights)": "`weights/`"}[model]  # fmt: skip
        assert 0 < float(median.rstrip(" %")) < 100 and parity in ("passes", "FAILS")
        assert float(gain.rstrip("x")) == pytest.approx(ms[fp32] / ms[int8], rel=0.2)  # ms: 1 decimal
        assert goal == ("met" if float(gain.rstrip("x")) >= 2 else "NOT met")
    ratio = re.search(r"int8 export against the full model's, side by side: \*\*([\d.]+)x\*\*", stdout)
    full, mobile = pairs["full (ResNet-18)"][1], pairs["mobile (released weights)"][1]
    assert ratio and float(ratio[1]) == pytest.approx(ms[full] / ms[mobile], rel=0.1)
    scored = [line.split(" | ") for line in stdout.splitlines() if line.startswith("| full | ")]
    assert [r[1] for r in scored] == [
        "PyTorch float32",
        "PyTorch bf16",
        "ONNX Runtime float32",
        "ONNX Runtime int8",
    ]
    abs_rel = {r[1]: float(r[2]) for r in scored}
    assert 0 < abs_rel["PyTorch float32"] < 2
    assert abs_rel["ONNX Runtime float32"] == pytest.approx(abs_rel["PyTorch float32"], abs=2e-4)


def test_eval_runs_the_network_at_the_checkpoints_size_whatever_the_data_config_says(
    checkpoint, kitti_data, tmp_path
):
    """The checkpoint was trained at 64x64 with base focal 20; a data config at 32x32 changes nothing."""
    data = {"generate": None, "datamodule": OmegaConf.merge(_datamodule(kitti_data), {"size": [32, 32]})}
    out = {}
    for name, size in (("cfg32", [32, 32]), ("cfg64", [64, 64])):
        data["datamodule"]["size"] = size
        cfg = load_cfg("eval", ckpt_path=checkpoint, paths={"output_dir": str(tmp_path / name)}, data=data)
        cfg.eval.pictures = 0
        out[name] = eval_checkpoint(cfg)
    assert out["cfg32"]["train_size"] == out["cfg64"]["train_size"] == [64, 64]
    a, b = out["cfg32"]["results"]["full"]["none"], out["cfg64"]["results"]["full"]["none"]
    assert a["abs_rel"] == b["abs_rel"] and a["rmse"] == b["rmse"]


@pytest.mark.parametrize("signum, status, name", [(2, 130, "SIGINT"), (15, 143, "SIGTERM")])
def test_a_numbered_folder_is_a_folder_and_a_signal_while_writing_keeps_the_summary(
    checkpoint, kitti_data, tmp_path, monkeypatch, capsys, signum, status, name
):
    """A sequence folder named ``0001`` is read as images, not as camera 1; Ctrl-C or SIGTERM while a
    batch is being written keeps the frames written so far, writes none twice, still writes
    summary.json, and ends the command with one line and the signal's status."""
    import signal

    from fisheyedepth.cli import run_command
    from fisheyedepth.inference import PredictionWriter

    folder = tmp_path / "0001"
    folder.mkdir()
    for p in sorted((kitti_data / "data_2d_raw" / TRAIN_SEQ / "image_02" / "data_rgb").glob("*.png"))[:4]:
        (folder / p.name).write_bytes(p.read_bytes())
    source = FrameSource(folder)
    assert not source.live and len(source) == 4 and is_live("0001") is True  # no such path: an index
    original, calls = PredictionWriter.write, []

    def write(self, name, *args):
        calls.append(name)
        if len(calls) == 2:
            signal.raise_signal(signum)
        return original(self, name, *args)

    monkeypatch.setattr(PredictionWriter, "write", write)
    calib = kitti_data / "calibration" / "image_02.yaml"
    cfg = load_cfg("predict", ckpt_path=checkpoint, input=str(folder), camera=str(calib), batch_size=4,
                   output=tmp_path / "out", paths={"output_dir": "unused"})  # fmt: skip
    with pytest.raises(SystemExit) as stopped:
        run_command(predict, cfg)  # as predict.py runs it
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert stopped.value.code == status and summary["interrupted"] == name
    assert summary["frames"] == 1 and len(calls) == 2
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(
        [f"{calls[0]}_colour.png", f"{calls[0]}_distance.npy", f"{calls[0]}_distance.png", "summary.json"]
    )  # the first frame whole, nothing of the second, no temporary
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (
        f"error: {'interrupted' if signum == 2 else 'terminated'} ({name}) after 1 frames; "
        f"their outputs and summary.json are in {tmp_path / 'out'}"
    )
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # the handler put back


def test_bench_gpu_step_times_its_variants_side_by_side():
    """scripts/bench/bench_gpu_step.py (BENCHMARKS.md, "Time to accuracy"), tiny and on the CPU: every
    variant asked for gets a row with a positive step time; the first is the reference of the ratios."""
    stdout = printed(
        "bench/bench_gpu_step",
        ["--device", "cpu", "--size", "64", "--batch", "1", "--steps", "1", "--rounds", "2", "--warmup", "1",
         "--variants", "float32", "bf16 autocast (gpu_10min)"],
    )  # fmt: skip
    rows = [line.strip("|").split(" | ") for line in stdout.splitlines() if line.startswith("| ")]
    assert [r[0].strip() for r in rows[1:]] == ["float32", "bf16 autocast (gpu_10min)"]
    for name, warmup, ms, _ in rows[1:]:
        assert float(warmup) > 0 and float(ms) > 0, name
    assert rows[1][3].strip() == "1.00x"


def test_bench_synthetic_splits_a_camera_frame_into_its_stages():
    """scripts/bench/bench_synthetic.py's breakdown, tiny: every stage takes time, the value noise is part
    of the shading, and the textures it timed are the shading module's own again afterwards."""
    from fisheyedepth.synthetic import noise, shading

    split = load_script("bench/bench_synthetic").stages(1, 32, 1)
    assert list(split) == ["fine cast", "shading", "of which value noise", "centre cast"]
    assert all(ms > 0 for ms in split.values()), split
    assert split["of which value noise"] < split["shading"]
    assert (shading.fbm2, shading.fbm3, shading.hash01) == (noise.fbm2, noise.fbm3, noise.hash01)


@pytest.mark.parametrize(
    ("flags", "expected"),
    [
        ("fpu avx2 avx512f avx512_bf16 amx_bf16", "EPYC-like, AVX-512 BF16, AMX"),
        ("fpu avx2 avx512f", "EPYC-like, AVX-512"),
        ("fpu sse4_2 avx2 fma", "EPYC-like, AVX2"),
        ("fpu sse4_2", "EPYC-like, no AVX2"),
    ],
)
def test_benchmarks_name_the_cpu_by_its_widest_vector_unit(tmp_path, flags, expected):
    """A benchmark's machine line says what sets a step's speed: the model and its vector unit."""
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text(f"processor\t: 0\nmodel name\t: EPYC-like\nflags\t\t: {flags}\n\nprocessor\t: 1\n")
    assert load_script("bench/_benchmarks").cpu_name(cpuinfo) == expected
    assert load_script("bench/_benchmarks").cpu_name(tmp_path / "absent") == platform.machine()
