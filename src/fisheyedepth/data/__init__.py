"""Data: dataset layouts (KITTI-360, robot rig), the dataset and DataModule (the synthetic world that renders
KITTI-360-layout datasets is :mod:`fisheyedepth.synthetic`).

``FisheyeDataModule`` is imported on first use: it needs Lightning (about 3 s to import), which a
process that only renders or reads data (the synthetic generator's worker processes, a converter) never
does."""

from .augment import Augment, PoseNoise, colour_jitter, flip_sample
from .batch import Batch, SkippedBatch, collate
from .dataset import FisheyeDataset, ImageCache
from .kitti360 import Kitti360Layout
from .layouts import CameraSpec, RigLayout

__all__ = [
    "Augment",
    "Batch",
    "PoseNoise",
    "CameraSpec",
    "FisheyeDataModule",
    "FisheyeDataset",
    "ImageCache",
    "Kitti360Layout",
    "RigLayout",
    "SkippedBatch",
    "colour_jitter",
    "collate",
    "flip_sample",
]


def __getattr__(name: str):
    if name == "FisheyeDataModule":
        from .datamodule import FisheyeDataModule

        return FisheyeDataModule
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
