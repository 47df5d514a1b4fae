#!/usr/bin/env python
"""Deployment speed and accuracy, every runtime side by side in one run (BENCHMARKS.md "Inference").

Speed: frames per second of the full network (ResNet-18, 64-bin head), batch 1, at ``--size``, in
interleaved rounds on the same input. Rows: today's PyTorch path before this benchmark's levers (NCHW,
the softmax expectation written out, as it ran until the fused expectation), then each lever: the fused
expectation with channels_last, bf16 autocast, ONNX Runtime float32 (the old graph and the fused one),
and static int8. Goal: >= 10 fps at 384x384 on 2 threads. Then the EfficientNet-Lite0 models as files,
float32 and int8 side by side: ``make train``'s (``--effnet-ckpt``) and the released weights
(``--mobile-ckpt``, default ``weights/``); for each model, its int8 file against its own float32 file:
the export's parity check (median relative difference on held-out calibration images, limit 3 %) and
the speed-up (goal >= 2x).

Accuracy (``--ckpt`` and ``--data``): each path made from that checkpoint at its training size, scored on
the ``--split`` split of ``--data`` (full range, unscaled). Goal: abs_rel at most 0.01 above float32.

An untrained network is the one ``model=fisheyedepth`` (or ``model=fisheyedepth_lite``) configures, with
``base_focal`` unset: no training cameras to take it from. ``--data`` is read as ``data=synthetic``
reads its dataset (a KITTI-360-layout folder with split files).

Usage: python scripts/bench/bench_inference.py [--size 384] [--threads 2] [--rounds 20]
           [--ckpt CKPT --data DATASET [--split test]] [--effnet-ckpt CKPT] [--mobile-ckpt CKPT]
           [--calibration DIR] [--no-write] [--quick]
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from fisheyedepth.checkpoints import released_checkpoint
from fisheyedepth.evaluation import evaluate
from fisheyedepth.inference import ExportableNet
from fisheyedepth.models.heads import at_least_float32, distance_to_sigmoid
from fisheyedepth.module import FisheyeDepthModule
from fisheyedepth.runtimes import (
    OnnxRuntime,
    TorchRuntime,
    TrainedDepthNet,
    calibration_split,
    onnx_export,
    onnx_session,
)

from _benchmarks import WORLD, bench_parser, interleaved, markers, parse_args, publish
from _compose import build_datamodule, build_module, compose_config

START, END = markers("bench_inference")
MODELS = {  # conf/model/
    "full": ["model=fisheyedepth"],
    "lite": ["model=fisheyedepth_lite"],
    "effnet": ["model=fisheyedepth_effnet"],
}
DATA = ["data=synthetic"]  # conf/data/: the --data folder is read as the synthetic world is
FULL_FP32, FULL_INT8 = "ONNX Runtime float32, fused graph", "ONNX Runtime int8 (bin expectation float32)"
MOBILE_INT8 = "mobile (released weights): ONNX Runtime int8"
# Each model's float32 and int8 files, measured side by side: model -> (float32 row, int8 row)
PAIRS = {
    "full (ResNet-18)": (FULL_FP32, FULL_INT8),
    "effnet (`make train`)": (
        "effnet (`make train`): ONNX Runtime float32",
        "effnet (`make train`): ONNX Runtime int8",
    ),
    "mobile (released weights)": ("mobile (released weights): ONNX Runtime float32", MOBILE_INT8),
}
BLOCK = 3  # timed frames per runner and round: a deployment runs one runtime frame after frame
DEFAULT_CALIBRATION = WORLD / "data_2d_raw"


def softmax_expectation(logits, depth_scale, bins, min_distance, max_distance):
    """The bin expectation as it ran before the fused one: softmax, product with the bins, sum."""
    with torch.autocast(logits.device.type, enabled=False):
        logits = at_least_float32(logits)
        p = torch.softmax(logits.clamp(-10.0, 10.0), dim=1)
        d = (p * bins.to(logits)[None, :, None, None]).sum(1, keepdim=True)
        scale = torch.as_tensor(depth_scale, dtype=d.dtype, device=d.device).reshape(-1, 1, 1, 1)
        return d * scale, distance_to_sigmoid(d, min_distance, max_distance)


def load(ckpt: str | None, variant: str = "full") -> FisheyeDepthModule:
    """A trained module, or an untrained one (speed only) as ``model=fisheyedepth`` configures it;
    ``variant``: the key of :data:`MODELS` (``lite``: ``model=fisheyedepth_lite``, ...)."""
    torch.manual_seed(0)
    if ckpt:
        return FisheyeDepthModule.from_checkpoint(ckpt)
    return build_module(compose_config(MODELS[variant]), base_focal=None)


def old_path(module: FisheyeDepthModule) -> ExportableNet:
    """Today's path before the levers: NCHW weights, the softmax expectation."""
    net = module.depth_net
    net.expectation, net.channels_last = softmax_expectation, False
    net.to(memory_format=torch.contiguous_format)
    return ExportableNet(net).eval()


