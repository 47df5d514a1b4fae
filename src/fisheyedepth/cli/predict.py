"""``python predict.py ckpt_path=... input=DIR_OR_VIDEO_OR_CAMERA camera=CALIB``: metric distance for every
frame, written as it comes, beside a ``summary.json``; unreadable frames are skipped and listed, nothing is
overwritten. ``runtime=onnx model=FILE.onnx`` runs an exported file (float32 or int8) instead of a
checkpoint; ``precision=bf16`` runs a checkpoint in bf16."""

from __future__ import annotations

import json
import logging
import sys
import time
from typing import Any

from omegaconf import DictConfig
from rich.console import Console
from tqdm import tqdm

from ..cameras import load_camera
from ..files import atomic_write_text
from ..images import FrameSource
from ..inference import FramePrediction, PredictionWriter, frame_recording
from ..options.defaults import CONF_DIR
from ..options.kinds import SWITCH
from ..plan import predict_plan
from ..rerun3d import RecordingError
from ..runtimes import OnnxRuntime
from ..signals import Terminated, signal_name, stopped_by
from . import free_path, load_runtime, model_file_alias, run_command

log = logging.getLogger("fisheyedepth")
RECORDING = "recording.rrd"  # rerun=true: the run's Rerun recording in the output folder


class RecordingFailed(ValueError):
    """``rerun=true``'s recording could not be written; the frames' outputs and summary.json are kept."""


def predict(cfg: DictConfig) -> dict[str, Any]:
    plan = predict_plan(cfg)  # the output folder writable, the runtime's options: nothing loaded yet
    out = plan.output
    writer = PredictionWriter(out, plan.z_depth, plan.point_cloud, plan.png_scale, plan.vmin, plan.vmax,
                              plan.overwrite)  # fmt: skip
    source = FrameSource(plan.input, plan.max_frames)  # lists the inputs without decoding any
    writer.check_free(source.names())
    SWITCH.check("rerun", rerun := cfg.get("rerun", False))
    recorded, bag_out = out / RECORDING if rerun else None, cfg.get("bag_out")
    summary, failed, stop = None, None, None
    try:
        with frame_recording(recorded, source, plan.overwrite, bag_out) as recording:  # refused if it exists
            runtime = load_runtime(plan.runtime)
            batch_size = 1 if source.live else int(plan.batch_size)  # a live frame is written as it comes
            run = FramePrediction(
                runtime, load_camera(plan.camera), plan.camera, writer, batch_size, recording
            )
            summary, stop = predict_frames(source, run, runtime, plan)
        failed = run.recording_error  # it stopped mid-run (and was discarded there)
    except RecordingError as err:  # closing it: the frames' own outputs are whole, the recording is not
        if summary is None:
            raise
        failed = str(err)
    if recorded is not None:
        summary["recording"] = None if failed else str(recorded)
        summary["recording_error"] = failed
    summary["bag_out"] = None if bag_out is None else str(bag_out)
    summary_path = out / "summary.json" if plan.overwrite else free_path(out / "summary.json")
    atomic_write_text(summary_path, json.dumps(summary, indent=2) + "\n")
    if failed:  # one line, exit 2: the frames predicted and their summary are kept, no recording
        raise RecordingFailed(
            f"{failed}; the {summary['frames']} frames predicted are in {out} ({summary_path.name})"
        )
    if stop is not None:  # one line, exit 130 / 143: what was predicted is kept
        why, status = stopped_by(stop)
        kept = f"{summary['frames']} frames; their outputs and {summary_path.name} are in {out}"
        print(f"error: {why} after {kept}", file=sys.stderr)
        raise SystemExit(status)
    unreadable, grey = summary["unreadable"], summary["grayscale"]
    Console(width=130).print(
        f"{summary['frames']} frames in {summary['seconds']:.1f} s ({summary['fps']} fps), {len(unreadable)} "
        f"unreadable skipped{': ' + ', '.join(unreadable[:5]) if unreadable else ''}"
        f"{f', {len(grey)} grayscale' if grey else ''}; outputs in {out} ({summary_path.name}"
        f"{', ' + RECORDING if recorded is not None else ''})"
    )
    return summary


def predict_frames(
    source: FrameSource, run: FramePrediction, runtime, plan
) -> tuple[dict, BaseException | None]:
    """Every frame of ``source`` through ``run``: the summary, and the signal that stopped it or None."""
    out = plan.output
    unreadable: list[str] = []
    grayscale: list[str] = []
    t0 = time.perf_counter()
    interrupted: BaseException | None = None
    try:
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
            run.add(frame)
    except (KeyboardInterrupt, Terminated) as stop:  # a live camera ends with Ctrl-C: what was
        interrupted = stop  # predicted is kept and summarised, then the command exits 130 / 143
    run.flush()
    done, seconds = run.written, time.perf_counter() - t0
    summary = {
        "input": str(source.source),
        "frames": done,
        "skipped": len(unreadable),
        "unreadable": unreadable,
        "grayscale": grayscale,
        "runtime": runtime_name(runtime),
        "input_size": list(runtime.input_size) if runtime.input_size else None,
        "post_process": runtime.post_process,
        "interrupted": signal_name(interrupted),  # the signal that stopped it, or null
        "seconds": round(seconds, 3),
        "fps": round(done / seconds, 2) if seconds > 0 else None,
        "output": str(out),
        "png_scale": f"uint16 = metres * {int(1000 if plan.png_scale == 'mm' else 256)}, 0 = no ray",
    }
    if done == 0 and interrupted is not None:
        raise interrupted  # before any frame: nothing to keep (run_command's one line)
    if done == 0:
        raise ValueError(f"{source.source}: no frame could be read ({len(unreadable)} unreadable)")
    return summary, interrupted


def runtime_name(runtime) -> str:
    if isinstance(runtime, OnnxRuntime):
        return f"onnx ({'int8' if runtime.quantize == 'int8' else 'float32'}): {runtime.path}"
    return f"torch ({runtime.precision})"


def main() -> None:
    """Console script ``fisheyedepth-predict`` (the same as ``python predict.py``, from a source checkout:
    the configs live in its ``conf/``, found by absolute path since a relative one would be read as a
    Python module's)."""
    import hydra

    sys.argv = model_file_alias(sys.argv)  # model=FILE.onnx (runtime=onnx)
    hydra.main(config_path=str(CONF_DIR), config_name="predict", version_base="1.3")(
        lambda cfg: run_command(predict, cfg)
    )()
