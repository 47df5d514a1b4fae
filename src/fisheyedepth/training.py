"""What a training step needs beyond the model and its loss: a step that no rank can take is skipped by
every rank together (:class:`StepGuard`, which also clips the gradients it has measured), and the
optimiser and learning-rate schedule built from their configs (:func:`build_optimizer`,
:func:`build_scheduler`: ``{"_target_": ..., "_partial_": true, **options}``, as in
``conf/model/optimizer`` and ``conf/model/scheduler``), and checkpoints that a kill never leaves half
written (:class:`AtomicCheckpointIO`)."""

from __future__ import annotations

import inspect
import warnings
from typing import Any

import lightning as L
import torch
from hydra.utils import get_class
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from torch import Tensor

from .checkpoints import write_checkpoint


def any_rank(flag: bool, device: torch.device) -> bool:
    """``flag`` on any process of a distributed run (every rank must call this at the same point);
    the flag itself when there is one process."""
    if not (torch.distributed.is_available() and torch.distributed.is_initialized()):
        return flag
    if torch.distributed.get_world_size() == 1:
        return flag
    value = torch.tensor([1.0 if flag else 0.0], device=device)
    torch.distributed.all_reduce(value, op=torch.distributed.ReduceOp.MAX)
    return bool(value.item() > 0)


class StepGuard:
    """Skips, on every rank together, a step that any rank cannot take: an unreadable batch before the
    forward pass, a non-finite loss after it, non-finite gradients before the optimiser. BatchNorm's
    running statistics go back to what they were before the forward pass, the skip is counted
    (:attr:`skipped`), warned about and logged as ``train/skipped_batches``.

    The module calls :meth:`keep_statistics` before its forward pass, :meth:`skip` and returns
    :meth:`skip_loss` from a step it skips, :meth:`check_gradients` in ``on_before_optimizer_step`` and
    :meth:`clip` in ``configure_gradient_clipping``."""

    def __init__(self, module: L.LightningModule):
        self.module = module
        self.skipped = 0
        self._statistics: dict[str, Tensor] = {}
        self._dropping = False  # the step was skipped: drop its gradients before the optimiser
        self.grad_norm: Tensor | None = None  # this step's gradient norm, for the clipping

    def any_rank(self, flag: bool) -> bool:
        return any_rank(flag, self.module.device)

    def keep_statistics(self) -> None:
        """Keep BatchNorm's running statistics, so that a non-finite batch does not poison them."""
        self._statistics = {name: b.clone() for name, b in self.module.named_buffers() if "running_" in name}

    def skip(self, why: str, batch_idx: int, batch_size: int) -> None:
        """Every rank skips this step together: BatchNorm restored, the skip counted and logged."""
        with torch.no_grad():
            for name, b in self.module.named_buffers():
                if name in self._statistics:
                    b.copy_(self._statistics[name])
        self.skipped += 1
        step = self.module.global_step
        warnings.warn(f"{why} at step {step} (batch {batch_idx}): step skipped", stacklevel=3)
        self.module.log("train/skipped_batches", float(self.skipped), batch_size=max(batch_size, 1))

    def skip_loss(self) -> Tensor:
        """What a skipped step returns: a zero loss on every parameter. Under DDP every rank must run
        the backward pass and its gradient all-reduce (Lightning refuses ``None`` there, and a rank
        left alone in a collective would wait forever); the zero gradients are then dropped before the
        optimiser (:meth:`check_gradients`), so nothing moves, Adam's moments included."""
        self._dropping = True
        return sum(p.sum() for p in self.module.parameters()) * 0.0

    def check_gradients(self) -> None:
        """Non-finite gradients after a finite loss: every rank drops them (a parameter without a
        gradient is left alone by the optimiser, its moments included) and restores BatchNorm. A step
        already skipped drops its zero gradients here."""
        params = list(self.module.parameters())
        if self._dropping:  # every rank agreed on it in the training step
            self._dropping = False
            for p in params:
                p.grad = None
            return
        grads = [p.grad for p in params if p.grad is not None]
        # one norm over every gradient (foreach kernels, ~4x cheaper than a finiteness test per tensor):
        # non-finite when any element is, or when the sum of squares overflows float32 (no usable step);
        # gradient clipping reuses it
        self.grad_norm = torch.nn.utils.get_total_norm(grads) if grads else None
        finite = self.grad_norm is None or bool(torch.isfinite(self.grad_norm))  # one sync
        if self.any_rank(not finite):
            for p in params:
                p.grad = None
            self.skip("non-finite gradients on a rank", -1, 0)

    def clip(self, optimizer, value: float | None, algorithm: str | None) -> None:
        """``trainer.gradient_clip_val`` by the norm of every gradient (the one :meth:`check_gradients`
        took) or by value. Done here rather than by Lightning's precision plugin, which refuses to clip
        for a fused optimiser under any mixed precision: its gradients are already unscaled here (bf16
        has no scaler; with float16's scaler the optimiser is not fused)."""
        norm, self.grad_norm = self.grad_norm, None
        if not value:
            return
        params = [p for group in optimizer.param_groups for p in group["params"] if p.grad is not None]
        if not params:
            return  # a skipped step: its gradients were dropped
        if algorithm in (None, "norm"):
            if norm is None:
                norm = torch.nn.utils.get_total_norm([p.grad for p in params])
            torch.nn.utils.clip_grads_with_norm_(params, value, norm)
        elif algorithm == "value":
            torch.nn.utils.clip_grad_value_(params, value)
        else:
            raise ValueError(f"gradient_clip_algorithm={algorithm!r}: expected norm or value")


def _call(config: dict[str, Any], *args: Any, **kwargs: Any) -> Any:
    """``config["_target_"]`` called with ``args``, the config's options and ``kwargs``."""
    options = {k: v for k, v in config.items() if not k.startswith("_")}
    return get_class(config["_target_"])(*args, **options, **kwargs)


def build_optimizer(config: dict[str, Any], params: list[Tensor], scaler: bool) -> torch.optim.Optimizer:
    """The configured optimiser over ``params``; one that takes ``fused`` gets the fused kernel (one pass
    per step on CPU and CUDA; 3x faster than foreach on 2 CPU cores, BENCHMARKS.md "Training loop")
    where every parameter lives on a device that has it, except under float16 mixed precision
    (``scaler``), whose gradient scaler then unscales inside the step."""
    extra = {}
    if "fused" in inspect.signature(get_class(config["_target_"])).parameters and "fused" not in config:
        fused = not scaler and all(
            p.device.type in ("cpu", "cuda") and p.dtype.is_floating_point for p in params
        )
        extra["fused"] = fused or None
    return _call(config, params, **extra)


def build_scheduler(config: dict[str, Any], optimizer: torch.optim.Optimizer):
    """The configured learning-rate schedule of ``optimizer`` (stepped once per epoch)."""
    return _call(config, optimizer)


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning's checkpoint writer through :func:`~fisheyedepth.checkpoints.write_checkpoint`: beside
    the target, then renamed over it. Lightning's own saves through an fsspec transaction: a temporary
    file in the system temp folder, moved over the target at the end."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options: Any | None = None) -> None:
        if storage_options is not None:
            raise TypeError(f"{type(self).__name__} takes no storage_options")
        write_checkpoint(checkpoint, path)


__all__ = ["AtomicCheckpointIO", "StepGuard", "any_rank", "build_optimizer", "build_scheduler"]
