"""Monodepth2's PoseNet, for the ablation without real-scale poses: an encoder (a ResNet or
EfficientNet-Lite0) on two stacked frames and a small convolutional decoder predicting axis-angle and
translation (no metric scale)."""

from __future__ import annotations

import os

import torch
from torch import Tensor, nn

from ..geometry import axis_angle_to_matrix, invert_pose, make_pose
from .encoders import make_encoder
from .heads import at_least_float32

# Monodepth2's PoseNet outputs 0.01 x its raw values (radians, metres) while its depth head starts at
# 1 / (1/100 + (1/0.1 - 1/100) / 2) = 0.2 m: a first translation of about 1 mm against 0.2 m of depth.
MONODEPTH2_TRANSLATION_PER_DISTANCE = 0.01 / 0.2


class PoseDecoder(nn.Module):
    """Axis-angle (0.01 rad per raw unit, as Monodepth2) and translation (``translation_scale`` metres per
    raw unit) from the encoder's last feature map."""

    def __init__(self, in_ch: int, translation_scale: float = 0.01):
        super().__init__()
        self.translation_scale = float(translation_scale)
        self.squeeze = nn.Conv2d(in_ch, 256, 1)
        self.conv1 = nn.Conv2d(256, 256, 3, 1, 1)
        self.conv2 = nn.Conv2d(256, 256, 3, 1, 1)
        self.out = nn.Conv2d(256, 6, 1)
        self.relu = nn.ReLU()

    def forward(self, feature: Tensor) -> tuple[Tensor, Tensor]:
        x = self.relu(self.squeeze(feature))
        x = self.relu(self.conv1(x))
        x = self.relu(self.conv2(x))
        x = self.out(x).mean((2, 3))
        return 0.01 * x[:, :3], self.translation_scale * x[:, 3:]


class PoseNet(nn.Module):
    """``translation_scale``: metres per raw output unit. Monodepth2's 0.01 suits its depth head, which
    starts at 0.2 m; a head that starts at distance ``d`` needs ``d * MONODEPTH2_TRANSLATION_PER_DISTANCE``
    so that the first warps have the same parallax (see ``FisheyeDepthModule``).
    ``channels_last``: weights and input in NHWC memory order, as in ``DepthNet``. ``encoder``, ``resnet``
    and ``weights`` as in ``DepthNet``; ImageNet weights of the first convolution are tiled over the two
    images and halved."""

    def __init__(
        self,
        resnet: int = 18,
        weights: str | os.PathLike | None = None,
        translation_scale: float = 0.01,
        channels_last: bool = False,
        encoder: str = "resnet",
    ):
        super().__init__()
        self.encoder = make_encoder(encoder, 2, resnet, weights)
        self.decoder = PoseDecoder(self.encoder.channels[-1], translation_scale)
        self.channels_last = channels_last
        if channels_last:
            self.to(memory_format=torch.channels_last)

    def forward(self, target: Tensor, source: Tensor, source_is_earlier: bool) -> Tensor:
        """``[B, 4, 4]`` transform from the target camera to the source camera.

        As in Monodepth2, the frames are fed in temporal order and the result is inverted for an earlier
        source, so the network always sees forward motion.
        """
        pair = torch.cat((source, target) if source_is_earlier else (target, source), 1)
        if self.channels_last:
            pair = pair.contiguous(memory_format=torch.channels_last)
        axis_angle, translation = self.decoder(self.encoder(pair)[-1])
        with torch.autocast(pair.device.type, enabled=False):  # the pose in float32 under bf16 autocast
            T = make_pose(axis_angle_to_matrix(at_least_float32(axis_angle)), at_least_float32(translation))
            return invert_pose(T) if source_is_earlier else T
