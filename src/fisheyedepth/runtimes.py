"""Runtimes: what turns images of a calibrated camera into metric distance once the network is trained.

- :class:`TorchRuntime`: a trained network in PyTorch (:class:`TrainedDepthNet`, the distance network of
  a checkpoint, read without the training parts or Lightning; or a
  :class:`~fisheyedepth.module.FisheyeDepthModule`), float32 or bf16 (autocast; fast only on CPUs with
  native bf16, such as AVX-512 BF16), channels_last.
- :class:`OnnxRuntime`: a file written by ``export.py`` (float32, or int8 with ``quantize=int8``) in ONNX
  Runtime with every graph optimisation on.

Both have ``input_size`` (W, H), the size the network runs at, and ``distance(images, cameras)``:
``[B, 3, H, W]`` float RGB in [0, 1] at the cameras' size -> ``[B, 1, H, W]`` metres. Each camera gets its
own ``depth_scale`` (paraxial focal / the checkpoint's base focal) in both, so an exported file serves
every camera of a rig. BENCHMARKS.md "Inference" compares their speed and accuracy.

The export side lives here too: :func:`onnx_metadata` (what a file carries so that it runs without its
checkpoint) and :func:`quantize_int8` (static int8 of the encoder, decoder, attention and logits in ONNX
Runtime's int8 operators, calibrated on training images; the encoder's first layers and the bin
expectation stay float32).
"""

from __future__ import annotations

import io
import math
import os
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor

from .checkpoints import model_from_checkpoint
from .images import IMAGE_SUFFIXES, read_image
from .models import DepthNet, depth_scale, distance_at_size
from .models.depth_net import check_input_size
from .options.defaults import check_numbers, model_options, unknown_options
from .options.kinds import one_of
from .options.tables import POST_PROCESSING, RUNTIME_PRECISIONS

META = "fisheyedepth."  # prefix of the ONNX metadata keys this project writes
# Nodes quantized to int8 (see quantize_int8): the encoder, the decoder, the channel attention and the
# logits' 3x3 convolution with the clamp on its output. The bin expectation after it (exp, a 1x1
# convolution with the bins, a division) stays float32: rounded bin weights move the distance by about
# 100 %. The logits' convolution in int8 moved the released weights' median by 0.1 points (1.3 % to
# 1.5 % at 384x384) and is a third of the head's time.
INT8_SCOPES = (
    "/depth_net/encoder/",
    "/depth_net/decoder/",
    "/depth_net/heads.0/attention/",
    "/depth_net/heads.0/logits/",
)


def _import_ort():
    try:
        import onnxruntime as ort
    except ImportError as err:  # an optional dependency: pip install 'fisheyedepth[export]'
        raise ImportError(
            "ONNX Runtime is not installed: pip install 'fisheyedepth[export]' (onnx, onnxruntime)"
        ) from err
    return ort


def onnx_session(model: bytes | str | os.PathLike, threads: int | None = None):
    """An ONNX Runtime CPU session: every graph optimisation on (constant folding, Conv+BN and
    Conv+activation fusion, NCHWc layouts for AVX-512; also ORT's default), one inference at a time on
    ``threads`` threads (default: torch's, i.e. this process's cores) and no inter-op pool."""
    ort = _import_ort()
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.intra_op_num_threads = int(threads or torch.get_num_threads())
    opts.inter_op_num_threads = 1
    source = model if isinstance(model, bytes) else str(model)
    return ort.InferenceSession(source, opts, providers=["CPUExecutionProvider"])


def onnx_metadata(
    input_size: tuple[int, int], depth_scale: float, base_focal: float | None, quantize: str | None
):
    """The key/value strings an exported file carries: with them ``predict.py runtime=onnx`` and
    ``eval.py runtime=onnx`` need no checkpoint."""
    return {
        META + "input_size": f"{int(input_size[0])},{int(input_size[1])}",
        META + "depth_scale": repr(float(depth_scale)),
        META + "base_focal": "none" if base_focal is None else repr(float(base_focal)),
        META + "quantize": quantize or "none",
    }


def onnx_export(
    net, size: tuple[int, int], base_focal: float | None, quantize: str | None = None, calibration=None
) -> bytes:
    """An :class:`~fisheyedepth.inference.ExportableNet` at ``size`` (W, H) as ONNX bytes (opset 17, any
    batch size), int8 with ``quantize="int8"`` (``calibration``: see :func:`quantize_int8`), with the
    metadata of :func:`onnx_metadata`."""
    buffer = io.BytesIO()
    example = torch.rand(1, 3, size[1], size[0], generator=torch.Generator().manual_seed(0))
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
    data = buffer.getvalue()
    if quantize:
        data = quantize_int8(data, calibration)
    return add_metadata(data, onnx_metadata(size, net.depth_scale, base_focal, quantize))


