"""A matching cost volume over metric distance: ManyDepth's (Watson et al., CVPR 2021) with fisheye warps
and real-scale relative poses.

For each target pixel p (ray r(p)) and distance hypothesis L_d (uniform in inverse distance), the point
``L_d r(p)`` lands in source s at ``F_s(T_{t->s} L_d r(p))``; the source's encoder features sampled there
are compared with the target's:

    C[d, p] = mean over the sources that see the point of  mean_c |f_t(p) - f_s(F_s(T L_d r(p)))|

The poses are metric (odometry, or a rig's extrinsics at one instant), so the volume is over metres: no
scale ambiguity to learn, and the rig's other cameras can be sources where nothing moves between them. A
hypothesis no source sees takes the pixel's mean over the hypotheses that are seen; one more channel
tells the decoder what fraction of hypotheses some source sees (0 everywhere: no sources, a single image).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor, nn

from ..cameras import CameraModel, RayCache
from ..geometry import sample, warp_to_source


class Sources(NamedTuple):
    """What the cost volume matches against: ``images [B, S, 3, H, W]`` at the target's size,
    ``poses [B, S, 4, 4]`` target-to-source (metres) and ``cameras``, one list of ``S`` per sample (at
    the images' size). ``S`` may be 0: the network then runs on the target alone."""

    images: Tensor
    poses: Tensor
    cameras: Sequence[Sequence[CameraModel]]

    @classmethod
    def of(cls, batch, augmented: bool = False) -> Sources:
        """A training batch's sources (:class:`~fisheyedepth.data.batch.Batch`): its real-scale poses, and
        its colour-jittered source images when ``augmented`` (what the network sees in training)."""
        return cls(batch.sources_aug if augmented else batch.sources, batch.poses, batch.source_camera)

    def resized(self, width: int, height: int) -> Sources:
        """The same sources with images area-resized to ``(width, height)`` and cameras alike."""
        b, s = self.images.shape[:2]
        images = self.images
        if s and tuple(images.shape[-2:]) != (height, width):
            flat = nn.functional.interpolate(images.flatten(0, 1), size=(height, width), mode="area")
            images = flat.reshape(b, s, 3, height, width)
        cameras = [[c.resize(width, height) for c in cams] for cams in self.cameras]
        return Sources(images, self.poses, cameras)


def inverse_distances(hypotheses: int, min_distance: float, max_distance: float) -> Tensor:
    """``[D]`` inverse distances from ``1 / min_distance`` to ``1 / max_distance`` in equal steps."""
    return torch.linspace(1 / min_distance, 1 / max_distance, hypotheses)


class CostVolume(nn.Module):
    """``forward(target [B, C, h, w], sources [B, S, C, h, w], poses, cameras, source_cameras)`` ->
    ``[B, D + 1, h, w]``: the feature matching cost of each of ``hypotheses`` distances (nearest first),
    and the fraction of them some source sees. Cameras are the feature maps' (resized to ``w x h``)."""

    def __init__(self, hypotheses: int = 32, min_distance: float = 0.5, max_distance: float = 80.0):
        super().__init__()
        if hypotheses < 2 or not 0 < min_distance < max_distance:
            raise ValueError(
                f"cost volume: hypotheses {hypotheses}, distances {min_distance}-{max_distance}; need at "
                "least 2 hypotheses and 0 < min_distance < max_distance"
            )
        self.hypotheses = hypotheses
        self.register_buffer(
            "inverse", inverse_distances(hypotheses, min_distance, max_distance), persistent=False
        )
        self.rays = RayCache()

    @property
    def channels(self) -> int:
        return self.hypotheses + 1

    def forward(
        self,
        target: Tensor,
        sources: Tensor,
        poses: Tensor,
        cameras: Sequence[CameraModel],
        source_cameras: Sequence[Sequence[CameraModel]],
    ) -> Tensor:
        batch, _, height, width = target.shape
        depth = self.hypotheses
        total = target.new_zeros(batch, depth, height, width)
        count = target.new_zeros(batch, depth, height, width)
        rays, has_ray = self.rays.batch(cameras, target.device, target.dtype)

        def each(x: Tensor) -> Tensor:  # [B, ...] -> [B * D, ...], hypotheses inner
            return x.unsqueeze(1).expand(batch, depth, *x.shape[1:]).reshape(batch * depth, *x.shape[1:])

        distance = (1 / self.inverse.to(target)).reshape(1, depth, 1, 1).expand(batch, -1, height, width)
        distance = distance.reshape(batch * depth, height, width)
        for j in range(sources.shape[1]):
            cams = [c[j] for c in source_cameras for _ in range(depth)]
            warp = warp_to_source(each(rays), each(has_ray), distance, each(poses[:, j]), cams)
            warped = sample(each(sources[:, j]), warp.grid).reshape(batch, depth, -1, height, width)
            cost = (warped - target[:, None]).abs().mean(2)
            seen = warp.valid.reshape(batch, depth, height, width).to(target.dtype)
            total = total + cost * seen
            count = count + seen
        seen = (count > 0).to(target.dtype)
        cost = total / count.clamp(min=1)
        fraction = seen.mean(1, keepdim=True)
        mean_seen = (cost * seen).sum(1, keepdim=True) / seen.sum(1, keepdim=True).clamp(min=1)
        cost = torch.where(seen > 0, cost, mean_seen.expand_as(cost))
        return torch.cat([cost, fraction], 1)


__all__ = ["CostVolume", "Sources", "inverse_distances"]
