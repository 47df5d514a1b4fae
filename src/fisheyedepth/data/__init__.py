"""Data: the synthetic fisheye world, dataset layouts (KITTI-360, robot rig), the dataset and DataModule."""

from .augment import Augment, PoseNoise, colour_jitter, flip_sample
from .batch import collate
from .datamodule import FisheyeDataModule
from .dataset import FisheyeDataset, ImageCache
from .layouts import CameraSpec, Kitti360Layout, RigLayout

__all__ = [
    "Augment",
    "PoseNoise",
    "CameraSpec",
    "FisheyeDataModule",
    "FisheyeDataset",
    "ImageCache",
    "Kitti360Layout",
    "RigLayout",
    "colour_jitter",
    "collate",
    "flip_sample",
]
