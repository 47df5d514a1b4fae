"""Hydra entry points (``train.py``, ``eval.py``): the only place configs become objects.

The library never sees an OmegaConf object: everything below is instantiated here and handed over as
plain Python values.
"""

from __future__ import annotations

import json
import logging
import subprocess
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from rich.console import Console
from rich.table import Table

from .data.synthetic import generate, is_complete
from .evaluation import evaluate
from .module import FisheyeDepthModule
from .utils import atomic_write_text

log = logging.getLogger("fisheyedepth")


def prepare_data(cfg: DictConfig) -> None:
    """Render the synthetic dataset on first use (``data.generate``); a finished one is reused."""
    gen = cfg.data.get("generate")
    if not gen:
        return
    root = Path(cfg.data.datamodule.root)
    if is_complete(root):
        return
    log.info("rendering the synthetic dataset into %s (first use)", root)
    generate(root, **OmegaConf.to_container(gen, resolve=True), overwrite=root.exists())


def load_module(path: str | Path) -> FisheyeDepthModule:
    """A trained module from a Lightning checkpoint, read with ``weights_only=True``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: checkpoint not found")
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    if "state_dict" not in ckpt or "hyper_parameters" not in ckpt:
        raise ValueError(f"{path}: not a FisheyeDepth checkpoint (no state_dict / hyper_parameters)")
    module = FisheyeDepthModule(**dict(ckpt["hyper_parameters"]))
    module.load_state_dict(ckpt["state_dict"])
    return module


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
) -> dict[str, Any]:
    """Evaluate on the test split at the ground truth's native resolution; write ``results.json``."""
    train_size = datamodule.size
    native = instantiate(cfg.data.datamodule, size=None, augment=None, batch_size=4, num_workers=0)
    loader = native.test_dataloader()
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
        "train_size": list(train_size) if train_size else None,
        "results": results,
        "commit": _git_commit(),
        "written": time.strftime("%Y-%m-%d %H:%M:%S"),
        **extra,
    }
    path = out_dir / "results.json"
    atomic_write_text(path, json.dumps(record, indent=2) + "\n")
    print_table(results, f"{record['experiment']}: {path}")
    return record


def train(cfg: DictConfig) -> dict[str, Any] | None:
    out_dir = Path(cfg.paths.output_dir)
    L.seed_everything(cfg.seed, workers=True)
    prepare_data(cfg)
    datamodule = instantiate(cfg.data.datamodule)
    module = instantiate(cfg.model, _convert_="all")
    logger = instantiate(cfg.logger) if cfg.get("logger") else False
    callbacks = [instantiate(c) for c in (cfg.get("callbacks") or {}).values()]
    trainer: L.Trainer = instantiate(
        cfg.trainer, logger=logger, callbacks=callbacks, default_root_dir=str(out_dir)
    )
    try:
        trainer.fit(module, datamodule=datamodule, ckpt_path=cfg.get("ckpt_path"))
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
    return run_evaluation(cfg, module, datamodule, out_dir, str(cfg.ckpt_path), {})


# ----------------------------------------------------------------------------------------------- predict
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def _frames(source: Path):
    """(name, BGR image or None when unreadable) from a folder of images or a video file."""
    import cv2

    if source.is_dir():
        for path in sorted(p for p in source.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES):
            yield path.stem, cv2.imread(str(path), cv2.IMREAD_COLOR), path
    elif source.is_file():
        video = cv2.VideoCapture(str(source))
        if not video.isOpened():
            raise ValueError(f"{source}: not a readable video")
        i = 0
        while True:
            ok, frame = video.read()
            if not ok:
                break
            yield f"frame_{i:06d}", frame, source
            i += 1
        video.release()
    else:
        raise FileNotFoundError(f"{source}: no such image folder or video")


