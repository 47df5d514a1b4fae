"""``python export.py ckpt_path=... format=onnx|torchscript [size=[W,H]] [camera=CALIB]``: the network at
one input size, traced, checked against PyTorch, written atomically with a ``.json`` record."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig
from rich.console import Console

from ..cameras import PinholeCamera, load_camera
from ..inference import DistancePredictor
from ..module import FisheyeDepthModule
from ..utils import atomic_write_bytes, atomic_write_text

EXPORT_FORMATS = {"onnx": ".onnx", "torchscript": ".pt"}


def export(cfg: DictConfig) -> dict[str, Any]:
    if cfg.format not in EXPORT_FORMATS:
        raise ValueError(f"format: {cfg.format!r} is not one of {', '.join(EXPORT_FORMATS)}")
    module = FisheyeDepthModule.from_checkpoint(cfg.ckpt_path)
    size = tuple(cfg.size) if cfg.get("size") else tuple(module.hparams.get("input_size") or ())
    if len(size) != 2:
        raise ValueError(
            "export needs a fixed input size: size=[W,H] (or a checkpoint that stores input_size)"
        )
    if cfg.get("camera"):
        camera = load_camera(cfg.camera)
    else:  # no camera: depth_scale 1, i.e. a camera with the base focal (the training cameras' mean)
        focal = module.depth_net.base_focal or 1.0
        camera = PinholeCamera(width=size[0], height=size[1], fx=focal, fy=focal, cx=0.0, cy=0.0)
    net = DistancePredictor(module, camera, size).exportable()
    suffix = EXPORT_FORMATS[cfg.format]
    path = (
        Path(cfg.output)
        if cfg.get("output")
        else Path(cfg.paths.output_dir) / f"fisheyedepth_{size[0]}x{size[1]}{suffix}"
    )
    if path.exists() and not cfg.overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=true to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    example = torch.rand(1, 3, size[1], size[0], generator=torch.Generator().manual_seed(0))
    buffer = io.BytesIO()  # serialised in memory, verified, then written atomically
    if cfg.format == "torchscript":
        torch.jit.save(torch.jit.trace(net, example), buffer)  # ScriptModule.save takes file names only
        exported = torch.jit.load(io.BytesIO(buffer.getvalue()))
        run = lambda x: exported(x)  # noqa: E731
    else:
        torch.onnx.export(
            net,
            (example,),
            buffer,
            input_names=["image"],
            output_names=["distance"],
            dynamic_axes={"image": {0: "batch"}, "distance": {0: "batch"}},
            opset_version=17,
            dynamo=False,
        )
        try:
            import onnxruntime as ort
        except ImportError:
            run = None
        else:
            session = ort.InferenceSession(buffer.getvalue(), providers=["CPUExecutionProvider"])
            run = lambda x: torch.from_numpy(session.run(None, {"image": x.numpy()})[0])  # noqa: E731
    atomic_write_bytes(path, buffer.getvalue())
    record: dict[str, Any] = {
        "format": cfg.format,
        "path": str(path),
        "size": list(size),
        "depth_scale": net.depth_scale,
        "checkpoint": str(cfg.ckpt_path),
    }
    if run is not None:
        probe = torch.rand(2, 3, size[1], size[0], generator=torch.Generator().manual_seed(1))
        with torch.no_grad():
            ref, got = net(probe), run(probe)
        record["max_relative_difference"] = float(((got - ref).abs() / ref.abs().clamp_min(1e-6)).max())
    atomic_write_text(path.with_suffix(path.suffix + ".json"), json.dumps(record, indent=2) + "\n")
    Console(width=130).print(record)
    return record
