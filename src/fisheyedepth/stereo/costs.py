"""The sweep's matching costs and its semi-global aggregation, on ``[B, 1, H, W]`` images and
``[B, D, H, W]`` cost volumes (:class:`.sweep.SweepMatcher`): ZNCC and census windows, Hirschmueller's path
costs, winner-take-all with a parabola and a confidence."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

COSTS = ("zncc", "census")


# ------------------------------------------------------------------ matching costs
def box_mean(x: Tensor, window: int) -> Tensor:
    """Mean over the ``window`` x ``window`` neighbourhood (the image's inside only, at its border): a row
    mean then a column mean, ``2 window`` additions per pixel instead of ``window**2``."""
    r = window // 2
    rows = F.avg_pool2d(x, (1, window), stride=1, padding=(0, r), count_include_pad=False)
    return F.avg_pool2d(rows, (window, 1), stride=1, padding=(r, 0), count_include_pad=False)


def window_stats(a: Tensor, window: int) -> tuple[Tensor, Tensor, Tensor]:
    """Per-pixel mean and variance of ``a`` over the window, and the image's largest variance (the scale
    of :func:`zncc_cost`'s regulariser): computed once for a reference compared with many warps."""
    mean = box_mean(a, window)
    var = (box_mean(a * a, window) - mean**2).clamp(min=0)
    return mean, var, var.amax(dim=(-2, -1), keepdim=True).clamp(min=1e-12)


def zncc_cost(
    a: Tensor, b: Tensor, window: int, stats_a: tuple[Tensor, Tensor, Tensor] | None = None, eps: float = 1e-4
) -> Tensor:
    """``(1 - ZNCC) / 2`` in [0, 1] of ``[B, 1, H, W]`` images over ``window`` x ``window``: 0 for
    windows equal up to gain and offset, 1 for inverted ones; flat windows score 0.5 (no evidence).
    ``stats_a``: :func:`window_stats` of ``a``, when already known."""
    mean_a, var_a, scale = window_stats(a, window) if stats_a is None else stats_a
    mean_b = box_mean(b, window)
    var_b = (box_mean(b * b, window) - mean_b**2).clamp(min=0)
    covariance = box_mean(a * b, window) - mean_a * mean_b
    ncc = covariance / torch.sqrt((var_a + eps * scale) * (var_b + eps * scale))
    return ((1 - ncc.clamp(-1, 1)) / 2)[:, 0]


def census(image: Tensor, window: int) -> Tensor:
    """``[B, window**2 - 1, H, W]`` bool: each neighbour brighter than the centre (the census transform)."""
    r = window // 2
    padded = F.pad(image, (r, r, r, r), mode="replicate")
    height, width = image.shape[-2:]
    bits = [
        padded[:, 0, dy : dy + height, dx : dx + width] > image[:, 0]
        for dy in range(window)
        for dx in range(window)
        if (dy, dx) != (r, r)
    ]
    return torch.stack(bits, 1)


def hamming(a: Tensor, b: Tensor) -> Tensor:
    """The fraction of census bits that differ, ``[B, H, W]`` in [0, 1]."""
    return (a != b).float().mean(1)


def census_cost(reference_bits: Tensor, images: Tensor, window: int) -> Tensor:
    """``hamming(reference_bits, census(image))`` for each of ``images [B, K, H, W]`` (``K`` warps compared
    with one reference's :func:`census` ``[B, window**2 - 1, H, W]``), ``[B, K, H, W]`` in [0, 1], without
    building the images' census: one neighbour at a time, the differing bits counted in uint8 (a tenth of
    the memory traffic of stacking the bits and averaging them as floats)."""
    r = window // 2
    height, width = images.shape[-2:]
    padded = F.pad(images, (r, r, r, r), mode="replicate")
    differ = torch.zeros(images.shape, dtype=torch.uint8, device=images.device)
    bit = 0
    for dy in range(window):
        for dx in range(window):
            if (dy, dx) == (r, r):
                continue
            brighter = padded[:, :, dy : dy + height, dx : dx + width] > images
            differ += brighter != reference_bits[:, bit : bit + 1]
            bit += 1
    return differ.float() / bit


# ------------------------------------------------------------------ semi-global aggregation
STRAIGHT = ((0, 1), (0, -1), (1, 0), (-1, 0))  # (dy, dx): along rows and columns, both ways
DIRECTIONS = {4: STRAIGHT, 8: (*STRAIGHT, (1, 1), (-1, -1), (1, -1), (-1, 1))}


def aggregate(volume: Tensor, p1: float, p2: float, paths: int = 4) -> Tensor:
    """The sum over ``paths`` directions of Hirschmueller's path costs ``L_r`` of ``volume [B, D, H, W]``
    (``paths=0``: the volume itself)."""
    if paths == 0:
        return volume
    return sum(path_cost(volume, dy, dx, p1, p2) for dy, dx in DIRECTIONS[paths])


def path_cost(volume: Tensor, dy: int, dx: int, p1: float, p2: float) -> Tensor:
    """``L_r`` along direction ``r = (dy, dx)``: one image line at a time, every line of the other axis and
    every hypothesis at once. A diagonal path walks the rows and takes its predecessor from the row
    before, shifted by one column. The walked axis is moved to the front, so each line is contiguous."""
    if dy == 0:  # horizontal: walk the columns
        return path_cost(volume.transpose(-1, -2), dx, 0, p1, p2).transpose(-1, -2)
    lines = volume.permute(2, 0, 1, 3).contiguous()  # [H, B, D, W]
    out = torch.empty_like(lines)
    rows = range(lines.shape[0]) if dy > 0 else range(lines.shape[0] - 1, -1, -1)
    previous = None
    for y in rows:
        cost = lines[y]  # [B, D, W]
        if previous is None:
            current = cost.clone()
        else:
            if dx:  # the predecessor of column x is column x - dx of the previous row
                previous = torch.roll(previous, shifts=dx, dims=-1)
                edge = slice(0, 1) if dx > 0 else slice(-1, None)
                previous[..., edge] = cost[..., edge]  # a path starts at the border
            best = previous.amin(1, keepdim=True)
            step = torch.minimum(previous, best + p2)  # stay, or jump anywhere
            step[:, :-1] = torch.minimum(step[:, :-1], previous[:, 1:] + p1)  # one hypothesis nearer
            step[:, 1:] = torch.minimum(step[:, 1:], previous[:, :-1] + p1)  # one farther
            current = cost + step - best
        out[y] = current
        previous = current
    return out.permute(1, 2, 0, 3)


def winner(aggregated: Tensor) -> tuple[Tensor, Tensor]:
    """Winner-take-all with a parabola through the winner and its two neighbours: ``[B, H, W]`` fractional
    hypothesis index, and the confidence ``1 - best / second best`` outside the winner's neighbours."""
    depth = aggregated.shape[1]
    best, index = aggregated.min(1)
    lower = aggregated.gather(1, (index - 1).clamp(min=0)[:, None])[:, 0]
    upper = aggregated.gather(1, (index + 1).clamp(max=depth - 1)[:, None])[:, 0]
    curvature = lower - 2 * best + upper
    offset = torch.where(curvature > 1e-12, (lower - upper) / (2 * curvature.clamp(min=1e-12)), 0 * best)
    inner = (index > 0) & (index < depth - 1)
    refined = index.to(aggregated.dtype) + torch.where(inner, offset.clamp(-0.5, 0.5), 0 * best)
    hypotheses = torch.arange(depth, device=aggregated.device).reshape(1, -1, 1, 1)
    near = (hypotheses - index[:, None]).abs() <= 1
    second = aggregated.masked_fill(near, float("inf")).amin(1)
    confidence = (1 - best / second.clamp(min=1e-12)).clamp(0, 1)
    return refined, confidence
