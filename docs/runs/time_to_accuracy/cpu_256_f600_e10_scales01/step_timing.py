"""Row 36's step timing (BENCHMARKS.md, session 13): the full model's training step with every speed
lever (bf16 autocast, channels_last, native-resolution loss, compiled kernels), 256x256, batch 4, two
sources, with the loss at scales 0-3 against scales 0 and 1 only; interleaved rounds, paired ratio.

    python docs/runs/time_to_accuracy/cpu_256_f600_e10_scales01/step_timing.py DATASET_ROOT [ROUNDS]
"""

import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[4]
sys.path.insert(0, str(ROOT / "scripts"))
from bench_training import make_batch, step  # noqa: E402

from fisheyedepth.module import FisheyeDepthModule  # noqa: E402


def main() -> None:
    torch.set_num_threads(2)
    rounds = int(sys.argv[2]) if len(sys.argv) > 2 else 15
    with tempfile.TemporaryDirectory() as tmp:
        data = make_batch(Path(sys.argv[1]), 256, 4, Path(tmp) / "cache")
    runs = {}
    for name, scales in (("scales 0-3", (0, 1, 2, 3)), ("scales 0-1", (0, 1))):
        torch.manual_seed(0)
        module = FisheyeDepthModule(
            log_images_every=0,
            channels_last=True,
            loss_resolution="native",
            compile_kernels=True,
            scales=scales,
        )
        module.on_fit_start()
        runs[name] = (module, torch.optim.Adam(module.parameters(), lr=1e-4))
    for module, optimizer in runs.values():  # warm-up and compilation
        for _ in range(2):
            step(module, optimizer, data, bf16=True)
    times = {name: [] for name in runs}
    names = list(runs)
    for r in range(rounds):
        for name in names if r % 2 == 0 else names[::-1]:
            t0 = time.perf_counter()
            step(*runs[name], data, bf16=True)
            times[name].append(time.perf_counter() - t0)
    for name in names:
        print(f"{name}: {statistics.median(times[name]):.3f} s")
    ratio = statistics.median(a / b for a, b in zip(times[names[0]], times[names[1]], strict=True))
    print(f"step with scales 0-3 / with scales 0-1: {ratio:.3f}")


if __name__ == "__main__":
    main()
