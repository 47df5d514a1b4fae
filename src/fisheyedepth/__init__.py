"""FisheyeDepth: real-scale self-supervised distance estimation for fisheye cameras."""

__version__ = "0.1.0"
