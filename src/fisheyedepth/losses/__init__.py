"""Self-supervised losses: photometric error (SSIM + L1), minimum reprojection with auto-masking, and
edge-aware smoothness."""

from .photometric import box_mean3, photometric_error, ssim
from .selfsup import (
    INVALID_WARP_ERROR,
    ReprojectionLoss,
    automasked_error,
    best_warp_error,
    edge_aware_smoothness,
    hint_loss,
    min_reprojection,
)

__all__ = [
    "INVALID_WARP_ERROR",
    "ReprojectionLoss",
    "automasked_error",
    "best_warp_error",
    "box_mean3",
    "edge_aware_smoothness",
    "hint_loss",
    "min_reprojection",
    "photometric_error",
    "ssim",
]
