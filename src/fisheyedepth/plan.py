"""What a command will do, worked out once from its composed config and checked before anything is built,
rendered or written: :class:`TrainPlan` (``train.py``), :class:`EvalPlan` (``eval.py``),
:class:`PredictPlan` (``predict.py``) and :class:`ExportPlan` (``export.py``), and the parts they share
(:class:`DataPlan`, :class:`ModelPlan`, :class:`RuntimePlan`, :class:`Scoring`). Each ``*_plan(cfg)``
reads the config; the commands (:mod:`fisheyedepth.cli`) build from the plan alone.

A plan is frozen and holds plain values (options as read-only mappings, lists as tuples), except the
``_target_`` configs a command makes objects of (the data module, trainer, logger and callbacks), kept as
config nodes, and a checkpoint to resume, kept as read."""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from .checkpoints import check_resumable, released_checkpoint
from .config import (
    check_config,
    configured_options,
    model_arguments,
    resolve_precision,
    rig_offsets,
    source_offsets,
)
from .files import check_apart, check_writable
from .models.depth_net import check_input_size, check_network_memory
from .options.defaults import check_combinations, net_options
from .options.kinds import check_options, one_of
from .options.tables import POST_PROCESSING, RUNTIME_PRECISIONS, TRAINER_OPTIONS
from .synthetic.spec import check_render_memory

log = logging.getLogger("fisheyedepth")

SELECT = ("last", "best")  # train.py's select: the checkpoint tested after training
EXPORT_FORMATS = {"onnx": ".onnx", "torchscript": ".pt"}
QUANTIZE = ("int8",)


def frozen(value: Any) -> Any:
    """``value`` read-only: mappings as :class:`~types.MappingProxyType`, lists as tuples, all the way
    down (:func:`thawed` gives the plain value back)."""
    if isinstance(value, Mapping):
        return MappingProxyType({k: frozen(v) for k, v in value.items()})
    if isinstance(value, (list, tuple)):
        return tuple(frozen(v) for v in value)
    return value


def thawed(value: Any) -> Any:
    """A fresh plain copy of a :func:`frozen` value: dicts and lists."""
    if isinstance(value, Mapping):
        return {k: thawed(v) for k, v in value.items()}
    if isinstance(value, tuple):
        return [thawed(v) for v in value]
    return value


@dataclass(frozen=True)
class DataPlan:
    """The data a command reads: ``datamodule``, the data module's ``_target_`` config; ``offsets`` and
    ``rig_offsets``, the source frames it loads for the model (``train.py``: the model's
    ``objective.source_offsets`` and ``rig_offsets``; None: the data module's own); ``root`` and
    ``generate``, the synthetic worlds rendered on first use (None: nothing to render); ``name``, the data
    as ``results.json`` names it."""

    datamodule: DictConfig
    offsets: tuple[int, ...] | None
    rig_offsets: tuple[int, ...] | None
    root: str | tuple[str, ...] | None
    generate: Mapping[str, Any] | None
    name: str

    def arguments(self) -> dict[str, Any]:
        """What the data module is given beside its config: the sources the model warps, if any."""
        if self.offsets is None:
            return {}
        return {"offsets": list(self.offsets), "rig_offsets": list(self.rig_offsets or ())}


def data_plan(
    cfg: DictConfig, offsets: Sequence[int] | None = None, rig: Sequence[int] | None = None
) -> DataPlan:
    """``cfg.data``, its data module loading the source ``offsets`` and ``rig`` offsets when given."""
    gen, root = cfg.data.get("generate"), None
    if gen:  # one folder, or a list (a mixed dataset: one world per folder)
        root = cfg.data.datamodule.root
        root = OmegaConf.to_container(root, resolve=True) if OmegaConf.is_list(root) else str(root)
    return DataPlan(
        datamodule=cfg.data.datamodule,
        offsets=None if offsets is None else tuple(offsets),
        rig_offsets=None if rig is None else tuple(rig),
        root=frozen(root),
        generate=frozen(OmegaConf.to_container(gen, resolve=True)) if gen else None,
        name=str(cfg.data.datamodule.root),
    )


