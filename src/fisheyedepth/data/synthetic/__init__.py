"""A synthetic fisheye world with exact ground truth, written in the KITTI-360 layout.

``generate(out, rig="kitti360", frames=200, size=256, seed=0)`` renders a street world seen by a moving
rig of calibrated fisheye cameras, with real-scale poses, Velodyne scans and the exact distance of every
pixel. See docs/data-format.md for the layout.
"""

from .rig import RIGS, Rig, make_rig
from .world import World, make_trajectory, make_world
from .writer import generate, is_complete

__all__ = ["RIGS", "Rig", "World", "generate", "is_complete", "make_rig", "make_trajectory", "make_world"]
