"""Networks: ResNet and EfficientNet-Lite0 encoders, the depth network with multi-channel or sigmoid heads,
and PoseNet."""

from .depth_net import DepthDecoder, DepthNet, depth_scale, distance_at_size, upsample_inverse
from .efficientnet import EfficientNetLiteEncoder
from .encoders import ENCODERS, make_encoder
from .heads import (
    MultiChannelHead,
    SigmoidHead,
    bin_expectation,
    bin_sums_conv,
    bin_sums_reduced,
    distance_bins,
    sigmoid_to_distance,
)
from .posenet import PoseNet
from .resnet import ResNetEncoder, WeightsError

__all__ = [
    "ENCODERS",
    "EfficientNetLiteEncoder",
    "DepthDecoder",
    "DepthNet",
    "MultiChannelHead",
    "PoseNet",
    "ResNetEncoder",
    "SigmoidHead",
    "WeightsError",
    "depth_scale",
    "distance_at_size",
    "distance_bins",
    "make_encoder",
    "bin_expectation",
    "bin_sums_conv",
    "bin_sums_reduced",
    "sigmoid_to_distance",
    "upsample_inverse",
]