@dataclass(frozen=True)
class ModelPlan:
    """The module to build: its class (``model._target_``) and its options as configured, resolved, in
    their groups (``net``, ``objective``, ``optimizer``, ``scheduler``) beside the module's own; the module
    fills in what they leave out from its YAML. ``net.base_focal`` may still be ``auto`` here: the
    training cameras give its number once the data exists
    (:func:`fisheyedepth.config.resolve_base_focal`), and :meth:`arguments` takes it then."""

    target: str
    options: Mapping[str, Any]

    def arguments(self, **resolved: Any) -> dict[str, Any]:
        """The options as plain dicts, each group in ``resolved`` merged over its group
        (``net={"base_focal": 21.5}``)."""
        out = thawed(self.options)
        for key, value in resolved.items():
            out[key] = merged(out.get(key), value)
        return out

    def configured(self) -> dict[str, Any]:
        """Every option of the module, its defaults where the config is silent (imports its class)."""
        return configured_options(self.target, self.arguments())


def merged(base: Any, over: Any) -> Any:
    """``over`` merged into ``base`` key by key where both are dicts, else ``over``."""
    if not (isinstance(base, dict) and isinstance(over, dict)):
        return over
    return base | {k: merged(base.get(k), v) for k, v in over.items()}


def model_plan(cfg: DictConfig) -> ModelPlan:
    """``cfg.model``."""
    target, options = model_arguments(cfg)
    return ModelPlan(target, frozen(options))


@dataclass(frozen=True)
class Scoring:
    """How a split is scored into ``results.json`` (``eval.*``) and the names it records: the
    ``experiment`` (None: named by the command) and the ``data``."""

    protocols: tuple[str, ...]
    scalings: tuple[str, ...]
    camera_height: float | None
    pictures: int
    experiment: str | None
    data: str


def scoring(cfg: DictConfig, data: DataPlan) -> Scoring:
    """``cfg.eval`` and ``experiment_name``, on ``data``."""
    ev = cfg.eval
    return Scoring(
        protocols=tuple(ev.protocols),
        scalings=tuple(ev.scalings),
        camera_height=ev.get("camera_height"),
        pictures=int(ev.pictures),
        experiment=cfg.get("experiment_name"),
        data=data.name,
    )


@dataclass(frozen=True)
class TrainPlan:
    """What ``train.py`` will do: train into ``output_dir`` (resuming ``resume``: ``resumed`` is that
    checkpoint as read and checked against the model), on ``data``, the ``model``, with the ``trainer``,
    ``logger`` and ``callbacks`` configs, at ``precision`` (resolved) on ``accelerator`` (``auto`` chosen
    by what the machine has: :func:`choose_accelerator`), seeded with ``seed``; then, with
    ``test``, score the ``select``-ed checkpoint (last or best) on the test split by ``scoring``."""

    output_dir: Path
    resume: str | None
    data: DataPlan
    model: ModelPlan
    trainer: DictConfig
    logger: DictConfig | None
    callbacks: tuple[DictConfig, ...]
    precision: Any
    accelerator: str | None
    devices: Any
    select: str
    seed: int
    test: bool
    keep_freed_memory: bool
    scoring: Scoring
    resumed: Mapping[str, Any] | None = field(default=None, repr=False, compare=False)


def check_select(select: str) -> str:
    """``select`` if it is one of :data:`SELECT`, else a ValueError naming it."""
    if select not in SELECT:
        raise ValueError(f"select={select!r}: expected one of {SELECT}")
    return select


def choose_accelerator(accelerator: Any) -> Any:
    """``trainer.accelerator``, with ``auto`` (train.py's default, ``conf/trainer/auto.yaml``) chosen by
    what the machine has: ``cuda`` where torch sees a CUDA GPU, else ``cpu``. A named one is kept."""
    if accelerator != "auto":
        return accelerator
    return "cuda" if torch.cuda.is_available() else "cpu"


