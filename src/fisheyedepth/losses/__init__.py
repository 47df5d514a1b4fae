"""Self-supervised losses: photometric error (SSIM + L1), minimum reprojection with auto-masking, and
edge-aware smoothness."""

from .photometric import box_mean3, photometric_error, ssim
from .selfsup import (
    INVALID_WARP_ERROR,
    ReprojectionLoss,
    automasked_error,
    edge_aware_smoothness,
    min_reprojection,
)

__all__ = [
    "INVALID_WARP_ERROR",
    "ReprojectionLoss",
    "automasked_error",
    "box_mean3",
    "edge_aware_smoothness",
    "min_reprojection",
    "photometric_error",
    "ssim",
]
