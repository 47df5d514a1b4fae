"""Hydra entry points (``train.py``, ``eval.py``): the only place configs become objects.

The library never sees an OmegaConf object: everything below is instantiated here and handed over as
plain Python values.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.utils import instantiate
from lightning.pytorch.utilities.exceptions import SIGTERMException
from omegaconf import DictConfig, OmegaConf
from rich.console import Console
from rich.table import Table

from .checkpoints import check_resumable, load_module
from .data.synthetic import ensure_dataset, is_complete
from .evaluation import evaluate
from .module import FisheyeDepthModule
from .utils import atomic_write_text

log = logging.getLogger("fisheyedepth")

EXIT_SIGTERM = 128 + 15  # the shell's status for a process ended by SIGTERM
EXIT_USAGE = 2
# Errors about the user's input (files, options): one line naming the file or option, no traceback.
INPUT_ERRORS = (FileNotFoundError, FileExistsError, NotADirectoryError, ValueError, KeyError)


def run_command(command, cfg: DictConfig):
    """Run an entry point; an input error prints one line (``error: <file>: <what>``) and exits 2.
    ``FISHEYEDEPTH_TRACEBACK=1`` shows the full traceback instead."""
    try:
        return command(cfg)
    except INPUT_ERRORS as exc:
        if os.environ.get("FISHEYEDEPTH_TRACEBACK"):
            raise
        message = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"error: {message}", file=sys.stderr)
        raise SystemExit(EXIT_USAGE) from None


def prepare_data(cfg: DictConfig) -> None:
    """Render the synthetic dataset on first use (``data.generate``); a finished one is reused. A folder
    that is not a synthetic dataset made by this project is refused and left untouched."""
    gen = cfg.data.get("generate")
    if not gen:
        return
    root = Path(cfg.data.datamodule.root)
    if not is_complete(root):
        log.info("rendering the synthetic dataset into %s (first use)", root)
    ensure_dataset(root, **OmegaConf.to_container(gen, resolve=True))


def _git_commit() -> str | None:
    try:
        return subprocess.run(
            ["git", "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
            cwd=Path(__file__).parent,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def print_table(results: dict[str, Any], title: str) -> None:
    table = Table(title=title)
    for col in ("protocol", "scaling", "abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3", "images"):
        table.add_column(col, justify="right")
    for name, res in results.items():
        for scaling in (k for k in res if k in ("none", "median", "dnet")):
            m = res[scaling]
            table.add_row(
                name,
                scaling,
                *(f"{m[k]:.3f}" for k in ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")),
                str(m["images"]),
            )
    Console(width=130).print(table)


def run_evaluation(
    cfg: DictConfig,
    module: FisheyeDepthModule,
    datamodule,
    out_dir: Path,
    ckpt: str | None,
    extra: dict[str, Any],
    split: str = "test",
) -> dict[str, Any]:
    """Evaluate ``split`` at the ground truth's native resolution, the network at the size it was
    trained at (its checkpoint's ``input_size``); write ``results.json``."""
    train_size = module.hparams.get("input_size") or datamodule.size
    native = instantiate(cfg.data.datamodule, size=None, augment=None, batch_size=4, num_workers=0)
    loader = native.dataloader(split)
    results = evaluate(
        module,
        loader,
        train_size,
        list(cfg.eval.protocols),
        list(cfg.eval.scalings),
        cfg.eval.get("camera_height"),
        out_dir / "predictions",
        int(cfg.eval.pictures),
    )
    record = {
        "experiment": cfg.get("experiment_name"),
        "checkpoint": ckpt,
        "model": {
            k: module.hparams[k] for k in ("fisheye_projection", "real_scale", "multi_channel", "attention")
        },
        "data": str(cfg.data.datamodule.root),
        "split": split,
        "train_size": list(train_size) if train_size else None,
        "results": results,
        "commit": _git_commit(),
        "written": time.strftime("%Y-%m-%d %H:%M:%S"),
        **extra,
    }
    path = free_path(out_dir / "results.json")  # a resumed run keeps the earlier run's results
    atomic_write_text(path, json.dumps(record, indent=2) + "\n")
    print_table(results, f"{record['experiment']}: {path}")
    return record


def train(cfg: DictConfig) -> dict[str, Any] | None:
    out_dir = Path(cfg.paths.output_dir)
    if cfg.get("ckpt_path"):
        check_resumable(cfg.ckpt_path)
    L.seed_everything(cfg.seed, workers=True)
    prepare_data(cfg)
    datamodule = instantiate(cfg.data.datamodule)
    module = instantiate(cfg.model, _convert_="all")
    logger = instantiate(cfg.logger) if cfg.get("logger") else False
    callbacks = [instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c is not None]
    trainer: L.Trainer = instantiate(
        cfg.trainer, logger=logger, callbacks=callbacks, default_root_dir=str(out_dir)
    )
    try:
        try:
            trainer.fit(module, datamodule=datamodule, ckpt_path=cfg.get("ckpt_path"))
        except SIGTERMException:
            # Lightning stops at a batch boundary and raises SystemExit(None), i.e. exit 0: a job
            # scheduler, make or a shell script would take the run for finished.
            last = Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt"
            log.error(
                "terminated by SIGTERM at step %d; no results.json. Resume with ckpt_path=%s",
                trainer.global_step,
                last if last.is_file() else "<a checkpoint of this run>",
            )
            raise SystemExit(EXIT_SIGTERM) from None
        record = None
        if cfg.get("test") and trainer.is_global_zero and not trainer.fast_dev_run:
            ckpt = getattr(trainer.checkpoint_callback, "best_model_path", "") or None
            best = load_module(ckpt) if ckpt else module
            record = run_evaluation(
                cfg,
                best,
                datamodule,
                out_dir,
                ckpt,
                {
                    "resumed_from": cfg.get("ckpt_path"),
                    "global_step": trainer.global_step,
                    "skipped_batches": module.skipped_batches,
                },
            )
        return record
    finally:
        if logger and type(logger).__name__ == "WandbLogger":
            import wandb

            wandb.finish()  # one wandb run per job, also inside a multirun sweep


def eval_checkpoint(cfg: DictConfig) -> dict[str, Any]:
    out_dir = Path(cfg.paths.output_dir)
    prepare_data(cfg)
    module = load_module(cfg.ckpt_path).to(cfg.get("device", "cpu"))
    datamodule = instantiate(cfg.data.datamodule)
    return run_evaluation(
        cfg, module, datamodule, out_dir, str(cfg.ckpt_path), {}, str(cfg.get("split", "test"))
    )


# ----------------------------------------------------------------------------------------------- predict
def free_path(path: Path) -> Path:
    """``path``, or ``name_1.ext``, ``name_2.ext`` ... when it exists: an earlier run's file is kept."""
    candidate, n = path, 0
    while candidate.exists():
        n += 1
        candidate = path.with_name(f"{path.stem}_{n}{path.suffix}")
    return candidate


def _check_aspect(frame_path: Path, size: tuple[int, int], camera, calibration) -> None:
    """A calibration is resized to the images only when both have one aspect ratio."""
    (w, h), (cw, ch) = size, (camera.width, camera.height)
    if abs(w * ch - h * cw) > 0.01 * w * ch:
        raise ValueError(
            f"{frame_path}: image is {w}x{h} but the calibration {calibration} is {cw}x{ch}, another "
            "aspect ratio; resizing the camera model would stretch it (crop the images or recalibrate)"
        )


def predict(cfg: DictConfig) -> dict[str, Any]:
    import numpy as np
    from tqdm import tqdm

    from .cameras import load_camera
    from .images import FrameSource
    from .inference import DistancePredictor, PredictionWriter

    out = Path(cfg.output) if cfg.get("output") else Path(cfg.paths.output_dir)
    writer = PredictionWriter(
        out, cfg.z_depth, cfg.point_cloud, str(cfg.png_scale), cfg.vmin, cfg.vmax, cfg.overwrite
    )
    source = FrameSource(cfg.input)  # lists the inputs without decoding any
    writer.check_free(source.names())
    module = load_module(cfg.ckpt_path)
    camera = load_camera(cfg.camera)
    predictors: dict[tuple[int, int], DistancePredictor] = {}
    unreadable: list[str] = []
    grayscale: list[str] = []
    done, t0 = 0, time.perf_counter()
    batch: list = []

    def run_batch() -> int:
        h, w = batch[0].bgr.shape[:2]
        if (w, h) not in predictors:
            _check_aspect(batch[0].path, (w, h), camera, cfg.camera)
            cam = camera if (w, h) == (camera.width, camera.height) else camera.resize(w, h)
            predictors[(w, h)] = DistancePredictor(module, cam, cfg.get("size"), cfg.get("device", "cpu"))
        predictor = predictors[(w, h)]
        rgb = np.stack([f.bgr[..., ::-1] for f in batch])
        images = torch.from_numpy(rgb.copy()).permute(0, 3, 1, 2).float() / 255.0
        distance = predictor(images).cpu()
        for frame, d, colour in zip(batch, distance[:, 0], rgb, strict=True):
            writer.write(frame.name, d, colour, predictor.camera)
        n = len(batch)
        batch.clear()
        return n

    for frame in tqdm(source, total=len(source) or None, desc="predicting", unit="frame"):
        if frame.bgr is None:
            unreadable.append(str(frame.path))
            log.warning("%s, skipped", frame.error)
            continue
        if frame.channels == 1:
            grayscale.append(str(frame.path))
            if len(grayscale) == 1:
                log.warning(
                    "%s: grayscale image, replicated to 3 channels (and any others: summary)", frame.path
                )
        if batch and frame.bgr.shape != batch[0].bgr.shape:
            done += run_batch()
        batch.append(frame)
        if len(batch) >= cfg.batch_size:
            done += run_batch()
    if batch:
        done += run_batch()
    seconds = time.perf_counter() - t0
    summary = {
        "input": str(source.source),
        "frames": done,
        "skipped": len(unreadable),
        "unreadable": unreadable,
        "grayscale": grayscale,
        "seconds": round(seconds, 3),
        "fps": round(done / seconds, 2) if seconds > 0 else None,
        "output": str(out),
        "png_scale": f"uint16 = metres * {int(1000 if cfg.png_scale == 'mm' else 256)}, 0 = no ray",
    }
    if done == 0:
        raise ValueError(f"{source.source}: no frame could be read ({len(unreadable)} unreadable)")
    summary_path = out / "summary.json" if cfg.overwrite else free_path(out / "summary.json")
    atomic_write_text(summary_path, json.dumps(summary, indent=2) + "\n")
    Console(width=130).print(
        f"{done} frames in {seconds:.1f} s ({summary['fps']} fps), {len(unreadable)} unreadable "
        f"skipped{': ' + ', '.join(unreadable[:5]) if unreadable else ''}"
        f"{f', {len(grayscale)} grayscale' if grayscale else ''}; outputs in {out} ({summary_path.name})"
    )
    return summary


def predict_cli() -> None:
    """Console script ``fisheyedepth-predict`` (the same as ``python predict.py``)."""
    import hydra

    hydra.main(config_path="../../conf", config_name="predict", version_base="1.3")(
        lambda cfg: run_command(predict, cfg)
    )()


# ----------------------------------------------------------------------------------------------- export
EXPORT_FORMATS = {"onnx": ".onnx", "torchscript": ".pt"}


def export(cfg: DictConfig) -> dict[str, Any]:
    from .cameras import load_camera
    from .inference import DistancePredictor

    if cfg.format not in EXPORT_FORMATS:
        raise ValueError(f"format: {cfg.format!r} is not one of {', '.join(EXPORT_FORMATS)}")
    module = load_module(cfg.ckpt_path)
    size = tuple(cfg.size) if cfg.get("size") else tuple(module.hparams.get("input_size") or ())
    if len(size) != 2:
        raise ValueError(
            "export needs a fixed input size: size=[W,H] (or a checkpoint that stores input_size)"
        )
    if cfg.get("camera"):
        camera = load_camera(cfg.camera)
    else:  # no camera: depth_scale 1 (right unless the model was trained with base_focal)
        from .cameras import PinholeCamera

        camera = PinholeCamera(width=size[0], height=size[1], fx=1.0, fy=1.0, cx=0.0, cy=0.0)
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
    tmp = path.with_name(f".{path.name}.tmp")
    if cfg.format == "torchscript":
        traced = torch.jit.trace(net, example)
        traced.save(str(tmp))
        exported = torch.jit.load(str(tmp))
        run = lambda x: exported(x)  # noqa: E731
    else:
        torch.onnx.export(
            net,
            (example,),
            str(tmp),
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
            session = ort.InferenceSession(str(tmp), providers=["CPUExecutionProvider"])
            run = lambda x: torch.from_numpy(session.run(None, {"image": x.numpy()})[0])  # noqa: E731
    import os

    os.replace(tmp, path)
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
