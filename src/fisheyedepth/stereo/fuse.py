"""One image's distance from every partner it was matched with (rig cameras and its own motion), fused.

Each partner's estimate at a pixel carries its precision: one grid pixel of disparity error moves the
distance by about ``step / parallax`` of itself (``sigma``). At each pixel the kept estimate with the
largest parallax is the anchor; the others agree with it where they differ by less than the two
``sigma`` together. The fused distance is the inverse-variance mean of the anchor and those that agree
(so where partners disagree, the larger parallax wins), and its confidence

    confidence = (partners that agree / partners that kept the pixel) / (1 + sigma_fused),

in (0, 1): near 1 for agreeing, precise partners (sigma_fused small), lower for a short baseline or a far
point, halved where half the partners contradict the anchor. The dense map takes the fused checked
distance where there is one, else the filled estimate of the partner with the largest parallax.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from .mapback import PixelMaps


class Fused(NamedTuple):
    distance: np.ndarray  # [H, W] float32 metres where some partner's checks keep the pixel, else 0
    dense: np.ndarray  # [H, W] float32 metres wherever some partner could match the pixel, else 0
    confidence: np.ndarray  # [H, W] float32 in [0, 1] of the kept distance (0 where none)
    agreeing: np.ndarray  # [H, W] uint8: partners whose kept estimate went into the distance


def fuse(maps: Sequence[PixelMaps]) -> Fused:
    """The partners' :class:`~.mapback.PixelMaps` of one image fused (module docstring)."""
    if not maps:
        raise ValueError("maps: nothing to fuse; an image needs at least one partner")
    distance = np.stack([m.distance for m in maps])  # [P, H, W]
    parallax = np.stack([m.parallax for m in maps])
    steps = np.array([m.step for m in maps], dtype=np.float32)[:, None, None]
    kept = distance > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma = np.where(kept & (parallax > 0), steps / parallax, np.inf)
    anchor = np.argmin(sigma, axis=0)[None]
    anchor_distance = np.take_along_axis(distance, anchor, 0)
    anchor_sigma = np.take_along_axis(sigma, anchor, 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        agree = kept & (np.abs(distance / anchor_distance - 1) <= sigma + anchor_sigma)
        weight = np.where(agree, 1 / sigma**2, 0)
        total = weight.sum(0)
        fused = np.where(total > 0, (weight * distance).sum(0) / total, 0)
        fused_sigma = np.where(total > 0, 1 / np.sqrt(total), np.inf)
        share = agree.sum(0) / np.maximum(kept.sum(0), 1)
    confidence = np.where(total > 0, share / (1 + fused_sigma), 0)

    dense = np.stack([m.dense for m in maps])
    dense_parallax = np.where(dense > 0, np.stack([m.dense_parallax for m in maps]) / steps, -1)
    best = np.take_along_axis(dense, np.argmax(dense_parallax, axis=0)[None], 0)[0]
    dense_out = np.where(fused > 0, fused, best)
    return Fused(
        fused.astype(np.float32), dense_out.astype(np.float32), confidence.astype(np.float32),
        agree.sum(0).astype(np.uint8),
    )  # fmt: skip
