"""Data: the synthetic fisheye world, dataset layouts (KITTI-360, robot rig), the dataset and DataModule."""

from .augment import Augment, PoseNoise, colour_jitter, flip_sample
from .batch import Batch, SkippedBatch, collate
from .datamodule import FisheyeDataModule
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