def add_metadata(onnx_bytes: bytes, metadata: dict[str, str]) -> bytes:
    """``onnx_bytes`` with ``metadata`` in the model's ``metadata_props``, replacing the entries of the
    same keys (two entries of one key would leave ONNX Runtime to pick either)."""
    import onnx

    model = onnx.load_from_string(onnx_bytes)
    kept = [entry for entry in model.metadata_props if entry.key not in metadata]
    del model.metadata_props[:]
    model.metadata_props.extend(kept)
    for key, value in metadata.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    return model.SerializeToString()


def flip_averaged(distance, images: Tensor, cameras) -> Tensor:
    """Monodepth2's post-processing for calibrated cameras: ``distance(images, cameras)`` of the images and
    of their mirror images (each camera flipped, :meth:`~fisheyedepth.cameras.CameraModel.flip`; one
    call of twice the batch), the second mirrored back, averaged in inverse distance (Monodepth2
    averages disparities). Mirroring keeps the length of every ray, so both are estimates of the same
    distance at each pixel; the mean cancels what in the network's error is not mirror-symmetric."""
    n = images.shape[0]
    both = distance(torch.cat((images, images.flip(-1))), [*cameras, *(c.flip() for c in cameras)])
    direct, mirrored = both[:n], both[n:].flip(-1)
    return 2.0 / (1.0 / direct.clamp_min(1e-6) + 1.0 / mirrored.clamp_min(1e-6))


def post_processed(run, images: Tensor, cameras, post_process: str) -> Tensor:
    """``run(images, cameras)``, or its :func:`flip_averaged` mean with ``post_process="flip"``."""
    return flip_averaged(run, images, cameras) if post_process == "flip" else run(images, cameras)


class TrainedDepthNet(torch.nn.Module):
    """The distance network of a training checkpoint and the options it was trained with
    (``hparams``, as :class:`~fisheyedepth.module.FisheyeDepthModule` holds them), without the PoseNet,
    the objective or Lightning: what prediction, evaluation and export need (and they start without
    importing Lightning, about 3 s)."""

    def __init__(self, hparams: dict[str, Any]):
        super().__init__()
        self.hparams = hparams
        self.depth_net = DepthNet(**hparams["net"])

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike) -> TrainedDepthNet:
        """The network of a Lightning checkpoint, read with ``weights_only=True`` and checked as
        ``FisheyeDepthModule.from_checkpoint`` checks it (the PoseNet of a PoseNet row is left out: it
        is training's alone); a file that does not hold one raises
        :class:`~fisheyedepth.checkpoints.CheckpointError` naming it."""
        return model_from_checkpoint(path, cls.from_arguments, skip=("pose_net.",))

    @classmethod
    def from_arguments(cls, **arguments: Any) -> TrainedDepthNet:
        """From the module's keyword arguments; a TypeError for one it does not take, as the module's."""
        unknown = unknown_options(arguments)
        if unknown:
            raise TypeError(f"unexpected {', '.join(unknown)}")
        hparams = model_options(**arguments)
        check_numbers(hparams)
        return cls(hparams)


