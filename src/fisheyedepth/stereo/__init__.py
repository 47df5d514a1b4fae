"""Metric distance from geometry, untrained, for calibrated cameras of any model, through one matcher
interface (:mod:`.matchers`): :class:`SgbmMatcher` rectifies every pair on the sphere and matches it with
OpenCV's semi-global matcher (:mod:`.pipeline`: :mod:`.rectify`, :mod:`.match`, :mod:`.fill`,
:mod:`.mapback`, then :mod:`.fuse`), :class:`SweepMatcher` sweeps every partner at once over distance
hypotheses (:mod:`.sweep`). :class:`RigStereo` is the live API for a rig, one call per instant
(:mod:`.live`); the multi-view command's run over a recording is :mod:`.recording`."""

from .fuse import Fused, fuse
from .live import CameraResult, RigStereo
from .mapback import PixelMaps
from .match import SgbmParameters
from .matchers import MATCHERS, Matcher
from .pipeline import SgbmSettings, match_pair, rectify_pair
from .sgbm import SgbmMatcher
from .sweep import SweepMatcher, SweepResult, SweepSettings, View

__all__ = [
    "MATCHERS",
    "CameraResult",
    "Fused",
    "Matcher",
    "PixelMaps",
    "RigStereo",
    "SgbmMatcher",
    "SgbmParameters",
    "SgbmSettings",
    "SweepMatcher",
    "SweepResult",
    "SweepSettings",
    "View",
    "fuse",
    "match_pair",
    "rectify_pair",
]
