"""``FisheyeDepthModule``: the LightningModule that trains a distance network with fisheye warps.

It holds the networks (``depth_net``, and ``pose_net`` without real-scale poses), the training objective
(:class:`~fisheyedepth.losses.objective.SelfSupervisedObjective`), the step guard
(:class:`~fisheyedepth.training.StepGuard`) and the Lightning lifecycle. Its options come in groups, as
in ``conf/model`` (:mod:`fisheyedepth.options`); a group given in part takes the defaults for the rest.
The paper's Table 2 switches:
``objective.fisheye_projection``, ``objective.real_scale`` and ``net.multi_channel`` (Monodepth2's single
sigmoid channel when off, instead of the binned head with attention).
"""

from __future__ import annotations

import functools
import os
import warnings
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch import Tensor

from .checkpoints import model_from_checkpoint
from .data.batch import Batch, SkippedBatch
from .files import atomic_write_png
from .losses.objective import SelfSupervisedObjective
from .losses.photometric import photometric_error
from .metrics import DepthMetrics
from .models import DepthNet, PoseNet, bin_expectation, bin_sums_reduced
from .models.cost_volume import Sources
from .models.depth_net import check_network_memory
from .models.posenet import MONODEPTH2_TRANSLATION_PER_DISTANCE
from .options.defaults import check_numbers, model_options, unknown_options
from .training import StepGuard, build_optimizer, build_scheduler
from .viz import panel