def calibration_set(folder: Path | None, size: tuple[int, int], count: int = 32) -> list[np.ndarray]:
    return calibration_and_probes(folder, size, count)[0]


def calibration_and_probes(
    folder: Path | None, size: tuple[int, int], count: int = 32
) -> tuple[list[np.ndarray], np.ndarray]:
    """The int8 ranges' images and the held-out probes, as ``export.py`` reads them from ``folder``."""
    if folder is not None and folder.is_dir():
        return calibration_split(folder, size, count)
    print(f"(no calibration folder {folder}: int8 ranges from random images, its accuracy is not meaningful)")
    gen = np.random.default_rng(0)
    images = [gen.random((1, 3, size[1], size[0]), dtype=np.float32) for _ in range(count + 4)]
    return images[:count], np.concatenate(images[count:])


def trained_or_untrained(ckpt: str | None, variant: str):
    """The distance network of ``ckpt`` (read as export.py reads it), or an untrained one of ``variant``."""
    if ckpt:
        return TrainedDepthNet.from_checkpoint(ckpt)
    return load(None, variant)


def int8_parity(net: ExportableNet, int8: bytes, probes: np.ndarray, threads: int) -> float:
    """The export's parity statistic of an int8 file: the median relative difference of its distance
    from PyTorch's on the held-out probes (``cli/export.py``: ``PARITY``, at most 3 %)."""
    session = onnx_session(int8, threads)
    with torch.no_grad():
        ref = net(torch.from_numpy(probes))
    got = torch.from_numpy(np.concatenate([session.run(None, {"image": p[None]})[0] for p in probes]))
    return float(((got - ref).abs() / ref.abs().clamp_min(1e-6)).median())