def describe_accelerator(accelerator: Any) -> str:
    """``accelerator`` as the run's log states it: ``cuda (NVIDIA H200)``, ``cpu``."""
    if accelerator in ("cuda", "gpu") and torch.cuda.is_available():
        return f"{accelerator} ({torch.cuda.get_device_name(0)})"
    return str(accelerator)


def check_training(cfg: DictConfig, model: ModelPlan, data: DataPlan) -> None:
    """What :func:`~fisheyedepth.config.check_config` leaves to the training plan: the trainer's options
    by kind and range (:data:`~fisheyedepth.options.tables.TRAINER_OPTIONS`), the model's options that
    contradict each other (:func:`~fisheyedepth.options.defaults.check_combinations`), and the memory the
    rendering (:func:`~fisheyedepth.synthetic.spec.check_render_memory`) and the network's training step
    (:func:`~fisheyedepth.models.depth_net.check_network_memory`) need, against this machine's."""
    trainer = OmegaConf.to_container(cfg.trainer, resolve=True)
    check_options({k: v for k, v in trainer.items() if k in TRAINER_OPTIONS}, TRAINER_OPTIONS, "trainer.")
    options = thawed(model.options)
    check_combinations(options, "model.")
    if data.generate is not None:
        check_render_memory(thawed(data.generate), "data.generate.")
    datamodule = cfg.data.datamodule
    sources = len(data.offsets or ()) + len(data.rig_offsets or ())
    net = net_options(**(options.get("net") or {}))  # the module's defaults where the config is silent
    batch, size = int(datamodule.batch_size), tuple(datamodule.size)
    check_network_memory(net, "model.net.", batch, size, sources, training=True)


def train_plan(cfg: DictConfig) -> TrainPlan:
    """``train.py``'s plan. Refused here, before any folder, render or fit: sizes, switches and numbers
    of their kind and range (the trainer's too), options that contradict each other or need more memory
    than the machine has (:func:`check_training`), source offsets the data module contradicts, a
    ``select`` that is not one of :data:`SELECT`, and a checkpoint that cannot be resumed with this model
    (read here; the model's class, and Lightning with it, is imported only for one that can be)."""
    output_dir = Path(cfg.paths.output_dir)
    check_config(cfg)
    data = data_plan(cfg, source_offsets(cfg), rig_offsets(cfg))
    select = check_select(cfg.get("select", "last"))
    model = model_plan(cfg)
    check_training(cfg, model, data)
    trainer = cfg.trainer
    accelerator = choose_accelerator(trainer.get("accelerator"))
    precision = resolve_precision(trainer.get("precision"), accelerator)
    resume = str(cfg.ckpt_path) if cfg.get("ckpt_path") else None
    resumed = check_resumable(resume, model.configured) if resume else None
    return TrainPlan(
        output_dir=output_dir,
        resume=resume,
        data=data,
        model=model,
        trainer=trainer,
        logger=cfg.get("logger") or None,
        callbacks=tuple(c for c in (cfg.get("callbacks") or {}).values() if c is not None),
        precision=precision,
        accelerator=accelerator,
        devices=trainer.get("devices"),
        select=select,
        seed=cfg.seed,
        test=bool(cfg.get("test")),
        keep_freed_memory=bool(cfg.get("keep_freed_memory")),
        scoring=scoring(cfg, data),
        resumed=None if resumed is None else MappingProxyType(resumed),
    )


def checkpoint_to_read(ckpt_path: Any) -> str:
    """``ckpt_path``, or the released weights (``weights/``, checked against their checksum) when none
    is given: metric distance from a calibrated camera without training."""
    if ckpt_path:
        return str(ckpt_path)
    path = released_checkpoint()
    log.info("no ckpt_path: the released weights %s (weights/README.md)", path)
    return str(path)


