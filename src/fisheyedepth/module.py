"""``FisheyeDepthModule``: the LightningModule that trains a distance network with fisheye warps.

One switch per ablation of the paper's Table 2:
- ``fisheye_projection``: off -> every camera is replaced by the pinhole camera with its paraxial focal
  length and principal point (what Monodepth2 assumes) for both the rays and the reprojection;
- ``real_scale``: off -> relative poses come from a PoseNet instead of the batch (evaluate with median
  scaling);
- ``multi_channel``: off -> Monodepth2's single sigmoid channel instead of the binned head with attention.
"""

from __future__ import annotations

import dataclasses
import functools
import numbers
import os
import warnings
from pathlib import Path
from typing import Any

import cv2
import lightning as L
import torch
from torch import Tensor
from torch.nn import functional as F

from .cameras import CameraModel, RayCache, pinhole_like
from .cameras.pinhole import PINHOLE_FOCALS
from .checkpoints import CheckpointError, module_arguments, read_checkpoint, weights_mismatch
from .data.batch import Batch, SkippedBatch
from .geometry import (
    invert_pose,
    rotation_error_deg,
    sample,
    translation_direction_error_deg,
    warp_to_source,
)
from .losses import ReprojectionLoss, edge_aware_smoothness, min_reprojection
from .losses.photometric import photometric_error
from .metrics import DepthMetrics
from .models import DepthNet, PoseNet, bin_expectation, bin_sums_reduced
from .models.posenet import MONODEPTH2_TRANSLATION_PER_DISTANCE
from .viz import panel

LOSS_RESOLUTIONS = ("full", "native")
# Numeric hyper-parameters: a string (``model.lr=abc``) is refused by name, not deep in the optimiser
REALS = (
    *("lr", "weight_decay", "lr_gamma", "smoothness", "min_distance", "max_distance", "decoder_width"),
    "pose_translation_scale",
)
INTEGERS = ("resnet", "n_bins", "lr_step", "log_images_every", "rim_margin")
OPTIONAL = ("pose_translation_scale", "rim_margin")  # None: the default
LR_SCHEDULES = ("step", "cosine")