class TorchRuntime:
    """A trained module in PyTorch: ``precision`` fp32 or bf16 (autocast around the network; the bin
    expectation and everything after it stay float32), weights in channels_last (the same numbers,
    1.4x faster at 384x384 on the CPU of BENCHMARKS.md). The module itself is put in eval mode, moved
    to ``device`` and converted to channels_last, in place (no copy of its weights)."""

    def __init__(
        self,
        module,
        input_size: tuple[int, int] | None = None,
        precision: str = "fp32",
        device="cpu",
        post_process: str = "none",
    ):
        self.precision = one_of("precision", precision, RUNTIME_PRECISIONS)
        self.post_process = one_of("post_process", post_process, POST_PROCESSING)
        self.module = module.eval().to(device)
        self.device = torch.device(device)
        net = self.module.depth_net
        if not net.channels_last:
            net.to(memory_format=torch.channels_last)
            net.channels_last = True
        size = check_input_size(input_size, "size") if input_size else module.hparams.get("input_size")
        self.input_size = None if size is None else (int(size[0]), int(size[1]))
        # a multi-view network's sources: the frames and the rig's cameras its loss warped, (offsets,
        # rig_offsets); None for the monocular network
        objective = module.hparams.get("objective", {})
        self.sources = None
        if net.cost_volume is not None:
            self.sources = (tuple(objective["source_offsets"]), tuple(objective["rig_offsets"]))
            if self.post_process != "none":
                raise ValueError(
                    f"post_process: {self.post_process!r} is for the monocular network; the multi-view "
                    "network's sources would have to be flipped too"
                )

    def describe(self) -> dict[str, Any]:
        """What results.json records of the model: its switches, upsampling, runtime and precision."""
        net, objective = self.module.hparams["net"], self.module.hparams["objective"]
        out = {k: objective[k] for k in ("fisheye_projection", "real_scale")}
        out |= {k: net[k] for k in ("multi_channel", "attention")}
        return out | {
            "upsample": self.module.depth_net.upsample,
            "runtime": "torch",
            "precision": self.precision,
            "device": str(self.device),
            "post_process": self.post_process,
        }

    @torch.no_grad()
    def distance(self, images: Tensor, cameras, sources=None) -> Tensor:
        """Distance ``[B, 1, H, W]`` of images of ``cameras``; ``sources``
        (:class:`~fisheyedepth.models.cost_volume.Sources`) for the multi-view network."""
        if sources is not None:
            sources = sources._replace(
                images=sources.images.to(self.device), poses=sources.poses.to(self.device)
            )

        def run(batch: Tensor, batch_cameras) -> Tensor:
            return self.module.depth_net.distance(batch, batch_cameras, self.input_size, sources)

        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.precision == "bf16"):
            return post_processed(run, images.to(self.device), cameras, self.post_process)


class OnnxRuntime:
    """A file written by ``export.py`` in ONNX Runtime. The file's ``depth_scale`` (frozen at export) is
    replaced by each camera's own, from the base focal the file carries."""

    sources = None  # an exported file takes one image (export refuses the multi-view network)

    def __init__(self, path: str | os.PathLike, threads: int | None = None, post_process: str = "none"):
        self.path = Path(path)
        self.post_process = one_of("post_process", post_process, POST_PROCESSING)
        if not self.path.is_file():
            raise FileNotFoundError(f"{self.path}: no such ONNX file")
        _import_ort()
        try:
            self.session = onnx_session(self.path, threads)
        except Exception as err:  # onnxruntime raises its own exception types for unreadable files
            raise ValueError(
                f"{self.path}: not a readable ONNX model ({str(err).splitlines()[0][:200]})"
            ) from None
        meta = self.session.get_modelmeta().custom_metadata_map
        self.input_size = self._field(meta, "input_size")
        self.file_scale = self._field(meta, "depth_scale")
        self.base_focal = self._field(meta, "base_focal")
        self.quantize = self._field(meta, "quantize") if META + "quantize" in meta else "none"
        self.input_name = self.session.get_inputs()[0].name
        self._check_graph()

    def _field(self, meta: dict[str, str], key: str):
        """The metadata field ``key`` read by :data:`METADATA`; a missing or unfit value is a ValueError
        naming the file and the field, as a checkpoint's options are named: a depth scale of 0 or a base
        focal of inf would otherwise give distances of 1e9 m or NaN with no error."""
        if META + key not in meta:
            raise ValueError(
                f"{self.path}: metadata field '{META + key}' is missing; export the file with export.py "
                "(it records the input size and the depth scale)"
            )
        parse, expected = METADATA[key]
        try:
            return parse(meta[META + key])
        except ValueError:
            raise ValueError(
                f"{self.path}: metadata field '{META + key}' is {meta[META + key]!r}, not {expected}"
            ) from None

    def _check_graph(self) -> None:
        """The graph must be what the metadata says: ``[B, 3, H, W]`` images at ``input_size`` in,
        ``[B, 1, H, W]`` distance out (a symbolic dimension is not compared)."""
        w, h = self.input_size
        tensors = (self.session.get_inputs()[0], "input", 3), (self.session.get_outputs()[0], "output", 1)
        for tensor, role, channels in tensors:
            name = f"the graph's {role} '{tensor.name}'"
            shape = [d if isinstance(d, int) else "?" for d in tensor.shape]  # "?": symbolic
            if len(shape) != 4:
                raise ValueError(f"{self.path}: {name} is {shape}, not [B, C, H, W]")
            if shape[1] not in ("?", channels):
                what = "RGB" if role == "input" else "one distance per pixel"
                raise ValueError(f"{self.path}: {name} has {shape[1]} channels, not {channels} ({what})")
            if shape[3] not in ("?", w) or shape[2] not in ("?", h):
                raise ValueError(
                    f"{self.path}: metadata field '{META}input_size' says {w}x{h}, but {name} is "
                    f"{shape[3]}x{shape[2]}"
                )

    def describe(self) -> dict[str, Any]:
        """What results.json records: the file; its distance is resized in inverse distance."""
        return {
            "runtime": "onnx",
            "file": str(self.path),
            "quantize": self.quantize,
            "upsample": "distance",
            "post_process": self.post_process,
        }

    def run(self, images: Tensor) -> Tensor:
        """The file as it is: ``[B, 3, h, w]`` at ``input_size`` -> distance with the file's depth_scale."""
        array = np.ascontiguousarray(images.detach().cpu().numpy(), dtype=np.float32)
        return torch.from_numpy(self.session.run(None, {self.input_name: array})[0])

    def distance(self, images: Tensor, cameras, sources=None) -> Tensor:
        if sources is not None:
            raise ValueError(f"{self.path}: an exported file takes one image, not source frames")

        def run(small: Tensor, small_cameras) -> Tensor:
            scale = depth_scale(small_cameras, self.base_focal) / self.file_scale
            return self.run(small) * scale.reshape(-1, 1, 1, 1)

        def at_size(batch: Tensor, batch_cameras) -> Tensor:
            return distance_at_size(run, batch, batch_cameras, self.input_size)

        return post_processed(at_size, images.cpu(), cameras, self.post_process)