@dataclass(frozen=True)
class RuntimePlan:
    """The network ``predict.py`` and ``eval.py`` run: ``kind`` torch (``checkpoint`` in PyTorch, at
    ``precision`` on ``device``, ``upsample`` None: the checkpoint's) or onnx (``model_file``, an
    ``export.py`` file, which fixes the input size, on ``threads``); ``size``, the network's input
    (None: the checkpoint's or the file's); ``post_process``, none or flip."""

    kind: str
    checkpoint: str | None
    model_file: str | None
    size: tuple[int, int] | None
    precision: str | None
    device: Any
    upsample: str | None
    post_process: str
    threads: int | None


def runtime_plan(cfg: DictConfig) -> RuntimePlan:
    """``runtime``, ``ckpt_path`` or ``model_file`` (typed ``model=FILE.onnx``), ``size``,
    ``precision``, ``device``, ``upsample``, ``threads``, ``post_process`` (each None where the runtime
    has no use for it). Refused here: a runtime that is not torch or onnx, a file without runtime=onnx
    or runtime=onnx without one, and for torch a precision, post-processing or size it cannot run."""
    kind, size = str(cfg.get("runtime", "torch")), cfg.get("size")
    size = tuple(size) if size else None
    post_process, upsample = str(cfg.get("post_process", "none")), cfg.get("upsample")
    if kind == "onnx":
        if not cfg.get("model_file"):
            raise ValueError("model: runtime=onnx needs the exported file, model=FILE.onnx (export.py)")
        if upsample not in (None, "distance"):
            raise ValueError(
                f"upsample: {upsample!r}; an exported file upsamples its distance (upsample=distance)"
            )
        file = str(cfg.model_file)
        return RuntimePlan("onnx", None, file, size, None, None, None, post_process, cfg.get("threads"))
    if kind != "torch":
        raise ValueError(f"runtime: {kind!r} is not one of torch, onnx")
    if cfg.get("model_file"):
        raise ValueError("model: a file is for runtime=onnx (runtime=onnx model=FILE.onnx)")
    precision = one_of("precision", str(cfg.get("precision", "fp32")), RUNTIME_PRECISIONS)
    one_of("post_process", post_process, POST_PROCESSING)
    size = check_input_size(size, "size") if size else None
    return RuntimePlan(
        kind="torch",
        checkpoint=checkpoint_to_read(cfg.get("ckpt_path")),
        model_file=None,
        size=size,
        precision=precision,
        device=cfg.get("device", "cpu"),
        upsample=None if upsample is None else str(upsample),  # only how a distance reaches a larger image
        post_process=post_process,
        threads=None,
    )


@dataclass(frozen=True)
class EvalPlan:
    """What ``eval.py`` will do: run ``runtime`` on the ``split`` of ``data``, scored by ``scoring``
    into ``output_dir/results.json``."""

    output_dir: Path
    data: DataPlan
    runtime: RuntimePlan
    split: str
    scoring: Scoring


def eval_plan(cfg: DictConfig) -> EvalPlan:
    """``eval.py``'s plan; its runtime's options are refused here (:func:`runtime_plan`)."""
    data = data_plan(cfg)
    return EvalPlan(
        output_dir=Path(cfg.paths.output_dir),
        data=data,
        runtime=runtime_plan(cfg),
        split=str(cfg.get("split", "test")),
        scoring=scoring(cfg, data),
    )


@dataclass(frozen=True)
class PredictPlan:
    """What ``predict.py`` will do: run ``runtime`` on the frames of ``input`` (a folder, a video or a
    live camera; at most ``max_frames``) taken by the camera calibrated in ``camera``, ``batch_size`` at a
    time, and write their distance into ``output`` (checked writable), with the outputs its writer is
    asked for (``z_depth``, ``point_cloud``, ``png_scale``, the colour scale ``vmin``-``vmax``,
    ``overwrite``)."""

    output: Path
    input: Any
    camera: Any
    max_frames: int | None
    batch_size: Any
    runtime: RuntimePlan
    z_depth: bool
    point_cloud: bool
    png_scale: str
    vmin: float
    vmax: float
    overwrite: bool


