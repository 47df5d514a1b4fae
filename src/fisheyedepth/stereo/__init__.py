"""Metric distance from geometry, untrained, for calibrated cameras of any model: every pair rectified on
the sphere and matched by OpenCV's semi-global matcher (:mod:`.rectify`, :mod:`.match`, :mod:`.fill`,
:mod:`.mapback`, :mod:`.fuse`; :class:`.pipeline.RigStereo` for a live rig), or swept over distance
hypotheses (:mod:`.sweep`)."""

from .fuse import Fused, fuse
from .mapback import PixelMaps
from .match import MatcherSettings
from .pipeline import RigStereo, StereoSettings, match_pair, rectify_pair
from .rectify import Rectification, build_rectification, remap
from .sweep import COSTS, StereoResult, SweepStereo, View, aggregate, census, hamming, winner, zncc_cost

__all__ = [
    "COSTS",
    "Fused",
    "MatcherSettings",
    "PixelMaps",
    "Rectification",
    "RigStereo",
    "StereoResult",
    "StereoSettings",
    "SweepStereo",
    "View",
    "aggregate",
    "build_rectification",
    "census",
    "fuse",
    "hamming",
    "match_pair",
    "rectify_pair",
    "remap",
    "winner",
    "zncc_cost",
]
