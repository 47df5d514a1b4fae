#!/usr/bin/env python
"""The training loop's step as ``train.py`` runs it (Lightning, the data loader's worker on the same cores,
gradient clipping, the non-finite-gradient check, Adam), before and after the trims outside the network;
results go into BENCHMARKS.md.

``scripts/bench/bench_training.py`` times forward, loss, backward and a plain Adam step on one batch; a real
training step also waits for the loader (whose worker shares the 2 cores), checks the gradients, clips
them and logs. Each measurement here is a fresh ``train.py +experiment=cpu_30min`` process (world 0 of
``make train``, rendered on first use) that trains ``--steps`` steps of one epoch and reports the median
cycle (one batch start to the next: the loader's wait plus the step) after ``--warmup`` steps. The
"before" process puts back, in itself only, the paths the trims replaced:

- Adam with the per-tensor (foreach) kernel instead of the fused one;
- the finiteness test of every gradient tensor instead of one norm over all of them, and Lightning's
  gradient clipping, which takes the norm again, instead of the module's, which reuses it;
- the colour jitter as its chain of eight operations instead of one affine map.

The two kinds alternate for ``--rounds`` rounds (the order swapped every round); the speed-up is the
median of the paired per-round ratios.

Usage: python scripts/bench/bench_fit.py [--rounds 3] [--steps 60] [--warmup 15] [--no-write] [--quick]
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import platform
import runpy
import statistics
import sys
import tempfile
import time
from pathlib import Path

from _benchmarks import (
    ROOT,
    WORLD,
    alternate,
    bench_parser,
    child_result,
    markers,
    paired_ratio,
    parse_args,
    publish,
    require_world,
    run_child,
)

START, END = markers("bench_fit")
KINDS = ("before the trims", "after the trims")


def chain_jitter(images, brightness, contrast, saturation, hue, generator=None):
    """The colour jitter as it was: one operation after another (the same numbers as the one map)."""
    import torch

    def draw(spread: float) -> float:
        return 1.0 + (2 * torch.rand((), generator=generator).item() - 1) * spread

    w = torch.tensor([0.299, 0.587, 0.114]).to(images)[:, None, None]
    out = images * draw(brightness)
    grey = (out * w).sum(-3, keepdim=True)
    out = grey.mean((-2, -1), keepdim=True) + draw(contrast) * (out - grey.mean((-2, -1), keepdim=True))
    grey = (out * w).sum(-3, keepdim=True)
    out = grey + draw(saturation) * (out - grey)
    if hue:
        angle = (2 * torch.rand((), generator=generator).item() - 1) * hue * 2 * math.pi
        yiq = torch.tensor([[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]])
        c, s = math.cos(angle), math.sin(angle)
        rot = torch.tensor([[1.0, 0, 0], [0, c, -s], [0, s, c]])
        m = (torch.linalg.inv(yiq) @ rot @ yiq).to(out)
        out = torch.einsum("ij,...jhw->...ihw", m, out)
    return out.clamp(0, 1)


def restore_before() -> None:
    """Put back the three paths the trims replaced, in this process (and its forked loader worker)."""
    import lightning as L
    import torch

    import fisheyedepth.data.augment as augment
    from fisheyedepth.module import FisheyeDepthModule
    from fisheyedepth.training import StepGuard

    plain_adam = torch.optim.Adam

    class ForeachAdam(plain_adam):
        def __init__(self, params, **kwargs):
            kwargs.update(fused=None, foreach=True)
            super().__init__(params, **kwargs)

    torch.optim.Adam = ForeachAdam

    def per_tensor_check(self) -> None:  # the check as it was before the one-norm test
        params = list(self.module.parameters())
        if self._dropping:
            self._dropping = False
            for p in params:
                p.grad = None
            return
        grads = [p.grad for p in params if p.grad is not None]
        finite = not grads or bool(torch.stack([torch.isfinite(g).all() for g in grads]).all())
        if self.any_rank(not finite):
            for p in params:
                p.grad = None
            self.skip("non-finite gradients on a rank", -1, 0)

    StepGuard.check_gradients = per_tensor_check
    # and Lightning's clipping, which takes the gradients' norm again
    FisheyeDepthModule.configure_gradient_clipping = L.LightningModule.configure_gradient_clipping
    augment.colour_jitter = chain_jitter


def child(kind: str, steps: int, warmup: int, out_dir: Path) -> None:
    """One measurement: a ``train.py`` process that trains ``steps`` steps; prints JSON."""
    import lightning as L

    if kind == KINDS[0]:
        restore_before()
    cycles: list[float] = []

    class Cycle(L.Callback):
        last: float | None = None

        def on_train_batch_start(self, trainer, module, batch, batch_idx):
            now = time.perf_counter()
            if self.last is not None:
                cycles.append(now - self.last)
            self.last = now

    import fisheyedepth.cli.train as entry

    instantiate = entry.instantiate

    def with_cycle(config, *args, **kwargs):  # the trainer gets the timing callback too
        if "callbacks" in kwargs and str(config.get("_target_", "")).endswith("Trainer"):
            kwargs["callbacks"] = [*kwargs["callbacks"], Cycle()]
        return instantiate(config, *args, **kwargs)

    entry.instantiate = with_cycle
    sys.argv = [
        "train.py",
        "+experiment=cpu_30min",
        f"hydra.run.dir={out_dir}",
        "trainer.max_epochs=1",
        f"trainer.limit_train_batches={steps + 1}",
        "trainer.limit_val_batches=0",
        "trainer.num_sanity_val_steps=0",
        "test=false",
        "logger=none",
        "~callbacks.progress",
        f"paths.data_dir={WORLD.parent}",
    ]
    try:  # as ``python train.py``: Hydra finds conf/ beside the script
        runpy.run_path(str(ROOT / "train.py"), run_name="__main__")
    except SystemExit as exc:
        if exc.code:
            raise
    kept = cycles[warmup:]
    child_result({"cycle": statistics.median(kept), "steps": len(kept)})


def measure(kind: str, steps: int, warmup: int, tmp: Path, index: int) -> dict[str, float]:
    env = {"OMP_NUM_THREADS": "2", "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT)])}
    arguments = [kind, "--steps", steps, "--warmup", warmup, "--out", tmp / f"run{index}"]
    return run_child(__file__, arguments, env=env, cwd=ROOT)


def main(argv=None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--warmup", type=int, default=15)
    parser.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = parse_args(parser, argv, quick={"rounds": 1, "steps": 3, "warmup": 1})
    if args.child:
        child(args.child[0], args.steps, args.warmup, args.out)
        return 0
    if args.steps <= args.warmup:
        raise SystemExit(f"--steps {args.steps} must exceed --warmup {args.warmup}")
    require_world()
    with tempfile.TemporaryDirectory(prefix="fd-bench-fit-") as tmp:
        runs = itertools.count()  # each child writes its run into a folder of its own
        results = alternate(
            KINDS, args.rounds, lambda kind: measure(kind, args.steps, args.warmup, Path(tmp), next(runs))
        )
    ratio = paired_ratio(results[KINDS[0]], results[KINDS[1]], "cycle")
    lines = [
        START,
        "## Training loop (`scripts/bench/bench_fit.py`)",
        "",
        f"Command: `python scripts/bench/bench_fit.py --rounds {args.rounds} --steps {args.steps} "
        f"--warmup {args.warmup}`  ",
        f"Machine: {os.cpu_count()} CPUs ({platform.machine()}), 2 threads; {time.strftime('%Y-%m-%d')}. "
        f"`train.py +experiment=cpu_30min` (batch 4 at 256x256, two sources, the loader's worker on the "
        f"same cores), {args.steps} steps per fresh process, the median cycle after {args.warmup} "
        f"warm-up steps; the two kinds alternate for {args.rounds} rounds.",
        "",
        "| training loop | cycle per step (median of rounds) |",
        "|---|---|",
    ]
    for kind in KINDS:
        lines.append(f"| {kind} | {statistics.median(r['cycle'] for r in results[kind]):.3f} s |")
    lines += ["", f"Speed-up (median of the paired per-round ratios): **{ratio:.2f}x**.", END]
    publish("\n".join(lines) + "\n", args.output, START, END, write=not args.no_write)
    return 0


if __name__ == "__main__":
    sys.exit(main())
