"""Self-supervised losses: photometric error (SSIM + L1), minimum reprojection with auto-masking, and
edge-aware smoothness."""

from .photometric import photometric_error, ssim
from .selfsup import ReprojectionLoss, edge_aware_smoothness, min_reprojection

__all__ = ["ReprojectionLoss", "edge_aware_smoothness", "min_reprojection", "photometric_error", "ssim"]
