"""A synthetic fisheye world with exact ground truth, written in the KITTI-360 layout.

``generate(out, rig="kitti360", frames=200, size=256, seed=0)`` renders a street world seen by a moving
rig of calibrated fisheye cameras, with real-scale poses, Velodyne scans and the exact distance of every
pixel. ``ensure_dataset(root, ...)`` is the first-use variant for training: it reuses a finished dataset
rendered with the same parameters, renders into an absent or empty folder, and never replaces a folder
that this generator did not make. See docs/data-format.md for the layout.
"""

from .rig import RIGS, Rig, make_rig
from .world import World, make_trajectory, make_world
from .writer import (
    MARKER,
    DatasetMismatch,
    NotASyntheticDataset,
    Terminated,
    ensure_dataset,
    generate,
    is_complete,
    made_by_generator,
)

__all__ = [
    "MARKER",
    "RIGS",
    "DatasetMismatch",
    "NotASyntheticDataset",
    "Rig",
    "Terminated",
    "World",
    "ensure_dataset",
    "generate",
    "is_complete",
    "made_by_generator",
    "make_rig",
    "make_trajectory",
    "make_world",
]