class FisheyeDepthModule(L.LightningModule):
    options = staticmethod(model_options)

    def __init__(self, **options: Any):
        """Keywords: the option groups ``net``, ``objective``, ``optimizer``, ``scheduler`` (dicts, each
        over the YAML's, :func:`~fisheyedepth.options.defaults.model_options`) and the module's own:
        ``eval_cap``: the validation metrics' ground-truth range (metres).
        ``input_size``: the (width, height) the network was trained at, kept in checkpoints for inference.
        ``compile_kernels``: while fitting, the bin expectation (its bin sums as channel reductions, which
        the compiler fuses with their backward) and the photometric error run as ``torch.compile``'d
        kernels (fused, the same numbers; compiled once per process, about a minute on 2 CPU cores);
        evaluation after fitting, prediction and export use the plain functions.
        ``log_images_every``: steps between the distance maps written to the logger (0: none)."""
        super().__init__()
        unknown = unknown_options(options)
        if unknown:
            raise TypeError(f"FisheyeDepthModule: unexpected {', '.join(unknown)}")
        hp = model_options(**options)
        check_numbers(hp)
        self.save_hyperparameters(hp)
        net, objective = dict(hp["net"]), dict(hp["objective"])
        check_network_memory(net, "net.")  # named in its group, before any weight is allocated
        self.depth_net = DepthNet(**net)
        translation = objective.pop("pose_translation_scale")
        if translation is None:  # Monodepth2's first parallax for this head's first distance
            translation = MONODEPTH2_TRANSLATION_PER_DISTANCE * self.depth_net.initial_distance
        self.pose_net = None
        if net["cost_volume"] and not objective["real_scale"]:
            raise ValueError(
                "net.cost_volume: the multi-view network matches over metric distance and needs real-scale "
                "poses (objective.real_scale: true)"
            )
        if not objective["real_scale"]:
            self.pose_net = PoseNet(
                resnet=net["resnet"], weights=net["weights"], translation_scale=translation,
                channels_last=net["channels_last"], encoder=net["encoder"],
            )  # fmt: skip
        self.objective = SelfSupervisedObjective(**objective, scales=net["scales"], pose_net=self.pose_net)
        self.scales = self.objective.scales
        self.val_metrics = DepthMetrics(tuple(hp["eval_cap"]))
        self.val_metrics_scaled = DepthMetrics(tuple(hp["eval_cap"]), median_scaling=True)
        self.guard = StepGuard(self)
        self.skipped_frames: list[str] = []

    @property
    def skipped_batches(self) -> int:
        """Training steps skipped so far (:class:`~fisheyedepth.training.StepGuard`)."""
        return self.guard.skipped

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike) -> FisheyeDepthModule:
        """A trained module from a Lightning checkpoint, read with ``weights_only=True``; a file that does
        not hold one raises :class:`~fisheyedepth.checkpoints.CheckpointError` naming it. Checkpoints
        whose hyper-parameters are flat (written before the option groups) load too."""
        return model_from_checkpoint(path, cls)

    def forward(
        self, image: Tensor, cameras: list, sources: Sources | None = None
    ) -> dict[str, dict[int, Tensor]]:
        return self.depth_net.for_cameras(image, cameras, sources=sources)

    def sources(self, batch: Batch, augmented: bool = False) -> Sources | None:
        """The batch's sources as the multi-view network reads them (real-scale poses); None for the
        monocular network."""
        return None if self.depth_net.cost_volume is None else Sources.of(batch, augmented)

    def transfer_batch_to_device(self, batch: Any, device: torch.device, dataloader_idx: int) -> Any:
        """Move tensors only: cameras are immutable values (frozen dataclasses) that live on no device."""
        if isinstance(batch, Batch | SkippedBatch):
            return batch.to(device)
        return super().transfer_batch_to_device(batch, device, dataloader_idx)

    # ------------------------------------------------------------------------------- steps
    def _count_skipped(self, batch: Batch | SkippedBatch) -> bool:
        """Record frames the dataset could not read (``skip_bad_frames``); True when nothing is left."""
        self.skipped_frames.extend(batch.skipped_frames)
        return isinstance(batch, SkippedBatch)

    def on_train_epoch_end(self) -> None:
        if self.skipped_frames:
            shown = "; ".join(self.skipped_frames[:3])
            warnings.warn(
                f"{len(self.skipped_frames)} frames skipped this epoch (skip_bad_frames): {shown}",
                stacklevel=1,
            )
            if self._trainer is not None:
                self.log("train/skipped_frames", float(len(self.skipped_frames)))
            self.skipped_frames.clear()

    def training_step(self, batch: Batch | SkippedBatch, batch_idx: int) -> Tensor:
        """A step that any rank cannot take is skipped by every rank together (:class:`StepGuard`): an
        unreadable batch before the forward pass, a non-finite loss after it, non-finite gradients in
        :meth:`on_before_optimizer_step`."""
        if self.guard.any_rank(self._count_skipped(batch)):
            if not isinstance(batch, SkippedBatch):
                self.guard.skipped += 1  # another rank could not read its batch
            return self.guard.skip_loss()
        self.guard.keep_statistics()
        outputs = self(batch.image_aug, batch.camera, self.sources(batch, augmented=True))
        loss, logs = self.objective(batch, outputs)
        if self.guard.any_rank(not bool(torch.isfinite(loss))):
            self.guard.skip("non-finite loss on a rank", batch_idx, len(batch))
            return self.guard.skip_loss()
        batch_size = len(batch)
        logs.pop("loss")
        self.log_dict({f"train/{k}": v.detach() for k, v in logs.items()}, batch_size=batch_size)
        self.log("train/loss", loss.detach(), prog_bar=True, batch_size=batch_size)
        self.log(
            "train/lr",
            self.trainer.optimizers[0].param_groups[0]["lr"] if self._trainer else 0.0,
            batch_size=batch_size,
        )
        every = self.hparams.log_images_every
        if every and self.global_step % every == 0:
            self.log_panel("train", batch, outputs["distance"][0])
        return loss

    def validation_step(self, batch: Batch | SkippedBatch, batch_idx: int) -> Tensor | None:
        if self._count_skipped(batch):
            return None
        outputs = self(batch.image, batch.camera, self.sources(batch))
        loss, logs = self.objective(batch, outputs)
        batch_size = len(batch)
        self.log("val/loss", loss, batch_size=batch_size, sync_dist=True)
        # the selection criterion: Monodepth2's automasked photometric error, comparable across epochs
        photometric = torch.stack([logs[f"automasked/{s}"] for s in self.scales]).mean()
        self.log("val/photometric", photometric, batch_size=batch_size, sync_dist=True)
        if self.pose_net is not None:
            errors = self.objective.pose_errors(batch)
            self.log_dict(
                {f"val/pose/{k}": v for k, v in errors.items()}, batch_size=batch_size, sync_dist=True
            )
        if batch.distance is not None:
            pred, gt = outputs["distance"][0], batch.distance
            valid = batch.mask > 0.5
            self.val_metrics.update(pred, gt, valid)
            self.val_metrics_scaled.update(pred, gt, valid)
        if batch_idx == 0:
            self.log_panel("val", batch, outputs["distance"][0])
        return loss

    def predict_step(
        self, batch: Batch | SkippedBatch, batch_idx: int, dataloader_idx: int = 0
    ) -> Tensor | None:
        if self._count_skipped(batch):
            return None
        return self.depth_net.distance(
            batch.image, batch.camera, self.hparams.input_size, self.sources(batch)
        )

    def on_validation_epoch_end(self) -> None:
        metrics, scaled = self.val_metrics, self.val_metrics_scaled
        if int(metrics.images) > 0:
            self.log_dict({f"val/{k}": v.float() for k, v in metrics.compute().items()})
            self.log_dict({f"val/scaled/{k}": v.float() for k, v in scaled.compute().items()})
        metrics.reset()
        scaled.reset()

    def on_fit_start(self) -> None:
        if self.hparams.compile_kernels:
            # the bin sums as channel reductions, which the compiler fuses (forward and backward)
            self.depth_net.expectation = torch.compile(
                functools.partial(bin_expectation, sums=bin_sums_reduced)
            )
            self.objective.reprojection.error_fn = torch.compile(photometric_error)

    def on_fit_end(self) -> None:
        self.depth_net.expectation = bin_expectation
        self.objective.reprojection.error_fn = photometric_error

    # ------------------------------------------------------------------------------- optimisation
    def on_before_optimizer_step(self, optimizer) -> None:
        self.guard.check_gradients()

    def configure_gradient_clipping(self, optimizer, gradient_clip_val=None, gradient_clip_algorithm=None):
        self.guard.clip(optimizer, gradient_clip_val, gradient_clip_algorithm)

    def configure_optimizers(self):
        scaler = self._trainer is not None and str(self.trainer.precision) in ("16-mixed", "16")
        optimizer = build_optimizer(self.hparams.optimizer, list(self.parameters()), scaler)
        scheduler = build_scheduler(self.hparams.scheduler, optimizer)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "epoch"}}

    # ------------------------------------------------------------------------------- pictures
    def log_panel(self, stage: str, batch: Batch, distance: Tensor) -> None:
        """Input | distance | GT | error of the first sample, through the logger or as a PNG in its folder."""
        if self._trainer is None or not self.trainer.is_global_zero:
            return
        gt = batch.distance[0] if batch.distance is not None else None
        net = self.hparams.net
        vmax = min(self.hparams.eval_cap[1], net["max_distance"])
        picture = panel(batch.image[0], distance[0], gt, net["min_distance"], vmax)
        tag, logger = f"{stage}/panel", self.logger
        if logger is not None and hasattr(logger, "log_image"):  # wandb
            logger.log_image(key=tag, images=[picture], step=self.global_step)
        elif logger is not None and hasattr(getattr(logger, "experiment", None), "add_image"):  # tensorboard
            logger.experiment.add_image(tag, picture, self.global_step, dataformats="HWC")
        else:
            folder = Path(
                logger.log_dir if logger is not None and logger.log_dir else self.trainer.default_root_dir
            )
            folder = folder / "images"
            folder.mkdir(parents=True, exist_ok=True)
            atomic_write_png(folder / f"{stage}_step{self.global_step:07d}.png", picture[..., ::-1])


def count_parameters(module: torch.nn.Module | None) -> int:
    return 0 if module is None else sum(p.numel() for p in module.parameters())


__all__ = ["FisheyeDepthModule", "count_parameters"]
