"""The parameters of a synthetic dataset: the kind and range of each (``data.generate.*`` of a training
config, the flags of ``fisheyedepth-synthetic``), those ``synthetic.json`` records and a finished dataset
must match to be reused."""

from __future__ import annotations

from ..option_checks import SWITCH, Choice, Group, Kind, ListOf, Number
from .sensor import EFFECTS
from .traffic import DENSITY

# must match a finished dataset's synthetic.json (a key it lacks, from an older version, is not checked)
CHECKED = (
    "rig",
    "frames",
    "size",
    "seed",
    "supersample",
    "lane",
    "scene",
    "random_cameras",
    "traffic",
    "effects",
)
# parameters a street dataset with fixed cameras does not write into synthetic.json (its files stay those
# of the versions before them): a finished dataset without the key was rendered with this value
UNWRITTEN = {"scene": "street", "random_cameras": False, "traffic": 0, "effects": []}
# The kind and range of each switch and number of the generation (``data.generate.*`` of a training
# config, the flags of ``fisheyedepth-synthetic``; fisheyedepth.option_checks): checked before anything
# is rendered. ``worlds``: a mixed dataset's per-folder parameters, each of the same kinds.
_WORLD_OPTIONS: dict[str, Kind] = {
    "frames": Number(low=9, whole=True, note="3 per split"),
    "size": Number(low=16, whole=True),  # and a multiple of 8 (generate)
    "seed": Number(low=0, whole=True),
    "supersample": Number(low=1, whole=True),
    "workers": Number(low=0, whole=True),
    "lidar": SWITCH,
    "progress": SWITCH,
    "random_cameras": SWITCH,
    "traffic": DENSITY,
    "effects": ListOf(Choice(EFFECTS, note="each effect a switch, named alone"), single=True),
}
GENERATE_OPTIONS: dict[str, Kind] = _WORLD_OPTIONS | {"worlds": ListOf(Group(_WORLD_OPTIONS), optional=True)}
