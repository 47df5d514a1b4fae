"""The training batch: what a sample holds, and the typed :class:`Batch` that ``collate`` builds.

A sample (what ``FisheyeDataset`` returns) is a dict:

| key | shape | meaning |
|---|---|---|
| ``image`` | ``[3, H, W]`` float in [0, 1] | target frame t, un-augmented (the photometric loss sees this) |
| ``image_aug`` | ``[3, H, W]`` | optional: the network's input (colour-jittered); defaults to ``image`` |
| ``sources`` | ``[S, 3, H, W]`` | source frames (t-1, t+1, ...), un-augmented |
| ``sources_aug`` | ``[S, 3, H, W]`` | optional: PoseNet's input; defaults to ``sources`` |
| ``poses`` | ``[S, 4, 4]`` float32 | real-scale ``T_target_to_source`` for each source |
| ``cam_to_body`` | ``[4, 4]`` float32 | optional: camera-to-body extrinsic ``E`` (``E M`` after a flip) |
| ``mask`` | ``[1, H, W]`` float | target body mask, 1 = usable pixel |
| ``source_mask`` | ``[S, 1, H, W]`` | optional: sources' body masks (default: ``mask``, same camera) |
| ``distance`` | ``[1, H, W]`` float | optional ground-truth distance in metres, 0 = unknown |
| ``distance_source`` | ``str`` | with ``distance``: "rendered", "lidar", "lidar_filtered" or "none" |
| ``moving`` | ``[1, H, W]`` float | optional, with ``distance``: 1 where the pixel sees a moving object |
| ``camera`` | a ``CameraModel`` | the target camera |
| ``source_camera`` | list of ``S`` cameras | optional: sources' cameras (default: ``camera``) |
| ``camera_name`` | ``str`` | optional: the rig's name for the target camera (e.g. ``image_02``) |
| ``frame`` | ``str`` | optional: ``<sequence>/<camera>/<frame key>``, to name the frame in reports |

``distance_source``: a dense rendered map, a projected LiDAR scan (every point, or occlusion-filtered),
or "none" (a frame without ground truth in a split that has it: all 0, no pixel scored).

``collate`` stacks samples into a :class:`Batch` with every optional part resolved, so the module reads
fields and never guesses. Cameras are Python values, not tensors: they stay lists, so one batch may mix
cameras and camera models.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch
from torch import Tensor

from ..cameras import CameraModel

REQUIRED = ("image", "sources", "poses", "mask", "camera")
OPTIONAL = (
    "image_aug",
    "sources_aug",
    "cam_to_body",
    "source_mask",
    "distance",
    "distance_source",
    "moving",
    "source_camera",
    "camera_name",
    "frame",
)


@dataclasses.dataclass
class Batch:
    """``B`` samples with ``S`` sources each, at one image size ``H x W``."""

    image: Tensor  # [B, 3, H, W] the target frames, un-augmented (the loss compares these)
    sources: Tensor  # [B, S, 3, H, W] source frames, un-augmented
    poses: Tensor  # [B, S, 4, 4] real-scale T_target_to_source (odometry or the synthetic world)
    mask: Tensor  # [B, 1, H, W] 1 = usable target pixel (body mask)
    camera: list[CameraModel]  # B target cameras
    image_aug: Tensor  # [B, 3, H, W] the network's input (colour-jittered, or image itself)
    sources_aug: Tensor  # [B, S, 3, H, W] the PoseNet's source input
    source_mask: Tensor  # [B, S, 1, H, W] the sources' body masks
    source_camera: list[list[CameraModel]]  # B lists of S source cameras
    cam_to_body: Tensor | None = None  # [B, 4, 4] camera-to-body extrinsics, when the layout has them
    distance: Tensor | None = None  # [B, 1, H, W] ground truth in metres (0 = unknown), when known
    moving: Tensor | None = None  # [B, 1, H, W] 1 = the ground truth is a moving object, when known
    skipped_frames: list[str] = dataclasses.field(default_factory=list)  # reasons, skip_bad_frames
    camera_name: list[str] | None = None  # B rig names of the target cameras, when the dataset gives them
    distance_source: list[str] | None = None  # B "rendered", "lidar", "lidar_filtered" or "none"
    frame: list[str] | None = None  # B "<sequence>/<camera>/<frame key>", when the dataset gives them

    def __len__(self) -> int:
        return len(self.camera)

    @property
    def n_sources(self) -> int:
        return self.sources.shape[1]

    def to(self, device: torch.device | str) -> Batch:
        """Tensors moved to ``device``; cameras are immutable values that live on no device."""
        moved = {
            f.name: getattr(self, f.name).to(device, non_blocking=True)
            for f in dataclasses.fields(self)
            if isinstance(getattr(self, f.name), Tensor)
        }
        return dataclasses.replace(self, **moved)


@dataclasses.dataclass
class SkippedBatch:
    """What ``collate`` returns when no sample of a batch could be read (``skip_bad_frames``)."""

    skipped_frames: list[str]

    def __len__(self) -> int:
        return 0

    def to(self, device: torch.device | str) -> SkippedBatch:
        return self


def collate(samples: list[dict[str, Any]]) -> Batch | SkippedBatch:
    """Stack samples into a :class:`Batch`, resolving every optional part.

    Samples the dataset could not build (``{"skipped": reason}``, with ``skip_bad_frames``) are left out
    and their reasons listed in ``skipped_frames``, so the training loop can count and report them.
    """
    skipped = [s["skipped"] for s in samples if "skipped" in s]
    samples = [s for s in samples if "skipped" not in s]
    if not samples:
        return SkippedBatch(skipped)
    keys = samples[0].keys()
    for i, s in enumerate(samples):
        if s.keys() != keys:
            raise ValueError(f"sample {i} has keys {sorted(s)}, sample 0 has {sorted(keys)}")
        missing = [k for k in REQUIRED if k not in s]
        if missing:
            raise ValueError(f"sample {i} lacks {', '.join(missing)}")
    unknown = sorted(set(keys) - set(REQUIRED) - set(OPTIONAL))
    if unknown:
        raise ValueError(f"samples have keys a batch does not know: {', '.join(unknown)}")

    def stack(key: str) -> Tensor:
        return torch.stack([s[key] for s in samples])

    image, sources, mask = stack("image"), stack("sources"), stack("mask")
    S = sources.shape[1]
    cameras = [s["camera"] for s in samples]
    return Batch(
        image=image,
        sources=sources,
        poses=stack("poses").float(),
        mask=mask,
        camera=cameras,
        image_aug=stack("image_aug") if "image_aug" in keys else image,
        sources_aug=stack("sources_aug") if "sources_aug" in keys else sources,
        source_mask=stack("source_mask")
        if "source_mask" in keys
        else mask[:, None].expand(-1, S, -1, -1, -1),
        source_camera=[list(s["source_camera"]) for s in samples]
        if "source_camera" in keys
        else [[c] * S for c in cameras],
        cam_to_body=stack("cam_to_body").float() if "cam_to_body" in keys else None,
        distance=stack("distance") if "distance" in keys else None,
        moving=stack("moving") if "moving" in keys else None,
        skipped_frames=skipped,
        camera_name=[str(s["camera_name"]) for s in samples] if "camera_name" in keys else None,
        distance_source=[str(s["distance_source"]) for s in samples] if "distance_source" in keys else None,
        frame=[str(s["frame"]) for s in samples] if "frame" in keys else None,
    )
