"""One image's distance from every partner it was matched with (rig cameras and its own motion), fused by
evidence.

Each partner's estimate at a pixel carries its expected error: ``u`` grid pixels of disparity (one for
the matcher, plus the pixels its round trip missed by, plus the pixels of its pose its images leave
unexplained: the pair's epipolar residual) move the distance by ``sigma = u step / parallax`` of itself.
So a long baseline counts for more only where its pose is as good as the short one's.

First the partners are compared as wholes: two partners that keep enough pixels in common (a hundred, or
a thousandth of the image) and whose distances differ there by more than their expected errors allow on
the median (a rig whose extrinsics are off in scale, odometry ten times too long) disagree; the partner
that disagrees with the most others is left out and named, until none disagree (two that only disagree
with each other are both left out: nothing says which is right).

Then, at each pixel, two kept estimates agree where their log-ratio is within twice their combined
``sigma``. The estimate that the most others agree with is the anchor (ties: the smaller ``sigma``),
and its agreeing estimates are the group. Where every kept estimate is in the group, the pixel is kept;
where some are not, it is kept only if the group outnumbers them, or, one against one, if the group's
``sigma`` is a third of theirs or less; otherwise it is dropped. A group of one (no partner corroborates
it) is kept only where it resolves its distance: ``sigma`` of :data:`MAX_LONE_SIGMA` or less. The fused
distance is the inverse-variance mean of the group, and its confidence

    confidence = (1 - 2^-n) (n / kept) / (1 + sigma_fused / 0.05),

in (0, 1): ``n`` partners in the group out of ``kept`` that kept the pixel (one partner alone is half
as sure as two that agree), lowered where the fused estimate's expected error passes 5 %. The dense map
takes the fused checked distance where there is one; elsewhere the filled estimates, where those of
every partner that filled the pixel agree within their expected error (else nothing: a filled pixel has
no evidence of its own to settle a disagreement) and, where one partner alone filled it, where that
estimate resolves its distance as a lone kept one must.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from .mapback import PixelMaps

AGREE = 2.0  # combined sigmas two estimates may differ by, in log distance
CLEARLY_BETTER = 3.0  # how many times more precise one estimate must be to settle a one-to-one disagreement
MIN_SHARED = 100  # pixels two partners must keep in common to be compared as wholes (or a thousandth)
SIGMA_SCALE = 0.05  # the expected relative error at which confidence is halved
# An estimate no other partner corroborates is kept only where a pixel of disparity error moves it by an
# eighth or less (8 pixels of parallax or more): on the development street's time pairs, the lone
# estimates under that were off by 50-80 % on the mean, those above it by 8 %.
MAX_LONE_SIGMA = 0.125


class Fused(NamedTuple):
    distance: np.ndarray  # [H, W] float32 metres where the partners' evidence keeps the pixel, else 0
    dense: np.ndarray  # [H, W] float32 metres where the filled estimates agree, else 0
    confidence: np.ndarray  # [H, W] float32 in [0, 1] of the kept distance (0 where none)
    agreeing: np.ndarray  # [H, W] uint8: partners whose kept estimate went into the distance
    left_out: dict[int, str] = {}  # partner index -> why it was not fused (it disagrees with the others)


def sigmas(maps: Sequence[PixelMaps], dense: bool = False, at: np.ndarray | None = None) -> np.ndarray:
    """``[P, N]`` each partner's expected relative error where it has an estimate (``inf`` elsewhere), at
    the flat pixel indices ``at`` (None: every pixel, ``N = H W``)."""
    out = []
    for m in maps:
        parallax = m.dense_parallax if dense else m.parallax
        miss = 0 if (dense or m.roundtrip is None) else m.roundtrip
        parallax = parallax.reshape(-1) if at is None else parallax.reshape(-1)[at]
        if not np.isscalar(miss):
            miss = miss.reshape(-1) if at is None else miss.reshape(-1)[at]
        with np.errstate(divide="ignore", invalid="ignore"):
            sigma = (1 + miss + m.residual) * m.step / parallax
        out.append(np.where((parallax > 0) & np.isfinite(sigma), sigma, np.inf))
    return np.stack(out).astype(np.float32)


def combined(sigma_a: np.ndarray, sigma_b: np.ndarray) -> np.ndarray:
    """The expected error of the difference of two independent estimates: ``sqrt(a^2 + b^2)``."""
    return np.sqrt(sigma_a * sigma_a + sigma_b * sigma_b)


def disagreeing(distance: np.ndarray, sigma: np.ndarray, pixels: int | None = None) -> dict[int, str]:
    """The partners (``[P, ...]`` distances, 0 where none; their ``sigma``) left out because they
    disagree as wholes with the others (module docstring), with why. ``pixels``: the image's (None: the
    size of a partner's distances; give it where they hold only some of the image's pixels)."""
    P = len(distance)
    kept = distance > 0
    floor = max(MIN_SHARED, (distance[0].size if pixels is None else pixels) // 1000)
    apart: dict[tuple[int, int], float] = {}
    for i in range(P):
        for j in range(i + 1, P):
            both = kept[i] & kept[j]
            if int(both.sum()) < floor:
                continue
            log_ratio = np.log(distance[i][both] / distance[j][both])
            allowed = AGREE * np.median(combined(sigma[i][both], sigma[j][both]))
            if abs(float(np.median(log_ratio))) > allowed:
                apart[i, j] = float(np.exp(np.median(log_ratio)))
    out: dict[int, str] = {}
    while apart:
        count = np.zeros(P, int)
        for i, j in apart:
            count[i] += 1
            count[j] += 1
        worst = np.flatnonzero(count == count.max())
        for k in worst:
            rivals = [(j if i == k else i, ratio if i == k else 1 / ratio) for (i, j), ratio in apart.items()
                      if k in (i, j)]  # fmt: skip
            said = ", ".join(f"partner {j}: x{ratio:.3g}" for j, ratio in rivals)
            out[int(k)] = f"its distances disagree with the other partners' on the pixels both keep ({said})"
        apart = {pair: r for pair, r in apart.items() if not set(pair) & set(int(k) for k in worst)}
    return out


def fuse(maps: Sequence[PixelMaps], min_confidence: float = 0.0) -> Fused:
    """The partners' :class:`~.mapback.PixelMaps` of one image fused by evidence (module docstring); a
    kept pixel whose confidence is under ``min_confidence`` is dropped from the distance (the dense map
    keeps it). Computed on the pixels some partner keeps only."""
    if not maps:
        raise ValueError("maps: nothing to fuse; an image needs at least one partner")
    shape = maps[0].distance.shape
    at = np.flatnonzero(np.logical_or.reduce([m.distance.reshape(-1) > 0 for m in maps]))
    distance = np.stack([m.distance.reshape(-1)[at] for m in maps])  # [P, N]
    sigma = sigmas(maps, at=at)
    left_out = disagreeing(distance, sigma, int(np.prod(shape))) if len(maps) > 1 else {}
    for k in left_out:
        distance[k] = 0
        sigma[k] = np.inf
    kept = distance > 0
    log_d = np.log(np.where(kept, distance, 1))
    P = len(maps)
    agree = np.zeros((P, *kept.shape), bool)  # agree[i, j]: estimates i and j agree (both kept)
    for i in range(P):
        agree[i, i] = kept[i]
        for j in range(i + 1, P):
            with np.errstate(invalid="ignore"):  # inf - inf where neither has an estimate
                close = np.abs(log_d[i] - log_d[j]) <= AGREE * combined(sigma[i], sigma[j])
            agree[i, j] = agree[j, i] = close & kept[i] & kept[j]
    support = agree.sum(1)  # [P, N]: how many agree with each estimate (itself included)
    # the anchor: the most support, then the smallest sigma
    order = np.where(kept, support * 1e6 - np.minimum(sigma, 1e5), -np.inf)
    anchor = np.argmax(order, axis=0)[None]
    group = _row(agree, anchor)
    n_group = group.sum(0)
    n_kept = kept.sum(0)
    rivals = kept & ~group
    n_rivals = rivals.sum(0)
    best_group = np.where(group, sigma, np.inf).min(0)
    best_rival = np.where(rivals, sigma, np.inf).min(0)
    settled = (n_rivals == 0) | (n_group > n_rivals)
    settled |= (n_group == n_rivals) & (n_group == 1) & (best_group * CLEARLY_BETTER <= best_rival)
    settled &= n_group > 0
    settled &= (n_group > 1) | (best_group <= MAX_LONE_SIGMA)  # a lone estimate must resolve its distance
    with np.errstate(divide="ignore", invalid="ignore"):
        weight = np.where(group & settled, 1 / sigma**2, 0)
        total = weight.sum(0)
        fused = np.where(total > 0, (weight * distance).sum(0) / total, 0)
        fused_sigma = np.where(total > 0, 1 / np.sqrt(total), np.inf)
        n = np.where(total > 0, n_group, 0)
        share = n / np.maximum(n_kept, 1)
    confidence = np.where(total > 0, (1 - 0.5**n) * share / (1 + fused_sigma / SIGMA_SCALE), 0)
    kept_fused = fused  # the dense map takes every fused pixel, sure or not
    if min_confidence > 0:
        sure = confidence >= min_confidence
        fused, confidence, n = (np.where(sure, x, 0) for x in (fused, confidence, n))
    dense = _dense(maps, left_out)
    whole = [np.zeros(shape, dtype).reshape(-1) for dtype in (np.float32, np.float32, np.float32, np.uint8)]
    for image, values in zip(whole, (kept_fused, fused, confidence, n), strict=True):
        image[at] = values
    dense_out, fused, confidence, n = (x.reshape(shape) for x in whole)
    dense_out = np.where(dense_out > 0, dense_out, dense)
    return Fused(fused, dense_out.astype(np.float32), confidence, n, left_out)


def _row(agree: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """``[P, ...]``: the estimates that agree with the anchor (``[1, ...]`` partner index) at each pixel."""
    P = agree.shape[0]
    index = np.broadcast_to(anchor[None], (1, P, *anchor.shape[1:]))
    return np.take_along_axis(agree, index, 0)[0]


def _dense(maps: Sequence[PixelMaps], left_out: dict[int, str]) -> np.ndarray:
    """The filled estimates' inverse-variance mean where every partner that filled the pixel agrees
    with the most precise one, else 0 (``[H, W]``; computed on the pixels some partner filled)."""
    shape = maps[0].dense.shape
    used = [m for i, m in enumerate(maps) if i not in left_out]
    out = np.zeros(int(np.prod(shape)), np.float64)
    if not used:
        return out.reshape(shape)
    at = np.flatnonzero(np.logical_or.reduce([m.dense.reshape(-1) > 0 for m in used]))
    dense = np.stack([np.zeros(len(at), np.float32) if i in left_out else m.dense.reshape(-1)[at]
                      for i, m in enumerate(maps)])  # fmt: skip
    sigma = np.where(dense > 0, sigmas(maps, dense=True, at=at), np.inf)
    has = dense > 0
    best = np.argmin(sigma, axis=0)[None]
    best_d = np.take_along_axis(dense, best, 0)[0]
    best_s = np.take_along_axis(sigma, best, 0)[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        log_ratio = np.abs(np.log(np.where(has, dense, 1) / np.where(best_d > 0, best_d, 1)))
        agree = ~has | (log_ratio <= AGREE * combined(sigma, best_s))
        weight = np.where(has, 1 / sigma**2, 0)
        total = weight.sum(0)
        mean = np.where(total > 0, (weight * dense).sum(0) / total, 0)
    resolved = (has.sum(0) > 1) | (best_s <= MAX_LONE_SIGMA)  # a lone filled estimate must resolve too
    out[at] = np.where(agree.all(0) & (best_d > 0) & resolved, mean, 0)
    return out.reshape(shape)