def basic_session(data: bytes, threads: int):
    """The session of :func:`onnx_session` with only ONNX Runtime's basic graph optimisations."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_BASIC
    opts.intra_op_num_threads, opts.inter_op_num_threads = threads, 1
    return ort.InferenceSession(data, opts, providers=["CPUExecutionProvider"])


def speed(args) -> tuple[dict[str, float], dict[str, str], dict[str, float]]:
    size = (args.size, args.size)
    x = torch.rand(1, 3, args.size, args.size)
    calibration, probes = calibration_and_probes(args.calibration, size)
    old = old_path(load(args.ckpt))
    fused = TorchRuntime(load(args.ckpt))  # fused expectation, channels_last
    net = ExportableNet(fused.module.depth_net).eval()
    focal = fused.module.depth_net.base_focal
    runners, notes = {}, {}
    runners["PyTorch eager, before (NCHW, softmax expectation)"] = lambda: old(x)
    notes["PyTorch eager, before (NCHW, softmax expectation)"] = (
        "today's `predict.py` path before this change"
    )
    runners["PyTorch eager, fused expectation + channels_last"] = lambda: net(x)
    notes["PyTorch eager, fused expectation + channels_last"] = "`predict.py` (float32, the same numbers)"

    def bf16():
        with torch.autocast("cpu", dtype=torch.bfloat16):
            return net(x)

    runners["PyTorch eager, + bf16 autocast"] = bf16
    notes["PyTorch eager, + bf16 autocast"] = "`predict.py precision=bf16`"
    feed = {"image": x.numpy()}
    lite = ExportableNet(TorchRuntime(load(args.lite_ckpt, "lite")).module.depth_net).eval()
    fused_graph = onnx_export(net, size, focal)  # one file, two sessions
    sessions = {
        "ONNX Runtime float32, before (softmax graph)": (onnx_export(old, size, focal), "today's export"),
        "ONNX Runtime float32, fused graph, basic graph optimisations": (
            fused_graph,
            "ORT's `ORT_ENABLE_BASIC` (no layout or conv-activation fusions)",
        ),
        FULL_FP32: (fused_graph, "`export.py` + `runtime=onnx`"),
        FULL_INT8: (
            onnx_export(net, size, focal, "int8", calibration),
            "`export.py quantize=int8` + `runtime=onnx`",
        ),
        "lite: ONNX Runtime float32": (onnx_export(lite, size, focal), "`model=fisheyedepth_lite`, exported"),
        "lite: ONNX Runtime int8": (
            onnx_export(lite, size, focal, "int8", calibration),
            "`model=fisheyedepth_lite`, `quantize=int8`",
        ),
    }
    parity = {"full (ResNet-18)": int8_parity(net, sessions[FULL_INT8][0], probes, args.threads)}
    effnet = trained_or_untrained(args.effnet_ckpt, "effnet")
    mobile = TrainedDepthNet.from_checkpoint(args.mobile_ckpt or released_checkpoint())
    described = {
        "effnet (`make train`)": (effnet, "`model=fisheyedepth_effnet` (EfficientNet-Lite0)"),
        "mobile (released weights)": (mobile, "`model=fisheyedepth_mobile` (a quarter of the decoder)"),
    }
    for model, (module, what) in described.items():
        exportable = ExportableNet(TorchRuntime(module).module.depth_net).eval()
        base = module.depth_net.base_focal
        fp32_row, int8_row = PAIRS[model]
        sessions[fp32_row] = (onnx_export(exportable, size, base), what)
        sessions[int8_row] = (onnx_export(exportable, size, base, "int8", calibration), "`quantize=int8`")
        parity[model] = int8_parity(exportable, sessions[int8_row][0], probes, args.threads)
    for name, (data, note) in sessions.items():
        basic = "basic graph" in name
        session = basic_session(data, args.threads) if basic else onnx_session(data, args.threads)
        runners[name] = lambda s=session: s.run(None, feed)
        notes[name] = note
    with torch.no_grad():
        # each round: every runner in turn, one untimed frame (the previous runner's idle threads
        # settle), then a block of BLOCK frames
        times = interleaved(runners, args.rounds, warmup=3, repeat=BLOCK, settle=True)
    return {name: statistics.median(ts) for name, ts in times.items()}, notes, parity


def accuracy(ckpt: str, args, tmp: Path) -> dict[str, dict[str, float]]:
    """Each path made from ``ckpt`` at its training size, on the ``--split`` split of ``--data``."""
    module = load(ckpt)
    size = tuple(module.hparams["input_size"])
    values = {"data.datamodule.root": args.data, "data.datamodule.cache_dir": tmp / "cache"}
    dm = build_datamodule(compose_config(DATA, values))
    calibration = calibration_set(args.calibration, size)
    net = ExportableNet(TorchRuntime(module).module.depth_net).eval()
    paths = {"PyTorch float32": TorchRuntime(load(ckpt))}
    paths["PyTorch bf16"] = TorchRuntime(load(ckpt), precision="bf16")
    for name, quantize in (("ONNX Runtime float32", None), ("ONNX Runtime int8", "int8")):
        path = tmp / f"{quantize or 'fp32'}.onnx"
        path.write_bytes(onnx_export(net, size, module.depth_net.base_focal, quantize, calibration))
        paths[name] = OnnxRuntime(path, args.threads)
    out = {}
    for name, runtime in paths.items():
        res = evaluate(runtime, dm.scoring_loader(args.split), size, ["full"], ("none",))
        out[name] = res["full"]["none"]
    return out


def main(argv=None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--size", type=int, default=384)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=20)
    parser.add_argument("--ckpt", help="a trained checkpoint (default: an untrained network, for speed only)")
    parser.add_argument("--lite-ckpt", help="a trained model=fisheyedepth_lite checkpoint (its own rows)")
    parser.add_argument(
        "--effnet-ckpt", help="make train's checkpoint (model=fisheyedepth_effnet; default: untrained)"
    )
    parser.add_argument("--mobile-ckpt", help="a model=fisheyedepth_mobile checkpoint (default: weights/)")
    parser.add_argument("--data", help="a dataset with ground truth: score every path on its --split")
    parser.add_argument("--split", default="test")
    parser.add_argument(
        "--calibration", type=Path, default=DEFAULT_CALIBRATION, help="training images for int8"
    )
    args = parse_args(parser, argv, quick={"size": 64, "rounds": 1})
    if args.data and not (args.ckpt or args.lite_ckpt or args.effnet_ckpt):
        parser.error("--data needs --ckpt, --lite-ckpt or --effnet-ckpt (accuracy is a trained network's)")
    torch.set_num_threads(args.threads)
    medians, notes, parity = speed(args)
    base = medians["PyTorch eager, before (NCHW, softmax expectation)"]
    command = "python scripts/bench/bench_inference.py"
    command += f" --size {args.size} --threads {args.threads} --rounds {args.rounds}"
    if args.ckpt:
        command += f" --ckpt {args.ckpt}"
    for flag, value in (("--lite-ckpt", args.lite_ckpt), ("--effnet-ckpt", args.effnet_ckpt),
                        ("--mobile-ckpt", args.mobile_ckpt)):  # fmt: skip
        if value:
            command += f" {flag} {value}"
    if args.data:
        command += f" --data {args.data} --split {args.split}"
    lines = [
        START,
        "## Inference (`scripts/bench/bench_inference.py`)",
        "",
        f"Command: `{command}`  ",
        f"Machine: {os.cpu_count()} CPUs ({platform.machine()}), torch {torch.__version__}, "
        f"{args.threads} threads; {time.strftime('%Y-%m-%d')}. Full model (ResNet-18, 64-bin head), batch 1, "
        f"{args.size}x{args.size}, median over {args.rounds} interleaved rounds "
        f"({BLOCK} frames per runtime each).",
        "",
        "| runtime | what runs it | ms / frame | fps | speed-up | goal >= 10 fps |",
        "|---|---|---|---|---|---|",
    ]
    for name, med in medians.items():
        lines.append(
            f"| {name} | {notes[name]} | {med * 1e3:.1f} | {1 / med:.1f} | {base / med:.2f}x | "
            f"{'met' if 1 / med >= 10 else 'NOT met'} |"
        )
    lines += [
        "",
        "Each model's int8 file against its own float32 file (the rows above): the export's parity check "
        f"(median relative difference from PyTorch on 4 held-out calibration images at {args.size}x"
        f"{args.size}, limit 3 %) and the speed-up.",
        "",
        "| model | checkpoint | int8 median relative difference | parity | int8 speed-up | goal >= 2x |",
        "|---|---|---|---|---|---|",
    ]
    checkpoints = {
        "full (ResNet-18)": args.ckpt,
        "effnet (`make train`)": args.effnet_ckpt,
        "mobile (released weights)": args.mobile_ckpt or "`weights/`",
    }
    for model, (fp32_row, int8_row) in PAIRS.items():
        gain, passes = medians[fp32_row] / medians[int8_row], parity[model] <= 0.03
        lines.append(
            f"| {model} | {checkpoints[model] or 'untrained'} | {100 * parity[model]:.2f} % | "
            f"{'passes' if passes else 'FAILS'} | {gain:.2f}x | {'met' if gain >= 2 else 'NOT met'} |"
        )
    ratio = medians[FULL_INT8] / medians[MOBILE_INT8]
    lines += [
        "",
        f"The mobile model's int8 export against the full model's, side by side: **{ratio:.2f}x** "
        f"(goal >= 2x: {'met' if ratio >= 2 else 'NOT met'}).",
    ]
    if args.data:
        import tempfile

        lines += [
            "",
            f"Accuracy of each path made from a checkpoint, at its training size, on `{args.data}` "
            f"({args.split} split, full range, no scaling). Goal: abs_rel at most 0.01 above its float32.",
            "",
            "| model | path | abs_rel | a1 | rmse (m) | abs_rel - float32 | goal |",
            "|---|---|---|---|---|---|---|",
        ]
        for label, ckpt in (("full", args.ckpt), ("lite", args.lite_ckpt), ("effnet", args.effnet_ckpt)):
            if not ckpt:
                continue
            with tempfile.TemporaryDirectory() as tmp:
                scores = accuracy(ckpt, args, Path(tmp))
            ref = scores["PyTorch float32"]["abs_rel"]
            for name, m in scores.items():
                delta = m["abs_rel"] - ref
                lines.append(
                    f"| {label} | {name} | {m['abs_rel']:.4f} | {m['a1']:.4f} | {m['rmse']:.3f} | "
                    f"{delta:+.4f} | {'met' if delta <= 0.01 else 'NOT met'} |"
                )
    lines.append(END)
    publish("\n".join(lines) + "\n", args.output, START, END, write=not args.no_write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