def predict_plan(cfg: DictConfig) -> PredictPlan:
    """``predict.py``'s plan: the output folder is checked first (a read-only or full filesystem is
    named before any network is loaded), then the runtime."""
    option = "output" if cfg.get("output") else "paths.output_dir"
    output = check_writable(cfg.output if cfg.get("output") else cfg.paths.output_dir, option)
    if cfg.input is not None and Path(str(cfg.input)).exists():  # a folder or a video, not a live camera
        check_apart(output, option, {"the input": cfg.input})
    return PredictPlan(
        output=output,
        input=cfg.input,
        camera=cfg.camera,
        max_frames=cfg.get("max_frames"),
        batch_size=cfg.batch_size,
        runtime=runtime_plan(cfg),
        z_depth=cfg.z_depth,
        point_cloud=cfg.point_cloud,
        png_scale=str(cfg.png_scale),
        vmin=cfg.vmin,
        vmax=cfg.vmax,
        overwrite=cfg.overwrite,
    )


@dataclass(frozen=True)
class ExportPlan:
    """What ``export.py`` will do: the network of ``checkpoint`` at ``size`` (None: the checkpoint's
    ``input_size``) in ``format``, int8 with ``quantize`` (its ranges from ``calibration_frames`` images
    of ``calibration``), its depth scale for ``camera`` (None: 1), written to ``output`` (None: a file
    named by size and format in ``output_dir``; :meth:`path`), replacing one only with ``overwrite``."""

    checkpoint: str
    format: str
    quantize: str | None
    calibration: str | None
    calibration_frames: int | None
    size: tuple[int, int] | None
    camera: str | None
    output: Path | None
    output_dir: Path | None
    overwrite: bool

    def path(self, size: tuple[int, int]) -> Path:
        """The file written for the network at ``size``."""
        if self.output is not None:
            return self.output
        quantized = "_" + self.quantize if self.quantize else ""
        name = f"fisheyedepth_{size[0]}x{size[1]}{quantized}{EXPORT_FORMATS[self.format]}"
        return Path(self.output_dir) / name


def export_size(size: tuple, option: str) -> tuple[int, int]:
    """``size`` [W, H] checked as the one input size of an exported network, named ``option``."""
    if len(size) != 2:
        raise ValueError(
            "export needs a fixed input size: size=[W,H] (or a checkpoint that stores input_size)"
        )
    return check_input_size(size, option)


def export_plan(cfg: DictConfig) -> ExportPlan:
    """``export.py``'s plan; refused here: a format or quantisation it cannot write, int8 without
    calibration images, and a size the network cannot run at."""
    if cfg.format not in EXPORT_FORMATS:
        raise ValueError(f"format: {cfg.format!r} is not one of {', '.join(EXPORT_FORMATS)}")
    quantize = cfg.get("quantize")
    if quantize is not None and (quantize not in QUANTIZE or cfg.format != "onnx"):
        raise ValueError(f"quantize: {quantize!r}; only quantize=int8 with format=onnx (or null)")
    if quantize and not cfg.get("calibration"):
        raise ValueError("calibration: quantize=int8 needs a folder of training images, calibration=DIR")
    size = export_size(tuple(cfg.size), "size") if cfg.get("size") else None
    output, folder = cfg.get("output"), OmegaConf.select(cfg, "paths.output_dir")
    return ExportPlan(
        checkpoint=checkpoint_to_read(cfg.get("ckpt_path")),
        format=str(cfg.format),
        quantize=quantize,
        calibration=str(cfg.calibration) if quantize else None,
        calibration_frames=int(cfg.calibration_frames) if quantize else None,
        size=size,
        camera=cfg.get("camera"),
        output=Path(output) if output else None,
        output_dir=None if output or folder is None else Path(folder),
        overwrite=bool(cfg.get("overwrite")),
    )