def predict(cfg: DictConfig) -> dict[str, Any]:
    import cv2
    import numpy as np
    from tqdm import tqdm

    from .cameras import load_camera
    from .inference import DistancePredictor, colour_bar, distance_png, point_cloud, write_ply
    from .viz import colourise

    source = Path(cfg.input)
    out = Path(cfg.output) if cfg.get("output") else Path(cfg.paths.output_dir)
    module = load_module(cfg.ckpt_path)
    camera = load_camera(cfg.camera)
    predictors: dict[tuple[int, int], DistancePredictor] = {}
    wanted = ["_distance.npy", "_distance.png", "_colour.png"] + (["_z.npy"] if cfg.z_depth else [])
    wanted += [".ply"] if cfg.point_cloud else []
    frames = list(_frames(source))
    if not cfg.overwrite:
        clash = next(
            (out / f"{name}{s}" for name, _, _ in frames for s in wanted if (out / f"{name}{s}").exists()),
            None,
        )
        if clash is not None:
            raise FileExistsError(f"{clash} exists; pass overwrite=true to replace outputs")
    out.mkdir(parents=True, exist_ok=True)
    bad: list[str] = []
    done, t0 = 0, time.perf_counter()
    batch: list[tuple[str, np.ndarray]] = []

    def flush():
        nonlocal done
        if not batch:
            return
        h, w = batch[0][1].shape[:2]
        cam = camera if (w, h) == (camera.width, camera.height) else camera.resize(w, h)
        if (w, h) not in predictors:
            predictors[(w, h)] = DistancePredictor(module, cam, cfg.get("size"), cfg.get("device", "cpu"))
        rgb = np.stack([im[..., ::-1] for _, im in batch])
        images = torch.from_numpy(rgb.copy()).permute(0, 3, 1, 2).float() / 255.0
        distance = predictors[(w, h)](images).cpu()
        for (name, _), d, colour in zip(batch, distance[:, 0], rgb, strict=True):
            d_np = d.numpy().astype(np.float32)
            np.save(out / f"{name}_distance.npy", d_np)
            cv2.imwrite(str(out / f"{name}_distance.png"), distance_png(d_np, cfg.png_scale))
            vis = colour_bar(colourise(d_np, cfg.vmin, cfg.vmax), cfg.vmin, cfg.vmax)
            cv2.imwrite(str(out / f"{name}_colour.png"), vis[..., ::-1])
            if cfg.z_depth:
                rays, _ = module.rays.get(cam)
                np.save(out / f"{name}_z.npy", (d * rays[..., 2]).numpy().astype(np.float32))
            if cfg.point_cloud:
                write_ply(out / f"{name}.ply", *point_cloud(d, cam, colour, module.rays))
            done += 1
        batch.clear()

    for name, image, path in tqdm(frames, desc="predicting", unit="frame"):
        if image is None:
            bad.append(str(path))
            log.warning("%s: unreadable image, skipped", path)
            continue
        if batch and image.shape != batch[0][1].shape:
            flush()
        batch.append((name, image))
        if len(batch) >= cfg.batch_size:
            flush()
    flush()
    seconds = time.perf_counter() - t0
    summary = {
        "frames": done,
        "skipped": len(bad),
        "unreadable": bad,
        "seconds": round(seconds, 3),
        "fps": round(done / seconds, 2) if seconds > 0 else None,
        "output": str(out),
        "png_scale": f"uint16 = metres * {int(1000 if cfg.png_scale == 'mm' else 256)}",
    }
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    Console(width=130).print(
        f"{done} frames in {seconds:.1f} s ({summary['fps']} fps), {len(bad)} unreadable "
        f"skipped{': ' + ', '.join(bad[:5]) if bad else ''}; outputs in {out}"
    )
    return summary


def predict_cli() -> None:
    """Console script ``fisheyedepth-predict`` (the same as ``python predict.py``)."""
    import hydra

    hydra.main(config_path="../../conf", config_name="predict", version_base="1.3")(predict)()


# ----------------------------------------------------------------------------------------------- export
def export(cfg: DictConfig) -> dict[str, Any]:
    from .cameras import load_camera
    from .inference import DistancePredictor

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
    suffix = {"onnx": ".onnx", "torchscript": ".pt"}[cfg.format]
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
