"""A synthetic fisheye world with exact ground truth, written in the KITTI-360 layout.

``generate(out, WorldSpec(rig="kitti360", frames=200, size=256, seed=0))`` renders a street world seen by
a moving rig of calibrated fisheye cameras, with real-scale poses, Velodyne scans and the exact distance
of every pixel. ``ensure_dataset(root, spec)`` is the first-use variant for training: it reuses a
finished dataset rendered with the same spec, renders into an absent or empty folder, and never replaces
a folder that this generator did not make; ``ensure_datasets`` does it for each folder of a data config.
``WorldSpec(scene="indoor")`` renders a furnished room walked through by a hand-held rig instead of the
street, and ``random_cameras=True`` draws every camera (model family, intrinsics, mounting) from the
seed. See docs/data-format.md for the layout.

Modules: :mod:`.spec` (what a dataset is), :mod:`.world`, :mod:`.indoor`, :mod:`.traffic` and
:mod:`.rig` (the scenes, their motion and the cameras), :mod:`.raycast`, :mod:`.render`,
:mod:`.shading`, :mod:`.noise` and :mod:`.sensor` (rendering), :mod:`.scene` (the scene and trajectory of
a spec), :mod:`.frames` (a frame rendered and written), :mod:`.pool` (worker processes), :mod:`.layout`
(the files on disk), :mod:`.folder` (the temporary folder and which folders may be rendered into),
:mod:`.writer` (``generate``, ``ensure_dataset(s)``), :mod:`.cli` (``fisheyedepth-synthetic``).
"""

from .folder import MARKER, DatasetMismatch, NotASyntheticDataset, is_complete, made_by_generator
from .indoor import clearance, make_indoor_trajectory, make_indoor_world
from .layout import calibration_text
from .pool import Terminated
from .rig import FAMILIES, RIGS, Rig, camera_is_valid, make_rig, random_camera
from .scene import make_scene_trajectory, make_scene_world
from .spec import GENERATE_OPTIONS, WorldSpec
from .world import SCENES, World, make_trajectory, make_world
from .writer import ensure_dataset, ensure_datasets, generate

__all__ = [
    "FAMILIES",
    "GENERATE_OPTIONS",
    "MARKER",
    "RIGS",
    "SCENES",
    "DatasetMismatch",
    "NotASyntheticDataset",
    "Rig",
    "Terminated",
    "World",
    "WorldSpec",
    "calibration_text",
    "camera_is_valid",
    "clearance",
    "ensure_dataset",
    "ensure_datasets",
    "generate",
    "is_complete",
    "made_by_generator",
    "make_indoor_trajectory",
    "make_indoor_world",
    "make_rig",
    "make_scene_trajectory",
    "make_scene_world",
    "make_trajectory",
    "make_world",
    "random_camera",
]
