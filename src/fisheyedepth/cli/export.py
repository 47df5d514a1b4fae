"""``python export.py ckpt_path=... format=onnx|torchscript [size=[W,H]] [camera=CALIB]
[quantize=int8 calibration=DIR]``: the network at one input size, traced, checked against PyTorch, written
atomically with a ``.json`` record. An ONNX file carries its input size, depth scale and base focal in its
metadata, so ``predict.py runtime=onnx model=FILE`` and ``eval.py runtime=onnx model=FILE`` need no
checkpoint."""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig
from rich.console import Console

from ..cameras import PinholeCamera, load_camera
from ..inference import DistancePredictor
from ..outputs import output_lock, place, refuse_existing, writable
from ..plan import ExportPlan, export_plan, export_size
from ..runtimes import TrainedDepthNet, calibration_split, onnx_export, onnx_session

# Parity of an exported file with the PyTorch network it was made from, on probe images: the largest
# relative difference in distance allowed (float32 paths), or the median (int8, an approximation by
# design; its accuracy on a test split is in BENCHMARKS.md "Inference"). A file outside is not written.
PARITY = {"torchscript": ("max", 1e-4), "onnx": ("max", 1e-4), "onnx-int8": ("median", 0.03)}


def export(cfg: DictConfig) -> dict[str, Any]:
    plan = export_plan(cfg)  # format, quantisation, size and checkpoint checked: nothing read yet
    module = TrainedDepthNet.from_checkpoint(plan.checkpoint)
    if module.depth_net.cost_volume is not None:
        raise ValueError(
            f"{plan.checkpoint}: net.cost_volume: the multi-view network reads source frames and poses, "
            "which an exported file does not take yet; export a monocular checkpoint, or run this one in "
            "PyTorch"
        )
    size = plan.size or export_size(
        tuple(module.hparams.get("input_size") or ()), f"{plan.checkpoint}: input_size"
    )
    path = plan.path(size)
    refuse_existing(path, plan.overwrite)  # at once, not after waiting for another export of the file
    with output_lock(path):  # one export.py at a time writes this file
        refuse_existing(path, plan.overwrite)
        data, record = exported(plan, module, size, path)
        record["sha256"] = hashlib.sha256(data).hexdigest()
        with writable(path):
            place(path, data, json.dumps(record, indent=2) + "\n", plan.overwrite)
    Console(width=130).print(record)
    return record


def exported(plan: ExportPlan, module, size, path: Path):
    """The network of ``module`` at ``size`` serialised in ``plan.format`` and its record, checked against
    PyTorch on probe images (:data:`PARITY`): a file outside its tolerance is a ValueError."""
    if plan.camera:
        camera = load_camera(plan.camera)
    else:  # no camera: depth_scale 1, i.e. a camera with the base focal (the training cameras' mean)
        focal = module.depth_net.base_focal or 1.0
        camera = PinholeCamera(width=size[0], height=size[1], fx=focal, fy=focal, cx=0.0, cy=0.0)
    net = DistancePredictor(module, camera, size).exportable()
    example = torch.rand(1, 3, size[1], size[0], generator=torch.Generator().manual_seed(0))
    probe = torch.rand(2, 3, size[1], size[0], generator=torch.Generator().manual_seed(1))
    buffer = io.BytesIO()  # serialised in memory, verified, then written atomically
    if plan.format == "torchscript":
        torch.jit.save(torch.jit.trace(net, example), buffer)  # ScriptModule.save takes file names only
        exported = torch.jit.load(io.BytesIO(buffer.getvalue()))
        run = lambda x: exported(x)  # noqa: E731
        data = buffer.getvalue()
    else:
        calibration = None
        if plan.quantize:  # the parity probes are real images too, but not ones the ranges were measured on
            calibration, held = calibration_split(plan.calibration, size, plan.calibration_frames)
            probe = torch.from_numpy(held)
        data = onnx_export(net, size, module.depth_net.base_focal, plan.quantize, calibration)
        try:
            session = onnx_session(data)
        except ImportError:
            run = None
        else:
            run = lambda x: torch.from_numpy(session.run(None, {"image": x.numpy()})[0])  # noqa: E731
    record: dict[str, Any] = {
        "format": plan.format,
        "quantize": plan.quantize,
        "path": str(path),
        "size": list(size),
        "depth_scale": net.depth_scale,
        "base_focal": module.depth_net.base_focal,
        "checkpoint": plan.checkpoint,
    }
    if plan.quantize:
        record["calibration"] = {"folder": plan.calibration, "frames": len(calibration)}
    if run is not None:
        with torch.no_grad():
            ref, got = net(probe), run(probe)
        rel = ((got - ref).abs() / ref.abs().clamp_min(1e-6)).flatten()
        record["max_relative_difference"] = float(rel.max())
        record["median_relative_difference"] = float(rel.median())
        kind = "onnx-int8" if plan.quantize else plan.format
        statistic, tolerance = PARITY[kind]
        record["parity"] = {"statistic": statistic, "tolerance": tolerance}
        if record[f"{statistic}_relative_difference"] > tolerance:
            raise ValueError(
                f"{path}: not written, the exported network differs from PyTorch by "
                f"{record[f'{statistic}_relative_difference']:.2e} ({statistic} relative), over {tolerance}"
            )
    return data, record
