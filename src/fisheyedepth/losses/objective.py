"""The self-supervised training objective: relative poses, fisheye warps per scale, minimum reprojection
with auto-masking, the rim mask and edge-aware smoothness, as one ``nn.Module``.

``objective(batch, outputs)`` returns the total loss and its parts; :meth:`pixel_objective` gives the
photometric error per pixel at scale 0. Two of the paper's Table 2 switches live here:
- ``fisheye_projection``: off -> every camera is replaced by the pinhole camera with its paraxial focal
  length and principal point (what Monodepth2 assumes) for both the rays and the reprojection;
- ``real_scale``: off -> relative poses come from a PoseNet instead of the batch (evaluate with median
  scaling).
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from ..cameras import CameraModel, RayCache, pinhole_like
from ..cameras.pinhole import PINHOLE_FOCALS
from ..data.batch import Batch
from ..geometry import (
    invert_pose,
    rotation_error_deg,
    sample,
    translation_direction_error_deg,
    warp_to_source,
)
from ..options.kinds import check_options
from ..options.tables import OBJECTIVE_OPTIONS
from .selfsup import ReprojectionLoss, edge_aware_smoothness, min_reprojection

LOSS_RESOLUTIONS = ("full", "native")


class SelfSupervisedObjective(nn.Module):
    """Monodepth2's multi-scale photometric loss through fisheye warps.

    ``scales``: the network's output scales the loss averages over.
    ``pinhole_focal``: with ``fisheye_projection`` off, the pinhole stand-in's focal length: "paraxial"
    (the fisheye's focal at the image centre) or "calibration" (Mei's gamma as stored).
    ``source_offsets``: the frames each target is warped from (the PoseNet is run once per offset).
    ``rig_offsets``: the rig's other cameras are sources too, at these time offsets (cross-camera
    consistency, as in Full Surround Monodepth: 0 the same instant, +-1 the neighbouring frames); the
    extrinsics and odometry give their poses, so a PoseNet row cannot use them. The data module loads
    them after the ``source_offsets`` frames; the minimum reprojection treats every source alike.
    ``rim_margin``: None (the paper's) or a number of pixels: a validity mask at the fisheye rim. The
    pixels within that margin (at the input size) of the image circle's edge (the camera's field of
    view) join the body masks: not scored in the target, not sampled in a source; at a coarser loss scale
    a pixel whose footprint touches them is dropped too, as at the body's edge (0: that alone).
    ``smoothness``: weight of the smoothness term at scale 0 (divided by 2^s at scale s), one value for
    both heads (it acts on the same [0, 1] disparity), so that the head switch changes the head alone.
    ``loss_resolution``: "full" (Monodepth2: every scale's distance upsampled and warped at the input
    size) or "native" (each scale warped at its own size: a speed lever).
    ``brightness``: "none" (the paper's), or "affine": each source's brightness matched to the target's
    (mean and spread per channel) before the photometric error, for cameras whose exposure and white
    balance change from frame to frame.
    ``outliers``: the fraction of each target's pixels with the largest error left out of the loss (0:
    none, the paper's): what no warp of a static world explains, moving objects first.
    ``truth_weight``: weight of a supervised term, the mean absolute log ratio of the predicted to the
    ground-truth distance over the pixels where the training batch has ground truth (a synthetic world's
    exact maps), per scale as the photometric term. 0 (the paper's): self-supervised only. With
    ``photometric_weight`` 0 as well it is the ceiling probe: what this network can learn from these
    images when told the truth at every pixel. Validation still logs the photometric criterion.
    ``photometric_weight``: the photometric and smoothness terms' weight in training (1: the paper's).
    ``pose_net``: the PoseNet of a ``real_scale=False`` objective. It is borrowed, not owned: its weights
    belong to the caller (a LightningModule optimises and saves them as ``pose_net.*``).
    """

    def __init__(
        self,
        *,
        scales: tuple[int, ...],
        fisheye_projection: bool,
        pinhole_focal: str,
        real_scale: bool,
        source_offsets: tuple[int, ...],
        rig_offsets: tuple[int, ...],
        automask: bool,
        rim_margin: int | None,
        smoothness: float,
        loss_resolution: str,
        brightness: str,
        outliers: float,
        truth_weight: float,
        photometric_weight: float,
        pose_net: nn.Module | None = None,
    ):
        check_options(locals(), OBJECTIVE_OPTIONS)  # its arguments: switches and numbers of their kind
        super().__init__()
        if loss_resolution not in LOSS_RESOLUTIONS:
            raise ValueError(
                f"loss_resolution: {loss_resolution!r} is not one of {', '.join(LOSS_RESOLUTIONS)}"
            )
        if pinhole_focal not in PINHOLE_FOCALS:
            raise ValueError(f"pinhole_focal: {pinhole_focal!r} is not one of {', '.join(PINHOLE_FOCALS)}")
        if rig_offsets and not real_scale:
            raise ValueError(
                "rig_offsets: the other cameras' poses come from the extrinsics and odometry "
                "(real_scale=true); a PoseNet predicts one camera's own motion"
            )
        if rim_margin is not None and rim_margin < 0:
            raise ValueError(f"rim_margin: {rim_margin} pixels is negative (null switches the rim mask off)")
        if truth_weight + photometric_weight == 0:  # each finite and >= 0 (the table)
            raise ValueError(
                f"truth_weight {truth_weight}, photometric_weight {photometric_weight}: the weights are "
                "not negative and one of them is positive"
            )
        if (pose_net is None) != real_scale:
            raise ValueError("pose_net: a PoseNet is needed without real_scale, and only then")
        self.scales, self.source_offsets = tuple(scales), tuple(source_offsets)
        self.fisheye_projection, self.pinhole_focal = fisheye_projection, pinhole_focal
        self.rim_margin, self.smoothness, self.loss_resolution = rim_margin, smoothness, loss_resolution
        self.truth_weight, self.photometric_weight = float(truth_weight), float(photometric_weight)
        object.__setattr__(self, "pose_net", pose_net)  # borrowed: not a submodule, see the docstring
        self.reprojection = ReprojectionLoss(automask=automask, brightness=brightness, trim=outliers)
        self.rays = RayCache()

    # ------------------------------------------------------------------------------- geometry
    def warp_model(self, camera: CameraModel) -> CameraModel:
        """The camera model the warp uses: the real one, or its pinhole stand-in when the switch is off."""
        return camera if self.fisheye_projection else pinhole_like(camera, self.pinhole_focal)

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

    # ------------------------------------------------------------------------------- the loss
    def forward(
        self, batch: Batch, outputs: dict[str, dict[int, Tensor]]
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """The self-supervised loss, mean over scales (with ``truth_weight``, plus the supervised term:
        ``truth`` in the parts), and its parts for logging. The warps and the loss
        run in the batch's precision (float32) even under bf16 autocast (``trainer.precision=bf16-mixed``
        speeds up the networks only); the PoseNet runs in the caller's precision. In eval mode the parts
        include ``automasked/<s>``, validation's criterion."""
        with torch.autocast(batch.image.device.type, enabled=False):
            outputs = {
                k: {s: v.to(batch.image.dtype) for s, v in maps.items()} for k, maps in outputs.items()
            }
            logs: dict[str, Tensor] = {}
            total = batch.image.new_zeros(())
            if self.photometric_weight > 0 or not self.training:
                poses = self.relative_poses(batch).to(batch.image.dtype)
                photometric, logs = self._losses(batch, outputs, poses)
                total = total + self.photometric_weight * photometric
            if self.truth_weight > 0 and (self.training or batch.distance is not None):
                truth = self.truth_loss(batch, outputs["distance"])
                total, logs["truth"] = total + self.truth_weight * truth, truth
            logs["loss"] = total
            return total, logs

    def truth_loss(self, batch: Batch, distances: dict[int, Tensor]) -> Tensor:
        """Mean over scales of the mean ``|log(predicted / true)|`` over the pixels with ground truth
        inside the body mask, each scale's distance upsampled to the ground truth's size."""
        if batch.distance is None:
            raise ValueError(
                "objective.truth_weight: this batch has no ground-truth distance; the training split "
                "needs it (data.datamodule.ground_truth_splits, a synthetic world)"
            )
        truth = batch.distance.to(batch.image.dtype)
        known = (truth > 0) & (batch.mask > 0.5)
        if not bool(known.any()):  # zero, but still a function of the network (a step can backpropagate)
            return distances[self.scales[0]].sum() * 0.0
        log_truth = truth.clamp_min(1e-6).log()
        terms = []
        for s in self.scales:
            d = distances[s]
            if d.shape[-2:] != truth.shape[-2:]:
                d = F.interpolate(d, size=truth.shape[-2:], mode="bilinear", align_corners=False)
            terms.append((d.clamp_min(1e-6).log() - log_truth).abs()[known].mean())
        return torch.stack(terms).mean()

    def _losses(
        self, batch: Batch, outputs: dict[str, dict[int, Tensor]], poses: Tensor
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """Monodepth2's full-resolution multi-scale loss (``loss_resolution="full"``): every scale's
        distance is upsampled to the input size and warped there. ``"native"`` compares each scale at its
        own size instead (downsampled images, resized cameras; Monodepth1's choice), a speed lever."""
        H, W = batch.image.shape[-2:]
        full = self.level(batch, None)
        native = self.loss_resolution == "native"
        logs: dict[str, Tensor] = {}
        total = batch.image.new_zeros(())
        for s in self.scales:
            distance = outputs["distance"][s]
            level = full
            if distance.shape[-2:] != (H, W):
                if native:
                    level = self.level(batch, tuple(distance.shape[-2:]))
                else:
                    distance = F.interpolate(distance, size=(H, W), mode="bilinear", align_corners=False)
            warped, valid = self.warp_sources(level, distance, poses)
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
        return total / len(self.scales), logs

    @torch.no_grad()
    def pixel_objective(
        self, batch: Batch, distance: Tensor, poses: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """The photometric objective per pixel for ``distance [B, H, W]`` at the input size, as a
        training step computes it at scale 0 (minimum reprojection, auto-masking as configured) but
        without its tie-breaking noise; ``poses`` default to :meth:`relative_poses`. Returns
        ``(error, used, usable)``, each ``[B, H, W]``: ``used``, the pixels whose error depends on
        ``distance``; ``usable``, those a training step averages over (body mask, a ray)."""
        level = self.level(batch, None)
        poses = self.relative_poses(batch) if poses is None else poses
        warped, valid = self.warp_sources(level, distance, poses.to(batch.image.dtype))
        valid = valid & level.mask[:, None]
        errors = self.reprojection.photometric(warped, level.target, valid)
        error, used = min_reprojection(errors, valid, level.identity, self.reprojection.automask, noise=0.0)
        return error, used & level.mask, level.mask

    # ------------------------------------------------------------------------------- pieces
    def level(self, batch: Batch, size: tuple[int, int] | None) -> Level:
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
        return Level(
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

    def warp_sources(self, level: Level, distance: Tensor, poses: Tensor) -> tuple[Tensor, Tensor]:
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


@dataclasses.dataclass
class Level:
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


__all__ = ["LOSS_RESOLUTIONS", "Level", "SelfSupervisedObjective"]
