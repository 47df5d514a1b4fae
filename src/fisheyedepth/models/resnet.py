"""ResNet encoders (18, 34, 50) written here, with module names of torchvision's ResNet so that its
ImageNet state dicts load directly (torchvision itself cannot be installed next to lightning here).

``ResNetEncoder(depth, in_images=1, weights=None)`` returns the five feature maps Monodepth2 uses:
after conv1 (stride 2) and after layer1..layer4 (strides 4, 8, 16, 32).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import Tensor, nn

LAYERS = {18: ("basic", (2, 2, 2, 2)), 34: ("basic", (3, 4, 6, 3)), 50: ("bottleneck", (3, 4, 6, 3))}


class WeightsError(ValueError):
    """An ImageNet weights file does not fit the encoder; names the file and the key."""


def read_state_dict(path: str | os.PathLike) -> dict:
    """A state dict file read with ``weights_only=True``; a :class:`WeightsError` naming the file when it
    is unreadable or holds something else."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # unreadable, not a checkpoint, or refused by weights_only=True
        raise WeightsError(f"{path}: cannot read ImageNet weights ({exc})") from None
    if not isinstance(state, dict):
        raise WeightsError(f"{path}: expected a state dict, got {type(state).__name__}")
    return state


def tile_stem(state: dict, key: str, in_images: int) -> dict:
    """For ``in_images`` stacked input images, the first convolution's weights tiled and divided by their
    number (as Monodepth2 does for its pose encoder)."""
    if key in state and in_images > 1:
        state[key] = torch.cat([state[key]] * in_images, 1) / in_images
    return state


def load_checked(module: nn.Module, state: dict, path, name: str, expected: str) -> None:
    """``module.load_state_dict(state)`` after checking every key and shape; a :class:`WeightsError`
    names the file, the first key that does not fit, and ``name`` (the encoder) / ``expected``."""
    own = module.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    if missing or unexpected:
        key, what = (missing[0], "missing") if missing else (unexpected[0], "unexpected")
        raise WeightsError(
            f"{path}: key '{key}' {what} for {name} encoder "
            f"({len(missing)} missing, {len(unexpected)} unexpected); expected {expected}"
        )
    for key, value in state.items():
        if value.shape != own[key].shape:
            raise WeightsError(
                f"{path}: key '{key}' has shape {tuple(value.shape)}, {name} encoder needs "
                f"{tuple(own[key].shape)}"
            )
    module.load_state_dict(state)


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(self, inplanes: int, planes: int, stride: int = 1, downsample: nn.Module | None = None):
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(planes, planes, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.downsample = downsample

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        return self.relu(self.bn2(self.conv2(out)) + identity)


class Bottleneck(nn.Module):
    expansion = 4

    def __init__(self, inplanes: int, planes: int, stride: int = 1, downsample: nn.Module | None = None):
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride, 1, bias=False)  # stride on the 3x3 (ResNet v1.5)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, planes * 4, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(planes * 4)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        return self.relu(self.bn3(self.conv3(out)) + identity)


class ResNetEncoder(nn.Module):
    def __init__(self, depth: int = 18, in_images: int = 1, weights: str | os.PathLike | None = None):
        super().__init__()
        if depth not in LAYERS:
            raise ValueError(f"ResNet depth must be one of {sorted(LAYERS)}, got {depth}")
        kind, counts = LAYERS[depth]
        block = BasicBlock if kind == "basic" else Bottleneck
        self.depth, self.in_images = depth, in_images
        self.conv1 = nn.Conv2d(3 * in_images, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        self._inplanes = 64
        self.layer1 = self._layer(block, 64, counts[0], 1)
        self.layer2 = self._layer(block, 128, counts[1], 2)
        self.layer3 = self._layer(block, 256, counts[2], 2)
        self.layer4 = self._layer(block, 512, counts[3], 2)
        self.channels = [
            64,
            64 * block.expansion,
            128 * block.expansion,
            256 * block.expansion,
            512 * block.expansion,
        ]
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
        if weights is not None:
            self.load_imagenet(weights)

    def _layer(self, block, planes: int, blocks: int, stride: int) -> nn.Sequential:
        downsample = None
        if stride != 1 or self._inplanes != planes * block.expansion:
            downsample = nn.Sequential(
                nn.Conv2d(self._inplanes, planes * block.expansion, 1, stride, bias=False),
                nn.BatchNorm2d(planes * block.expansion),
            )
        layers = [block(self._inplanes, planes, stride, downsample)]
        self._inplanes = planes * block.expansion
        layers += [block(self._inplanes, planes) for _ in range(1, blocks)]
        return nn.Sequential(*layers)

    def load_imagenet(self, path: str | os.PathLike) -> None:
        """Load a torchvision ``resnet{depth}`` state dict (``fc.*`` ignored) with ``weights_only=True``.

        For several stacked input images the first convolution's weights are tiled and divided by their
        number (as Monodepth2 does for its pose encoder).
        """
        state = {k: v for k, v in read_state_dict(path).items() if not k.startswith("fc.")}
        load_checked(
            self, tile_stem(state, "conv1.weight", self.in_images), Path(path),
            f"a resnet{self.depth}", f"a torchvision resnet{self.depth} state dict",
        )  # fmt: skip

    def stage(self, k: int, x: Tensor) -> Tensor:
        """Feature map ``k`` (0..4, strides 2..32) from map ``k - 1`` (from the image for ``k = 0``): the
        encoder in steps, so that the multi-view network can join its cost volume after stage 1."""
        if k == 0:
            return self.relu(self.bn1(self.conv1((x - 0.45) / 0.225)))  # Monodepth2's input normalisation
        if k == 1:
            return self.layer1(self.maxpool(x))
        return (self.layer2, self.layer3, self.layer4)[k - 2](x)

    def forward(self, x: Tensor) -> list[Tensor]:
        features = []
        for k in range(5):
            x = self.stage(k, x)
            features.append(x)
        return features