class FisheyeDepthModule(L.LightningModule):
    def __init__(
        self,
        *,
        resnet: int = 18,
        weights: str | None = None,
        fisheye_projection: bool = True,
        real_scale: bool = True,
        multi_channel: bool = True,
        n_bins: int = 64,
        attention: bool = True,
        min_distance: float = 0.5,
        max_distance: float = 150.0,
        base_focal: float | None = None,
        scales: tuple[int, ...] = (0, 1, 2, 3),
        source_offsets: tuple[int, ...] = (-1, 1),
        rig_offsets: tuple[int, ...] = (),
        automask: bool = True,
        smoothness: float = 1e-3,
        lr: float = 1e-4,
        weight_decay: float = 1e-5,
        lr_step: int = 8,
        lr_gamma: float = 0.1,
        eval_cap: tuple[float, float] = (1e-3, 80.0),
        log_images_every: int = 200,
        input_size: tuple[int, int] | None = None,
        pose_translation_scale: float | None = None,
        pinhole_focal: str = "paraxial",
        channels_last: bool = False,
        loss_resolution: str = "full",
        compile_kernels: bool = False,
        lr_schedule: str = "step",
        upsample: str = "distance",
        decoder_width: float = 1.0,
        rim_margin: int | None = None,
    ):
        """``smoothness``: weight of the smoothness term at scale 0 (divided by 2^s at scale s), one value
        for both heads (it acts on the same [0, 1] disparity), so that the ``multi_channel`` switch changes
        the head alone (the reference's 1e-5 for its binned head would be a second change).
        ``input_size``: the (width, height) the network was trained at, kept in checkpoints for inference.
        ``pinhole_focal``: with ``fisheye_projection`` off, the pinhole stand-in's focal length:
        "paraxial" (the fisheye's focal at the image centre) or "calibration" (Mei's gamma as stored).
        ``channels_last``: the networks' weights and inputs in NHWC order: the same numbers (tested), a
        speed lever for oneDNN convolutions that ``scripts/bench_training.py`` measures against NCHW.
        ``loss_resolution``: "full" (Monodepth2: every scale's distance upsampled and warped at the input
        size) or "native" (each scale warped at its own size: a speed lever, see ``_losses``).
        ``compile_kernels``: while fitting, the bin expectation (its bin sums as channel reductions, which
        the compiler fuses with their backward) and the photometric error run as ``torch.compile``'d
        kernels (fused, the same numbers; compiled once per process, about a minute on 2 CPU cores);
        evaluation after fitting, prediction and export use the plain functions.
        ``upsample``: how a distance at the training size reaches a larger image at evaluation and
        prediction: "distance" (bilinear in inverse distance, the reference's) or "logits" (the binned
        head's logits upsampled, then the expectation: sharper edges; the sigmoid head ignores it).
        ``decoder_width``: Monodepth2's decoder channels times this factor (1: the paper's network; 0.5
        with 32 bins: ``model=fisheyedepth_lite``, the robot variant of BENCHMARKS.md "Inference").
        ``rim_margin``: None (the paper's) or a number of pixels: a validity mask at the fisheye rim. The
        pixels within that margin (at the input size) of the image circle's edge (the camera's field of
        view) join the body masks: not scored in the target, not sampled in a source; at a coarser loss
        scale a pixel whose footprint touches them is dropped too, as at the body's edge (0: that alone).
        ``lr_schedule``: "step" (Monodepth2: x ``lr_gamma`` after ``lr_step`` epochs) or "cosine"
        (cosine annealing to ``lr * lr_gamma`` over the run's ``max_epochs``).
        ``rig_offsets``: the rig's other cameras are sources too, at these time offsets (cross-camera
        consistency, as in Full Surround Monodepth: 0 the same instant, +-1 the neighbouring frames); the
        extrinsics and odometry give their poses, so a PoseNet row cannot use them. The data module
        loads them after the ``source_offsets`` frames; the minimum reprojection treats every source alike.
        ``pose_translation_scale``: the PoseNet's metres per raw output unit; None keeps Monodepth2's
        ratio to the depth head's initial distance (0.01 m per 0.2 m), so the PoseNet starts with the
        parallax Monodepth2 starts with whatever the head (1 m for the sigmoid head, 26 m for the
        binned one at 0.5-150 m). Monodepth2's fixed 0.01 leaves the first warps 5x to 130x too short
        here, and the PoseNet rows learn only once the PoseNet has grown its output that much."""
        super().__init__()
        check_numbers(locals())
        if loss_resolution not in LOSS_RESOLUTIONS:
            raise ValueError(
                f"loss_resolution: {loss_resolution!r} is not one of {', '.join(LOSS_RESOLUTIONS)}"
            )
        if lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule: {lr_schedule!r} is not one of {', '.join(LR_SCHEDULES)}")
        if pinhole_focal not in PINHOLE_FOCALS:
            raise ValueError(f"pinhole_focal: {pinhole_focal!r} is not one of {', '.join(PINHOLE_FOCALS)}")
        if rig_offsets and not real_scale:
            raise ValueError(
                "rig_offsets: the other cameras' poses come from the extrinsics and odometry "
                "(real_scale=true); a PoseNet predicts one camera's own motion"
            )
        if rim_margin is not None and rim_margin < 0:
            raise ValueError(f"rim_margin: {rim_margin} pixels is negative (null switches the rim mask off)")
        self.save_hyperparameters()
        self.scales = tuple(scales)
        self.rim_margin = rim_margin
        self.source_offsets = tuple(source_offsets)
        self.depth_net = DepthNet(
            resnet,
            weights,
            multi_channel,
            n_bins,
            attention,
            min_distance,
            max_distance,
            self.scales,
            base_focal,
            channels_last,
            upsample,
            decoder_width,
        )
        if pose_translation_scale is None:  # Monodepth2's first parallax for this head's first distance
            pose_translation_scale = MONODEPTH2_TRANSLATION_PER_DISTANCE * self.depth_net.initial_distance
        self.pose_net = (
            None if real_scale else PoseNet(resnet, weights, pose_translation_scale, channels_last)
        )
        self.smoothness = smoothness
        self.reprojection = ReprojectionLoss(automask=automask)
        self.rays = RayCache()
        self.val_metrics = DepthMetrics(tuple(eval_cap))
        self.val_metrics_scaled = DepthMetrics(tuple(eval_cap), median_scaling=True)
        self.skipped_batches = 0
        self._saved_statistics: dict[str, Tensor] = {}
        self._dropping = False  # the step was skipped: drop its gradients before the optimiser
        self._grad_norm: Tensor | None = None  # this step's gradient norm, for the clipping
        self.skipped_frames: list[str] = []

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike) -> FisheyeDepthModule:
        """A trained module from a Lightning checkpoint, read with ``weights_only=True``; a file that does
        not hold one raises :class:`~fisheyedepth.checkpoints.CheckpointError` naming it."""
        ckpt = read_checkpoint(path)
        try:
            module = cls(**module_arguments(path, ckpt))
        except TypeError as exc:
            raise CheckpointError(
                path, f"hyper_parameters do not fit {cls.__name__} ({exc}); another project's checkpoint?"
            ) from None
        state = ckpt["state_dict"]
        if not isinstance(state, dict):
            raise CheckpointError(path, f"its state_dict is a {type(state).__name__}, not a dictionary")
        mismatch = weights_mismatch(module.state_dict(), state)
        if mismatch:
            raise CheckpointError(
                path, f"weights do not fit the model its hyper_parameters describe: {mismatch}"
            )
        try:
            module.load_state_dict(state)
        except (RuntimeError, TypeError, AttributeError) as exc:
            lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
            detail = "; ".join(lines[1:3] or lines[:1])
            raise CheckpointError(
                path, f"weights do not fit the model its hyper_parameters describe ({detail[:300]})"
            ) from None
        return module

    # ------------------------------------------------------------------------------- geometry
    def warp_model(self, camera: CameraModel) -> CameraModel:
        """The camera model the warp uses: the real one, or its pinhole stand-in when the switch is off."""
        if self.hparams.fisheye_projection:
            return camera
        return pinhole_like(camera, self.hparams.pinhole_focal)

    def forward(self, image: Tensor, cameras: list[CameraModel]) -> dict[str, dict[int, Tensor]]:
        return self.depth_net.for_cameras(image, cameras)

    def relative_poses(self, batch: Batch) -> Tensor:
        """``[B, S, 4, 4]`` target-to-source transforms: the batch's real-scale poses, or the PoseNet's.

        With the camera-to-body extrinsic in the batch, the PoseNet predicts the motion of the body
        (the vehicle), which every camera shares, and each camera's pose follows from its extrinsic:
        ``E^-1 T_body E``, exactly how the real-scale poses are made from odometry. A PoseNet that
        predicted each camera's own motion had to tell a left-looking from a right-looking camera
        before anything else, and learned one motion for both instead (reversed for one of them)."""
        if self.pose_net is None:
            return batch.poses.to(batch.image.dtype)
        target, sources = batch.image_aug, batch.sources_aug
        offsets = enumerate(self.source_offsets)
        poses = torch.stack([self.pose_net(target, sources[:, j], o < 0) for j, o in offsets], 1)
        if batch.cam_to_body is None:
            return poses
        with torch.autocast(poses.device.type, enabled=False):  # float32 products under bf16 autocast
            E = batch.cam_to_body.to(poses)[:, None]
            return invert_pose(E) @ poses @ E

    @torch.no_grad()
    def pose_errors(self, batch: Batch) -> dict[str, Tensor]:
        """The PoseNet against the batch's true relative poses (odometry, or the synthetic world's exact
        ones): mean rotation error and translation-direction error (degrees, scale-free), the fraction
        of translations pointing backwards, and the median ratio of predicted to true translation
        length (the PoseNet's drifting scale)."""
        predicted, true = self.relative_poses(batch).double(), batch.poses.double()
        moving = true[..., :3, 3].norm(dim=-1) > 1e-6
        ratio = predicted[..., :3, 3].norm(dim=-1)[moving] / true[..., :3, 3].norm(dim=-1)[moving]
        direction = translation_direction_error_deg(predicted[moving], true[moving])
        nan = torch.tensor(float("nan"))
        return {
            "rotation_deg": rotation_error_deg(predicted, true).mean().float(),
            "direction_deg": direction.mean().float() if direction.numel() else nan,
            # a PoseNet that learned one motion for cameras facing opposite ways is right for one and
            # reversed for the other: a mean direction error near 90 degrees, half of it reversed
            "reversed": (direction > 90).double().mean().float() if direction.numel() else nan,
            "scale": ratio.median().float() if ratio.numel() else nan,
        }

    def losses(self, batch: Batch, outputs: dict[str, dict[int, Tensor]]) -> tuple[Tensor, dict[str, Tensor]]:
        """The self-supervised loss, mean over scales, and its parts for logging. The warps and the loss
        run in the batch's precision (float32) even under bf16 autocast (``trainer.precision=bf16-mixed``
        speeds up the networks only); the PoseNet runs in the caller's precision."""
        poses = self.relative_poses(batch).to(batch.image.dtype)
        with torch.autocast(batch.image.device.type, enabled=False):
            outputs = {
                k: {s: v.to(batch.image.dtype) for s, v in maps.items()} for k, maps in outputs.items()
            }
            return self._losses(batch, outputs, poses)

    def _level(self, batch: Batch, size: tuple[int, int] | None) -> _Level:
        """The target, sources, rays and masks the loss compares at ``size`` (H, W; None: the input's)."""
        cameras = [self.warp_model(c) for c in batch.camera]
        source_cameras = [[self.warp_model(c) for c in cams] for cams in batch.source_camera]
        target, sources, body = batch.image, batch.sources, batch.mask[:, 0] > 0.5
        source_mask = batch.source_mask
        if self.rim_margin is not None:  # the rim of each image circle joins its body mask
            body, source_mask = self._without_rim(batch, body, source_mask)
        if size is not None and tuple(size) != tuple(target.shape[-2:]):
            h, w = size

            def shrink(x: Tensor) -> Tensor:  # [B, S, C, H, W] -> [B, S, C, h, w], area means
                return F.interpolate(x.flatten(0, 1), size=(h, w), mode="area").unflatten(0, x.shape[:2])

            target = F.interpolate(target, size=(h, w), mode="area")
            sources = shrink(sources)
            # a pixel that is partly vehicle body is not scored (target), nor sampled (sources)
            body = shrink(body[:, None, None].to(target.dtype))[:, 0, 0] > 1 - 1e-6
            source_mask = (shrink(source_mask.to(target.dtype)) > 1 - 1e-6).to(source_mask.dtype)
            cameras = [c.resize(w, h) for c in cameras]
            source_cameras = [[c.resize(w, h) for c in cams] for cams in source_cameras]
        rays, rays_valid = self.rays.batch(cameras, target.device, target.dtype)
        identity = self.reprojection.identity(sources, target)  # the same at every scale of this size
        return _Level(
            target, sources, source_mask, source_cameras, rays, rays_valid, body & rays_valid, identity
        )

    def _without_rim(self, batch: Batch, body: Tensor, source_mask: Tensor) -> tuple[Tensor, Tensor]:
        """``body`` ``[B, H, W]`` and ``source_mask`` ``[B, S, 1, H, W]`` without the pixels within
        ``rim_margin`` of the edge of their camera's field of view (the real cameras', not the warp's)."""
        margin, device = self.rim_margin, body.device
        body = body & self.rays.inside(batch.camera, margin, device)
        sources = [
            self.rays.inside([cams[j] for cams in batch.source_camera], margin, device)
            for j in range(source_mask.shape[1])
        ]
        source_mask = source_mask * torch.stack(sources, 1)[:, :, None].to(source_mask.dtype)
        return body, source_mask

    def _warp_sources(self, level: _Level, distance: Tensor, poses: Tensor) -> tuple[Tensor, Tensor]:
        """Every source of ``level`` sampled where ``distance`` and the ``[B, S, 4, 4]`` target-to-source
        ``poses`` put each target pixel: ``([B, S, 3, H, W] images, [B, S, H, W] warp validity)``."""
        warped, valid = [], []
        for j in range(level.sources.shape[1]):
            cams = [c[j] for c in level.source_cameras]
            warp = warp_to_source(
                level.rays, level.rays_valid, distance, poses[:, j], cams, level.source_mask[:, j]
            )
            warped.append(sample(level.sources[:, j], warp.grid))
            valid.append(warp.valid)
        return torch.stack(warped, 1), torch.stack(valid, 1)

    @torch.no_grad()
    def pixel_objective(
        self, batch: Batch, distance: Tensor, poses: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """The photometric objective per pixel for ``distance [B, H, W]`` at the input size, as a
        training step computes it at scale 0 (minimum reprojection, auto-masking as configured) but
        without its tie-breaking noise; ``poses`` default to :meth:`relative_poses`. Returns
        ``(error, used, usable)``, each ``[B, H, W]``: ``used``, the pixels whose error depends on
        ``distance``; ``usable``, those a training step averages over (body mask, a ray)."""
        level = self._level(batch, None)
        poses = self.relative_poses(batch) if poses is None else poses
        warped, valid = self._warp_sources(level, distance, poses.to(batch.image.dtype))
        errors = self.reprojection.photometric(warped, level.target)
        valid = valid & level.mask[:, None]
        error, used = min_reprojection(errors, valid, level.identity, self.reprojection.automask, noise=0.0)
        return error, used & level.mask, level.mask

    def _losses(
        self, batch: Batch, outputs: dict[str, dict[int, Tensor]], poses: Tensor
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """Monodepth2's full-resolution multi-scale loss (``loss_resolution="full"``): every scale's
        distance is upsampled to the input size and warped there. ``"native"`` compares each scale at its
        own size instead (downsampled images, resized cameras; Monodepth1's choice), a speed lever."""
        H, W = batch.image.shape[-2:]
        full = self._level(batch, None)
        native = self.hparams.loss_resolution == "native"
        logs: dict[str, Tensor] = {}
        total = batch.image.new_zeros(())
        for s in self.scales:
            distance = outputs["distance"][s]
            level = full
            if distance.shape[-2:] != (H, W):
                if native:
                    level = self._level(batch, tuple(distance.shape[-2:]))
                else:
                    distance = F.interpolate(distance, size=(H, W), mode="bilinear", align_corners=False)
            warped, valid = self._warp_sources(level, distance, poses)
            photo, used, measured = self.reprojection(
                level.target, warped, valid, level.identity, level.mask, not self.training
            )
            disp = outputs["disp"][s]
            image_s = level.target  # native resolution: already the target at this scale
            if image_s.shape[-2:] != disp.shape[-2:]:
                image_s = F.interpolate(batch.image, size=disp.shape[-2:], mode="area")
            smooth = edge_aware_smoothness(disp, image_s)
            total = total + photo + self.smoothness / 2**s * smooth
            logs[f"photometric/{s}"], logs[f"smoothness/{s}"], logs[f"used_pixels/{s}"] = photo, smooth, used
            if measured is not None:  # validation's criterion; not computed in the training step
                logs[f"automasked/{s}"] = measured
        total = total / len(self.scales)
        logs["loss"] = total
        return total, logs

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

    def _any_rank(self, flag: bool) -> bool:
        """``flag`` on any process of a distributed run (every rank must call this at the same point);
        the flag itself when there is one process."""
        if not (torch.distributed.is_available() and torch.distributed.is_initialized()):
            return flag
        if torch.distributed.get_world_size() == 1:
            return flag
        value = torch.tensor([1.0 if flag else 0.0], device=self.device)
        torch.distributed.all_reduce(value, op=torch.distributed.ReduceOp.MAX)
        return bool(value.item() > 0)

    def _skip_step(self, why: str, batch_idx: int, batch_size: int) -> None:
        """Every rank skips this step together: BatchNorm's running statistics go back to what they
        were before the forward pass, and the skip is counted and logged."""
        with torch.no_grad():
            for name, b in self.named_buffers():
                if name in self._saved_statistics:
                    b.copy_(self._saved_statistics[name])
        self.skipped_batches += 1
        warnings.warn(f"{why} at step {self.global_step} (batch {batch_idx}): step skipped", stacklevel=2)
        self.log("train/skipped_batches", float(self.skipped_batches), batch_size=max(batch_size, 1))

    def _skip_loss(self) -> Tensor:
        """What a skipped step returns: a zero loss on every parameter. Under DDP every rank must run
        the backward pass and its gradient all-reduce (Lightning refuses ``None`` there, and a rank
        left alone in a collective would wait forever); the zero gradients are then dropped before the
        optimiser (:meth:`on_before_optimizer_step`), so nothing moves, Adam's moments included."""
        self._dropping = True
        return sum(p.sum() for p in self.parameters()) * 0.0

    def training_step(self, batch: Batch | SkippedBatch, batch_idx: int) -> Tensor:
        """A step that any rank cannot take is skipped by every rank together: an unreadable batch
        before the forward pass, a non-finite loss after it, non-finite gradients in
        :meth:`on_before_optimizer_step`."""
        if self._any_rank(self._count_skipped(batch)):
            if not isinstance(batch, SkippedBatch):
                self.skipped_batches += 1  # another rank could not read its batch
            return self._skip_loss()
        # a non-finite batch must not poison BatchNorm's running statistics either: keep them to restore
        self._saved_statistics = {name: b.clone() for name, b in self.named_buffers() if "running_" in name}
        outputs = self(batch.image_aug, batch.camera)
        loss, logs = self.losses(batch, outputs)
        if self._any_rank(not bool(torch.isfinite(loss))):
            self._skip_step("non-finite loss on a rank", batch_idx, len(batch))
            return self._skip_loss()
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

    def _evaluate(
        self, batch: Batch | SkippedBatch, stage: str, metrics: DepthMetrics, scaled: DepthMetrics
    ) -> tuple[Tensor, dict[str, dict[int, Tensor]]] | None:
        if self._count_skipped(batch):
            return None
        outputs = self(batch.image, batch.camera)
        loss, logs = self.losses(batch, outputs)
        batch_size = len(batch)
        self.log(f"{stage}/loss", loss, batch_size=batch_size, sync_dist=True)
        # the selection criterion: Monodepth2's automasked photometric error, comparable across epochs
        photometric = torch.stack([logs[f"automasked/{s}"] for s in self.scales]).mean()
        self.log(f"{stage}/photometric", photometric, batch_size=batch_size, sync_dist=True)
        if self.pose_net is not None:
            self.log_dict(
                {f"{stage}/pose/{k}": v for k, v in self.pose_errors(batch).items()},
                batch_size=batch_size,
                sync_dist=True,
            )
        if batch.distance is not None:
            pred, gt = outputs["distance"][0], batch.distance
            valid = batch.mask > 0.5
            metrics.update(pred, gt, valid)
            scaled.update(pred, gt, valid)
        return loss, outputs

    def validation_step(self, batch: Batch | SkippedBatch, batch_idx: int) -> Tensor | None:
        result = self._evaluate(batch, "val", self.val_metrics, self.val_metrics_scaled)
        if result is None:
            return None
        loss, outputs = result
        if batch_idx == 0:
            self.log_panel("val", batch, outputs["distance"][0])
        return loss

    def predict_step(
        self, batch: Batch | SkippedBatch, batch_idx: int, dataloader_idx: int = 0
    ) -> Tensor | None:
        if self._count_skipped(batch):
            return None
        return self.depth_net.distance(batch.image, batch.camera, self.hparams.input_size)

    def _log_metrics(self, stage: str, metrics: DepthMetrics, scaled: DepthMetrics) -> None:
        if int(metrics.images) == 0:
            metrics.reset()
            scaled.reset()
            return
        self.log_dict({f"{stage}/{k}": v.float() for k, v in metrics.compute().items()})
        self.log_dict({f"{stage}/scaled/{k}": v.float() for k, v in scaled.compute().items()})
        metrics.reset()
        scaled.reset()

    def on_validation_epoch_end(self) -> None:
        self._log_metrics("val", self.val_metrics, self.val_metrics_scaled)

    def on_fit_start(self) -> None:
        if self.hparams.compile_kernels:
            # the bin sums as channel reductions, which the compiler fuses (forward and backward)
            self.depth_net.expectation = torch.compile(
                functools.partial(bin_expectation, sums=bin_sums_reduced)
            )
            self.reprojection.error_fn = torch.compile(photometric_error)

    def on_fit_end(self) -> None:
        self.depth_net.expectation = bin_expectation
        self.reprojection.error_fn = photometric_error

    # ------------------------------------------------------------------------------- optimisation
    def on_before_optimizer_step(self, optimizer) -> None:
        """Non-finite gradients after a finite loss: every rank drops them (a parameter without a
        gradient is left alone by the optimiser, its moments included) and restores BatchNorm. A step
        already skipped in :meth:`training_step` drops its zero gradients here."""
        if self._dropping:  # every rank agreed on it in training_step
            self._dropping = False
            for p in self.parameters():
                p.grad = None
            return
        grads = [p.grad for p in self.parameters() if p.grad is not None]
        # one norm over every gradient (foreach kernels, ~4x cheaper than a finiteness test per tensor):
        # non-finite when any element is, or when the sum of squares overflows float32 (no usable step);
        # gradient clipping reuses it
        self._grad_norm = torch.nn.utils.get_total_norm(grads) if grads else None
        finite = self._grad_norm is None or bool(torch.isfinite(self._grad_norm))  # one sync
        if self._any_rank(not finite):
            for p in self.parameters():
                p.grad = None
            self._skip_step("non-finite gradients on a rank", -1, 0)

    def configure_gradient_clipping(self, optimizer, gradient_clip_val=None, gradient_clip_algorithm=None):
        """``trainer.gradient_clip_val`` by the norm of every gradient (the one the non-finite test took in
        :meth:`on_before_optimizer_step`) or by value. Done here rather than by Lightning's precision
        plugin, which refuses to clip for a fused optimiser under any mixed precision: its gradients are
        already unscaled here (bf16 has no scaler; with float16's scaler the optimiser is not fused)."""
        norm, self._grad_norm = self._grad_norm, None
        if not gradient_clip_val:
            return
        params = [p for group in optimizer.param_groups for p in group["params"] if p.grad is not None]
        if not params:
            return  # a skipped step: its gradients were dropped
        if gradient_clip_algorithm in (None, "norm"):
            if norm is None:
                norm = torch.nn.utils.get_total_norm([p.grad for p in params])
            torch.nn.utils.clip_grads_with_norm_(params, gradient_clip_val, norm)
        elif gradient_clip_algorithm == "value":
            torch.nn.utils.clip_grad_value_(params, gradient_clip_val)
        else:
            raise ValueError(f"gradient_clip_algorithm={gradient_clip_algorithm!r}: expected norm or value")

    def configure_optimizers(self):
        params = list(self.parameters())
        # the fused kernel (one pass per step on CPU and CUDA; 3x faster than foreach on 2 CPU cores,
        # BENCHMARKS.md "Training loop") where every parameter lives on a device that has it, except
        # under float16 mixed precision, whose gradient scaler then unscales inside the step
        scaler = self._trainer is not None and str(self.trainer.precision) in ("16-mixed", "16")
        fused = not scaler and all(
            p.device.type in ("cpu", "cuda") and p.dtype.is_floating_point for p in params
        )
        optimizer = torch.optim.Adam(
            params, lr=self.hparams.lr, weight_decay=self.hparams.weight_decay, fused=fused or None
        )
        if self.hparams.lr_schedule == "cosine":
            epochs = max(1, self.trainer.max_epochs or 1)  # -1 or None: a run bounded by max_steps
            scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(
                optimizer, epochs, eta_min=self.hparams.lr * self.hparams.lr_gamma
            )
        else:
            scheduler = torch.optim.lr_scheduler.StepLR(
                optimizer, self.hparams.lr_step, self.hparams.lr_gamma
            )
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "epoch"}}

    # ------------------------------------------------------------------------------- pictures
    def log_panel(self, stage: str, batch: Batch, distance: Tensor) -> None:
        """Input | distance | GT | error of the first sample, through the logger or as a PNG in its folder."""
        if self._trainer is None or not self.trainer.is_global_zero:
            return
        gt = batch.distance[0] if batch.distance is not None else None
        vmax = min(self.hparams.eval_cap[1], self.hparams.max_distance)
        picture = panel(batch.image[0], distance[0], gt, self.hparams.min_distance, vmax)
        tag = f"{stage}/panel"
        logger = self.logger
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
            cv2.imwrite(str(folder / f"{stage}_step{self.global_step:07d}.png"), picture[..., ::-1])


