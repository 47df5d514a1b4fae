"""Output heads: the paper's multi-channel head with channel attention, and Monodepth2's sigmoid head.

Both turn decoder features into a Euclidean distance map (metres along each pixel's ray) and a
disparity map normalised to [0, 1] (used by the smoothness loss and for display).
"""

from __future__ import annotations

import math
from contextlib import nullcontext

import torch
from torch import Tensor, nn
from torch.nn import functional as F


def conv3x3(in_ch: int, out_ch: int) -> nn.Sequential:
    """3x3 convolution with reflection padding (Monodepth2's ``Conv3x3``)."""
    return nn.Sequential(nn.ReflectionPad2d(1), nn.Conv2d(in_ch, out_ch, 3))


def distance_bins(n_bins: int, min_distance: float, max_distance: float) -> Tensor:
    """``n_bins`` log-spaced distances from ``min_distance`` to ``max_distance`` (metres)."""
    return torch.exp(torch.linspace(math.log(min_distance), math.log(max_distance), n_bins))


def at_least_float32(x: Tensor) -> Tensor:
    """``x`` in float32, or float64 if it is: what a bf16 network's output becomes before geometry."""
    return x.to(torch.promote_types(x.dtype, torch.float32))


def bin_sums_conv(weights: Tensor, bins: Tensor) -> Tensor:
    """``[B, K, H, W]`` bin weights -> ``[B, 2, H, W]``: ``sum_k w_k b_k`` and ``sum_k w_k`` as one 1x1
    convolution with two output channels (the fastest eager form; on CUDA without TF32)."""
    kernel = torch.stack((bins, torch.ones_like(bins))).to(weights)[:, :, None, None]
    # cuDNN would run the convolution in TF32 on Ampere and later
    exact = torch.backends.cudnn.flags(enabled=True, allow_tf32=False) if weights.is_cuda else nullcontext()
    with exact:
        return F.conv2d(weights, kernel)


def bin_sums_reduced(weights: Tensor, bins: Tensor) -> Tensor:
    """:func:`bin_sums_conv` as two sums over the channels: the form ``torch.compile`` fuses with the
    ``exp`` and its backward, where the convolution's backward is an external kernel 1.8x slower
    (BENCHMARKS.md, "Training step")."""
    b = bins.to(weights).reshape(1, -1, 1, 1)
    return torch.cat(((weights * b).sum(1, keepdim=True), weights.sum(1, keepdim=True)), 1)


def bin_expectation(
    logits: Tensor,
    depth_scale: Tensor | float,
    bins: Tensor,
    min_distance: float,
    max_distance: float,
    sums=bin_sums_conv,
) -> tuple[Tensor, Tensor]:
    """Multi-channel logits ``[B, K, H, W]`` -> (distance ``[B, 1, H, W]``, disparity ``[B, 1, H, W]``).

    distance = depth_scale * sum_k softmax(clamp(logits, -10, 10))_k * bin_k, a softmax expectation over
    ``K`` log-spaced bins; it is monotone in each logit's weight and lies in
    ``[min_distance, max_distance] * depth_scale``. The disparity is that of the unscaled expectation,
    ``(1/d - 1/max) / (1/min - 1/max)``, so it stays in [0, 1] for every camera. Computed in float32 (or
    float64) even under autocast: the logits of a bf16 network are cast up first.

    Fused: with the logits clamped to [-10, 10] no ``exp`` over- or underflows, so the softmax needs no
    max subtraction, and ``sum_k e^l_k b_k / sum_k e^l_k`` is one ``exp`` and one 1x1 convolution with
    two output channels (the bins and ones): no normalised probabilities, bin products or the layout
    copies a softmax over channels forces (a third of the whole network's time at 384x384 in
    channels_last, BENCHMARKS.md "Inference"). ``sums``: :func:`bin_sums_conv` (eager) or
    :func:`bin_sums_reduced` (the same numbers, for a ``torch.compile``'d kernel).
    """
    with torch.autocast(logits.device.type, enabled=False):
        logits = at_least_float32(logits)
        totals = sums(torch.exp(logits.clamp(-10.0, 10.0)), bins)  # [B, 2, H, W]
        d = totals[:, :1] / totals[:, 1:]
        disp = distance_to_sigmoid(d, min_distance, max_distance)
        scale = torch.as_tensor(depth_scale, dtype=d.dtype, device=d.device).reshape(-1, 1, 1, 1)
        return d * scale, disp


def sigmoid_to_distance(sigmoid: Tensor, min_distance: float, max_distance: float) -> Tensor:
    """Monodepth2's ``disp_to_depth``: inverse distance linear in the sigmoid between 1/max and 1/min."""
    inv = 1.0 / max_distance + (1.0 / min_distance - 1.0 / max_distance) * sigmoid
    return 1.0 / inv


def distance_to_sigmoid(distance: Tensor, min_distance: float, max_distance: float) -> Tensor:
    """The inverse of :func:`sigmoid_to_distance`: ``(1/d - 1/max) / (1/min - 1/max)``."""
    return (1.0 / distance - 1.0 / max_distance) / (1.0 / min_distance - 1.0 / max_distance)


class MultiChannelHead(nn.Module):
    """A_i = sigmoid(Conv_attn(X_i)); logits_i = Conv_disp,i(A_i * X_i) with K channels (the paper, III-C)."""

    def __init__(self, in_ch: int, n_bins: int = 64, attention: bool = True):
        super().__init__()
        self.attention = conv3x3(in_ch, in_ch) if attention else None
        self.logits = conv3x3(in_ch, n_bins)

    def forward(self, x: Tensor) -> Tensor:
        if self.attention is not None:
            x = torch.sigmoid(self.attention(x)) * x
        return self.logits(x)


class SigmoidHead(nn.Module):
    """Monodepth2's single sigmoid channel; its bias starts at ``logit(initial)``, so before training the
    head outputs ``initial`` on average (Monodepth2: 0.5)."""

    def __init__(self, in_ch: int, initial: float = 0.5):
        super().__init__()
        if not 0.0 < initial < 1.0:
            raise ValueError(f"SigmoidHead: initial must lie in (0, 1), got {initial}")
        self.conv = conv3x3(in_ch, 1)
        nn.init.constant_(self.conv[1].bias, math.log(initial / (1.0 - initial)))

    def forward(self, x: Tensor) -> Tensor:
        return torch.sigmoid(self.conv(x))
