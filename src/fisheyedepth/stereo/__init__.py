"""Metric distance from geometry: sweep stereo over calibrated cameras of any model, untrained."""

from .sweep import COSTS, StereoResult, SweepStereo, View, aggregate, census, hamming, winner, zncc_cost

__all__ = [
    "COSTS",
    "StereoResult",
    "SweepStereo",
    "View",
    "aggregate",
    "census",
    "hamming",
    "winner",
    "zncc_cost",
]