def _size(text: str) -> tuple[int, int]:
    """``"W,H"`` (the input size in an exported file's metadata) as (W, H), a size the network runs at."""
    w, h = (int(v) for v in text.split(","))
    return check_input_size((w, h), "input_size")


def _positive(text: str) -> float:
    """A finite number > 0 (``"0.0"``, ``"-1"``, ``"nan"`` and ``"inf"`` are not)."""
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(text)
    return value


def _focal(text: str) -> float | None:
    """The base focal: ``"none"`` (depth_scale 1 for every camera) or a focal length in pixels."""
    return None if text == "none" else _positive(text)


def _quantize(text: str) -> str:
    if text not in QUANTIZED:
        raise ValueError(text)
    return text


QUANTIZED = ("none", "int8")  # the values of the "quantize" field export.py writes
# The metadata fields OnnxRuntime reads: how each is parsed, and what it must be
METADATA = {
    "input_size": (_size, "'W,H', two whole numbers, each a multiple of 32"),
    "depth_scale": (_positive, "a finite number > 0 (the file's paraxial focal / base focal)"),
    "base_focal": (_focal, "'none' or a focal length in pixels, a finite number > 0"),
    "quantize": (_quantize, f"one of {', '.join(QUANTIZED)}"),
}


def calibration_images(folder: str | Path, size: tuple[int, int], count: int) -> list[np.ndarray]:
    """``count`` images spread evenly over the images under ``folder`` (recursively, in name order), as
    ``[1, 3, H, W]`` float32 RGB at ``size`` (W, H): the int8 ranges are measured on them."""
    root = Path(folder)
    if not root.is_dir():
        raise FileNotFoundError(f"calibration: {root} is not a folder of (training) images")
    files = sorted(p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise FileNotFoundError(f"calibration: no images ({' '.join(IMAGE_SUFFIXES)}) under {root}")
    picked = [files[i] for i in np.linspace(0, len(files) - 1, min(count, len(files))).round().astype(int)]
    images = []
    for path in picked:
        bgr = read_image(path).bgr
        rgb = cv2.resize(bgr, tuple(size), interpolation=cv2.INTER_AREA)[..., ::-1]
        images.append(np.ascontiguousarray(rgb.transpose(2, 0, 1)[None], dtype=np.float32) / 255.0)
    return images


def calibration_split(
    folder: str | Path, size: tuple[int, int], frames: int
) -> tuple[list[np.ndarray], np.ndarray]:
    """What ``export.py quantize=int8`` reads from ``folder`` (:func:`calibration_images` at ``size``):
    ``frames`` images to measure the int8 ranges on, and up to 4 more, spread among them but held out,
    as one ``[N, 3, H, W]`` batch to check the quantized file against (its parity)."""
    if frames < 2:
        raise ValueError(f"calibration_frames: {frames}; int8 ranges need at least 2 images")
    images = calibration_images(folder, size, frames + 4)
    held = set(range(1, len(images), 2)[:4]) if len(images) > 2 else set()
    calibration = [im for i, im in enumerate(images) if i not in held]
    if len(calibration) < 2 or not held:
        raise ValueError(
            f"calibration: {folder} has {len(images)} images; int8 needs at least 3 "
            "(2 to measure ranges on, 1 to check the quantized file against)"
        )
    return calibration, np.concatenate([images[i] for i in sorted(held)])


def as_runtime(model, input_size=None, precision: str = "fp32", device=None):
    """``model`` if it is a runtime already; a trained module as a :class:`TorchRuntime` (at
    ``input_size``, default its checkpoint's; on ``device``, default the module's)."""
    if isinstance(model, (TorchRuntime, OnnxRuntime)):
        return model
    return TorchRuntime(model, input_size, precision, model.device if device is None else device)


def quantize_int8(onnx_bytes: bytes, calibration: Iterable[np.ndarray], input_name: str = "image") -> bytes:
    """Static int8 quantization of an exported float32 file for ONNX Runtime's CPU kernels: weights per
    output channel (int8), activations per tensor (uint8) with min/max ranges from ``calibration``
    (``[1, 3, h, w]`` float32 images at the export size, training images). The nodes of
    :func:`int8_nodes` are quantized, the rest stays float32.

    The operator format (``QLinearConv``, ``QLinearAdd``, ``QLinearConcat``: ONNX Runtime's own int8
    operators), not QDQ pairs for ONNX Runtime to fuse: at 384x384 on 2 threads the QDQ file of the same
    nodes left more of its padding and dequantisation in float32 and ran 1.6x instead of 2.0x the
    float32 file's speed (EfficientNet-Lite0 with the full decoder; ResNet-18: 1.8x against 2.1x)."""
    _import_ort()
    import onnx
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.images = iter(calibration)

        def get_next(self):
            image = next(self.images, None)
            return None if image is None else {input_name: image}

    with tempfile.TemporaryDirectory() as tmp:  # the quantizer reads and writes files
        src, pre, dst = Path(tmp) / "fp32.onnx", Path(tmp) / "pre.onnx", Path(tmp) / "int8.onnx"
        src.write_bytes(onnx_bytes)
        # ONNX Runtime's own graph optimisations first (shape inference, BatchNorm folded into the
        # convolutions), so that each quantized convolution and its activation become one int8 kernel
        quant_pre_process(str(src), str(pre), skip_symbolic_shape=True)
        nodes = int8_nodes(onnx.load(str(pre)))
        if not nodes:
            raise ValueError(
                "quantize=int8: the graph has no encoder/decoder nodes to quantize (not an export.py file?)"
            )
        quantize_static(
            str(pre),
            str(dst),
            Reader(),
            quant_format=QuantFormat.QOperator,
            per_channel=True,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
            nodes_to_quantize=nodes,
        )
        return dst.read_bytes()


def int8_nodes(model) -> list[str]:
    """The nodes :func:`quantize_int8` quantizes: those under :data:`INT8_SCOPES` and the clamp of the
    logits, less :func:`finest_skip_nodes` (the encoder's layers up to its first, stride-2 feature map).

    Why those stay float32, measured on the released weights (EfficientNet-Lite0) at 384x384, each part
    quantized alone: the input normalisation moved the median distance by 0.6 %, the stem convolution
    1.9 %, the first block 3.6 %, any later block 1.3 % at most; the whole network 4.5 % (over the
    export's 3 %), with them float32 2.0 %. They feed the decoder's finest level directly, and at
    stride 2 they are a few per cent of the encoder's work. For ResNet-18 the same rule keeps its
    first 7x7 convolution."""
    keep = finest_skip_nodes(model.graph)
    producer = {out: node for node in model.graph.node for out in node.output}
    nodes = []
    for node in model.graph.node:
        if node.name in keep:
            continue
        source = producer.get(node.input[0]) if node.input else None
        clamp = node.op_type == "Clip" and source is not None and source.name.startswith(INT8_SCOPES[-1])
        if node.name.startswith(INT8_SCOPES) or clamp:
            nodes.append(node.name)
    return nodes


def finest_skip_nodes(graph) -> set[str]:
    """The names of the nodes that compute the finest feature map the decoder reads from the encoder
    (the first one the encoder produces, in the graph's topological order), and of everything before it."""
    produced = {out: (i, node) for i, node in enumerate(graph.node) for out in node.output}
    skips = [
        name
        for node in graph.node
        if node.name.startswith("/depth_net/decoder/")
        for name in node.input
        if name in produced and produced[name][1].name.startswith("/depth_net/encoder/")
    ]
    if not skips:
        return set()
    todo, seen = [produced[min(skips, key=lambda name: produced[name][0])][1]], set()
    while todo:
        node = todo.pop()
        if node.name not in seen:
            seen.add(node.name)
            todo += [produced[name][1] for name in node.input if name in produced]
    return seen
