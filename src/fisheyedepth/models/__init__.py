"""Networks: ResNet encoders, the depth network with multi-channel or sigmoid heads, and PoseNet."""

from .depth_net import DepthDecoder, DepthNet, upsample_inverse
from .heads import MultiChannelHead, SigmoidHead, distance_bins, gather_output, sigmoid_to_distance
from .posenet import PoseNet
from .resnet import ResNetEncoder, WeightsError

__all__ = [
    "DepthDecoder",
    "DepthNet",
    "MultiChannelHead",
    "PoseNet",
    "ResNetEncoder",
    "SigmoidHead",
    "WeightsError",
    "distance_bins",
    "gather_output",
    "sigmoid_to_distance",
    "upsample_inverse",
]