@dataclasses.dataclass
class _Level:
    """What the loss compares at one image size: target ``[B, 3, h, w]``, sources ``[B, S, 3, h, w]``
    and their body masks ``[B, S, 1, h, w]``, the warp cameras at that size, rays ``[B, h, w, 3]`` and
    their validity, the scored pixels ``[B, h, w]`` (body mask and rays) and the unwarped sources'
    errors ``[B, S, h, w]``."""

    target: Tensor
    sources: Tensor
    source_mask: Tensor
    source_cameras: list[list[CameraModel]]
    rays: Tensor
    rays_valid: Tensor
    mask: Tensor
    identity: Tensor


def check_numbers(values: dict[str, Any]) -> None:
    """A ValueError naming the first of :data:`REALS` and :data:`INTEGERS` in ``values`` that is not a
    number (a whole one), None allowed for :data:`OPTIONAL`."""
    for name in (*REALS, *INTEGERS):
        value, kind = values[name], numbers.Integral if name in INTEGERS else numbers.Real
        if value is None and name in OPTIONAL:
            continue
        if isinstance(value, bool) or not isinstance(value, kind):
            raise ValueError(
                f"{name}: {value!r} is not a {'whole number' if kind is numbers.Integral else 'number'}"
            )


def count_parameters(module: torch.nn.Module | None) -> int:
    return 0 if module is None else sum(p.numel() for p in module.parameters())


__all__ = ["FisheyeDepthModule", "count_parameters"]
